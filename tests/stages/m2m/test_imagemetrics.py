"""FID/KID on cached InceptionV3 features agree with torchmetrics fed the images."""
import numpy as np
import pytest
import torch

from stages.imagemetrics import (INPUT_RANGE, _feature_module, fid, heatmaps_figure, inception_features,
                                 kid, preprocess, tsne)


N = 3          # images per set: InceptionV3 costs ~0.2 s an image on this CPU


@pytest.fixture(scope="module")
def sets(skins):
    a = skins["Array3"]["images"][:N]
    b = skins["Diamond3"]["images"][:N]
    return a, b, inception_features(np.concatenate([a, b]), batch=4)


def test_preprocess_range_and_shape():
    x = preprocess(np.array([[[0, 255], [255, 0]]], np.uint8))
    assert x.shape == (1, 3, 299, 299)
    assert float(x.min()) == INPUT_RANGE[0] == -1.0
    assert float(x.max()) == INPUT_RANGE[1] == 0.9921875      # 255/128 - 1, fid-helper's TF range
    with pytest.raises(ValueError, match="uint8"):
        preprocess(np.zeros((1, 8, 8), np.float32))


def test_features_are_batch_independent(sets):
    a, b, feats = sets
    assert feats.shape == (2 * N, 2048) and feats.dtype == np.float32
    np.testing.assert_allclose(inception_features(b[1:2], batch=1), feats[N + 1:N + 2], rtol=1e-4, atol=1e-5)


class Features(torch.nn.Module):
    """torchmetrics' custom feature extractor: the InceptionV3 module of stages.imagemetrics,
    evaluated once per image batch (the FID and KID metrics are fed the same tensors), and
    optionally only the first `dims` features: torchmetrics' FID takes an eigendecomposition
    of a D x D matrix, 20 s at D = 2048 on this CPU."""

    def __init__(self, dims=2048):
        super().__init__()
        self.net, self.num_features, self.memo = _feature_module(), dims, {}

    def forward(self, images):
        key = (images.data_ptr(), tuple(images.shape))
        if key not in self.memo:
            self.memo[key] = self.net(images)
        return self.memo[key][:, :self.num_features]


def test_cached_feature_scores_equal_torchmetrics_on_images(sets):
    from torchmetrics.image.fid import FrechetInceptionDistance
    from torchmetrics.image.kid import KernelInceptionDistance
    a, b, feats = sets
    real, fake = (torch.from_numpy(np.repeat(x[:, None], 3, axis=1)) for x in (b, a))
    full = Features()
    sliced = Features(64)
    sliced.memo = full.memo
    fid_tm = FrechetInceptionDistance(feature=sliced)
    kid_tm = KernelInceptionDistance(feature=full, subsets=5, subset_size=2)
    for metric in (fid_tm, kid_tm):
        metric.update(real, real=True)
        metric.update(fake, real=False)
    expected_fid = float(fid_tm.compute())
    with torch.random.fork_rng():
        torch.manual_seed(7)
        expected_kid = float(kid_tm.compute()[0])
    assert expected_fid > 1.0 and expected_kid > 0.01
    assert fid(feats[:N, :64], feats[N:, :64]) == pytest.approx(expected_fid, rel=1e-4)
    assert kid(feats[:N], feats[N:], subset_size=2, subsets=5, seed=7) == pytest.approx(expected_kid, rel=1e-4)


def test_fid_of_a_set_with_itself_is_zero(sets):
    _, _, feats = sets
    other = fid(feats[:N], feats[N:])
    assert other > 50                                   # two different marker patterns
    assert abs(fid(feats[:N], feats[:N])) < 1e-6 * other
    assert abs(fid(feats, feats)) < 1e-3


def test_fid_matches_the_eigenvalue_formula():
    from torchmetrics.image.fid import _compute_fid
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(30, 16)), rng.normal(0.3, 1.5, size=(20, 16))
    expected = _compute_fid(torch.tensor(x.mean(0)), torch.tensor(np.cov(x.T)),
                            torch.tensor(y.mean(0)), torch.tensor(np.cov(y.T)))
    assert fid(x, y) == pytest.approx(float(expected), rel=1e-5)
    with pytest.raises(ValueError, match="at least 2"):
        fid(x[:1], y)


def test_kid_subset_capped_and_exact_when_it_covers_both_sets():
    rng = np.random.default_rng(1)
    x, y = rng.normal(size=(10, 8)), rng.normal(0.5, 1.0, size=(10, 8))
    assert kid(x, y, subset_size=50, seed=0) == pytest.approx(kid(x, y, subset_size=10, subsets=1, seed=3), rel=1e-5)
    assert kid(x, y, subset_size=10) > kid(x, x + 1e-3, subset_size=10)


def test_tsne_and_heatmap_figure():
    rng = np.random.default_rng(2)
    pts = tsne(np.concatenate([rng.normal(0, 1, (10, 20)), rng.normal(8, 1, (10, 20))]))
    assert pts.shape == (20, 2)
    centre_a, centre_b = pts[:10].mean(0), pts[10:].mean(0)
    assert np.linalg.norm(centre_a - centre_b) > 3 * pts[:10].std(0).max()   # clusters kept apart
    m = np.array([[np.nan, 300.0], [120.0, np.nan]])
    fig = heatmaps_figure({"before": m, "m2m": m / 100}, ["A", "B"], "FID", log=True)
    assert len(fig.axes) == 3 and fig.axes[0].get_title() == "FID before (mean 210)"
