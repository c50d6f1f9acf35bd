"""The force regressor, material compensation, force metrics and the force nodes, on tiny
synthetic contact sequences (see conftest.blob_contacts)."""
import json

import numpy as np
import pytest
import torch
from sklearn.metrics import mean_absolute_error, r2_score

from stages.common import InputError
from stages.force import plus
from stages.force.compensation import Curves, compensate, curves_from_calibration, fit_curves, label_scale, loading_mask
from stages.force.data import contact_runs, predict_rows
from stages.force.figures import METHODS
from stages.force.fit import fit_own, fit_transfer
from stages.force.metrics import METRICS, force_metrics
from stages.force.model import (ForceRegressor, StreamingPredictor, from_arrays, load_model, load_predictor,
                                model_config, predict_contacts, predict_sequence, mirror_group, resolve_range,
                                to_arrays)
from stages.force.study import ablation_metrics, ablation_variants, check_splits, force_study
from stages.force.train import fit, make_sequences

from force_synthetic import contact_artifact

PNG = b"\x89PNG\r\n\x1a\n"
REF = np.zeros((32, 32), np.uint8)


@pytest.fixture(scope="module")
def trained(blobs, tiny_config):
    """A tiny regressor fitted on 24 synthetic contacts; 8 more held out."""
    images, forces = blobs(32, seed=1)
    seqs = make_sequences(images[:24], forces[:24], REF, tiny_config)
    model, history = fit(seqs, tiny_config, steps=300, batch_size=4, lr=0.1, seq_len=14, seed=0)
    model.set_reference(REF)
    return model, history, images[24:], forces[24:], forces[:24]


# ---------------------------------------------------------------------------- regressor

def test_tiny_regressor_learns_synthetic_sequences(trained):
    model, history, images, forces, train_forces = trained
    true = np.concatenate(forces)
    pred = predict_contacts(model, np.concatenate(images), np.repeat(np.arange(8), 14))
    mae = np.abs(pred - true).mean(0)
    baseline = np.abs(true - np.concatenate(train_forces).mean(0)).mean(0)   # predict the mean
    assert np.all(mae[:2] < 0.6 * baseline[:2]), (mae, baseline)
    assert mae[2] < 0.3 * baseline[2] and mae[2] < 0.7, (mae, baseline)
    assert np.mean(history["loss"][-30:]) < 0.5 * np.mean(history["loss"][:10])
    assert history["frames_per_s"] > 0 and history["clipped_fraction"] == 0.0


def test_streaming_matches_predict_sequence(trained):
    model, _, images, _, _ = trained
    seq = predict_sequence(model, images[0], REF)
    stream = StreamingPredictor(model)                      # the reference stored with the model
    steps = np.stack([stream.step(img) for img in images[0]])
    np.testing.assert_allclose(steps, seq, atol=1e-5)
    stream.reset()
    np.testing.assert_allclose(stream.step(images[0][0]), seq[0], atol=1e-5)
    assert seq.shape == (14, 3) and seq.dtype == np.float32


def test_predict_contacts_resets_state_per_contact(trained):
    model, _, images, _, _ = trained
    both = predict_contacts(model, np.concatenate(images[:2]), np.repeat([5, 9], 14), REF, batch=1)
    np.testing.assert_allclose(both[14:], predict_sequence(model, images[1], REF), atol=1e-5)
    # without a reset the second contact would start from the first one's state
    carried = predict_sequence(model, np.concatenate(images[:2]), REF)[14:]
    assert np.abs(carried - both[14:]).max() > 1e-4


def test_wrong_inputs_name_what_was_expected(trained):
    """The Python entry points refuse what they cannot read instead of casting it: float or
    negative images would otherwise become uint8 garbage, and a contact_id of the wrong
    length would silently give as many rows as it has."""
    model, _, images, _, _ = trained
    frames = np.concatenate(images[:2])
    bad = [(lambda: predict_sequence(model, frames / 255.0, REF),
            r"force model images: expected uint8 marker images \(0/255\), got float64"),
           (lambda: predict_sequence(model, frames.astype(np.int16) - 1, REF), r"values -1\.\.254 outside"),
           (lambda: predict_sequence(model, frames[:, None], REF),
            r"force model images: expected \(H,W\) or \(N,H,W\) marker images, got shape \(28, 1,"),
           (lambda: predict_contacts(model, frames, np.repeat([5, 9], 13), REF),
            r"contact_id \(26,\) must give one contact per frame of images \(28,"),
           (lambda: predict_contacts(model, frames, np.repeat([5, 9], 14)[None], REF), r"contact_id \(1, 28\)"),
           (lambda: StreamingPredictor(model).step(frames[0] / 255.0),
            r"StreamingPredictor.step image: expected uint8 marker images \(0/255\), got float64"),
           (lambda: StreamingPredictor(model).reset(np.stack([REF] * 3, -1)),
            r"StreamingPredictor reference: expected \(H,W\) marker images, got shape \(\d+, \d+, 3\)")]
    for call, message in bad:
        with pytest.raises(ValueError, match=message):
            call()
    np.testing.assert_array_equal(predict_sequence(model, frames > 127, REF),
                                  predict_sequence(model, np.where(frames > 127, 255, 0).astype(np.uint8), REF))


def test_arrays_round_trip_exact(trained):
    model, _, images, _, _ = trained
    arrays = to_arrays(model)
    again = from_arrays(arrays, model.config)
    for k, v in to_arrays(again).items():
        np.testing.assert_array_equal(v, arrays[k])
    np.testing.assert_array_equal(predict_sequence(again, images[0]), predict_sequence(model, images[0]))
    assert arrays["reference"].shape == (32, 32)
    with pytest.raises(KeyError, match="missing"):
        from_arrays({k: v for k, v in arrays.items() if k != "linear.bias"}, model.config)


def test_config_validation_and_label_clipping():
    with pytest.raises(KeyError, match="hiden"):
        model_config({"hiden": 4})
    with pytest.raises(ValueError, match="multiple of 16"):
        model_config({"input_size": 40})
    with pytest.raises(ValueError, match="input_mode"):
        model_config({"input_mode": "sum"})
    model = ForceRegressor({"input_mode": "stack"})
    y = model.normalise(np.array([[-5.0, 0.0, -20.0], [9.0, 2.5, 10.0]])).numpy()
    np.testing.assert_allclose(y, [[0.0, 0.5, 0.0], [1.0, 0.75, 1.0]])
    np.testing.assert_allclose(model.denormalise(torch.tensor([0.5, 0.5, 0.8])).numpy(), [0, 0, 0], atol=1e-6)
    assert model.encoder.stem[0].in_channels == 2


def test_auto_force_range_from_the_training_labels(blobs, tiny_config):
    force = np.array([[-1.0, 0.2, -10.0], [3.0, 0.2, 0.0]])
    cfg = resolve_range({"force_min": "auto", "force_max": "auto"}, force)
    np.testing.assert_allclose(cfg["force_min"], [-1.2, -0.3, -10.5])   # 5% of the span; a
    np.testing.assert_allclose(cfg["force_max"], [3.2, 0.7, 0.5])       # constant axis +-0.5 N
    assert resolve_range({"force_min": [-1, -1, -1], "force_max": [1, 1, 1]}, force)["force_max"] == [1, 1, 1]
    with pytest.raises(ValueError, match="or both 'auto'"):
        model_config({"force_min": "auto"})
    with pytest.raises(ValueError, match="set from the training labels"):
        ForceRegressor({"force_min": "auto", "force_max": "auto"})
    with pytest.raises(ValueError, match="not finite"):
        resolve_range({"force_min": "auto", "force_max": "auto"}, [[0.0, np.nan, 1.0]])
    images, forces = blobs(4, seed=5)
    auto = {**tiny_config, "force_min": "auto", "force_max": "auto"}
    model, _ = fit(make_sequences(images, forces, REF, auto), auto, steps=1, batch_size=2, lr=0.01)
    labels = np.concatenate(forces)
    span = labels.max(0) - labels.min(0)
    np.testing.assert_allclose(model.force_min.numpy(), labels.min(0) - 0.05 * span, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(model.config["force_max"], labels.max(0) + 0.05 * span, rtol=1e-4, atol=1e-5)
    assert model.normalise(labels).min() >= 0.04 and model.normalise(labels).max() <= 0.96


def _dot_grid(xs, ys, size=32):
    img = np.zeros((size, size), np.uint8)
    for y in ys:
        for x in xs:
            img[y - 1:y + 2, x - 1:x + 2] = 255
    return img


def test_mirror_group_of_a_reference():
    grid = _dot_grid([6, 13, 18, 25], [6, 13, 18, 25])          # symmetric about both centre lines
    assert mirror_group(grid, 16) == ("x", "y", "xy")
    assert mirror_group(_dot_grid([4, 11, 18, 25], [6, 13, 18, 25]), 16) == ("y",)   # shifted in x
    assert mirror_group(_dot_grid([4, 11, 18, 25], [3, 10, 17, 24]), 16) == ()
    assert mirror_group(np.zeros((32, 32), np.uint8), 16) == ()
    with pytest.raises(InputError, match="force model mirror_read must be one of auto, none, got 'both'"):
        model_config({"mirror_read": "both"})


def test_mirror_read_cancels_shear_a_symmetric_frame_cannot_carry(tiny_config):
    torch.manual_seed(3)
    ref = _dot_grid([6, 13, 18, 25], [6, 13, 18, 25])
    auto, none = (ForceRegressor({**tiny_config, "mirror_read": m}) for m in ("auto", "none"))
    none.load_state_dict(auto.state_dict())
    # a press at the centre spreads the dots evenly: no shear; one off centre in x shears
    images = np.stack([ref, _dot_grid([5, 12, 19, 26], [5, 12, 19, 26]), _dot_grid([8, 15, 20, 27], [6, 13, 18, 25])])
    cid = np.zeros(3, int)
    read, plain = (predict_contacts(m, images[:2], cid[:2], ref) for m in (auto, none))
    assert np.abs(plain[:, :2]).max() > 0.01                  # the untrained network reads shear anyway
    np.testing.assert_allclose(read[:, :2], 0.0, atol=1e-5)
    np.testing.assert_allclose(read[:, 2], plain[:, 2], atol=1e-5)   # Fz: the frame's own reading
    # the mirror image of a contact reads the same shear with Fx reversed, and streams as it predicts
    flipped = predict_contacts(auto, images[:, :, ::-1].copy(), cid, ref[:, ::-1].copy())
    np.testing.assert_allclose(flipped[:, :2], predict_contacts(auto, images, cid, ref)[:, :2] * [-1, 1], atol=1e-5)
    stream = StreamingPredictor(auto, ref)
    assert stream.mirrors == ("x", "y", "xy")
    np.testing.assert_allclose([stream.step(i) for i in images], predict_contacts(auto, images, cid, ref), atol=1e-5)
    assert StreamingPredictor(auto, np.zeros((32, 32), np.uint8)).mirrors == ()


# ---------------------------------------------------------------------------- compensation

def _calibration(scale, unload=0.8, n=20):
    """Force that is scale * (d^2 + 2 d) loading and unload x that unloading."""
    d = np.r_[np.linspace(0, 1, n), np.linspace(1, 0, n)]
    loading = np.r_[np.ones(n, bool), np.zeros(n, bool)]
    fz = -scale * (d * d + 2 * d) * np.where(loading, 1.0, unload)
    return d, np.c_[0.1 * fz, -0.05 * fz, fz], loading


def test_fit_curves_recovers_polynomials():
    curves = fit_curves(*_calibration(2.0))
    np.testing.assert_allclose(curves.loading, [2.0, 4.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(curves.unloading, [1.6, 3.2, 0.0], atol=1e-9)
    d, f, load = _calibration(2.0)
    f[load] = 0.0                                   # no force while loading: no calibration
    with pytest.raises(ValueError, match="loading curve is not positive"):
        fit_curves(d, f, load)


def test_identical_curves_are_the_identity_exactly():
    rng = np.random.default_rng(0)
    force = rng.normal(size=(50, 3)).astype(np.float32)
    depth, loading = rng.uniform(0, 1, 50), rng.random(50) < 0.5
    a, b = fit_curves(*_calibration(1.3)), fit_curves(*_calibration(1.3))   # fitted twice
    out = compensate(force, depth, loading, a, b)
    assert out.dtype == np.float32 and np.array_equal(out, force)
    np.testing.assert_array_equal(label_scale(depth, loading, a, b), np.ones(50))


def test_soft_to_hard_increases_and_hard_to_soft_decreases():
    soft, hard = fit_curves(*_calibration(1.0)), fit_curves(*_calibration(3.0))
    force = np.array([[0.5, -0.2, -4.0], [-1.0, 0.3, -8.0], [0.0, 0.0, -1.0]], np.float32)
    depth, loading = np.array([0.3, 0.9, 0.05]), np.array([True, True, False])
    up = compensate(force, depth, loading, soft, hard)
    down = compensate(force, depth, loading, hard, soft)
    np.testing.assert_allclose(up, 3.0 * force, rtol=1e-6)      # proportional curves: ratio 3
    np.testing.assert_allclose(down, force / 3.0, rtol=1e-6)
    assert np.all(np.abs(up[:, 2]) > np.abs(force[:, 2])) and np.all(np.abs(down[:, 2]) < np.abs(force[:, 2]))


def test_loading_and_unloading_curves_by_phase():
    source = Curves(loading=(0.0, 1.0, 0.0), unloading=(0.0, 0.5, 0.0))
    target = Curves(loading=(1.0, 1.0, 0.0), unloading=(0.0, 2.0, 0.0))
    phase = np.array([0, 1, 2, 3, 3, 0], np.int8)
    depth = np.array([0.5, 1.0, 0.0, 0.5, 0.0, 2.0])
    loading = loading_mask(phase)
    assert loading.tolist() == [True, True, True, False, False, True]
    # loading: (d + 1) / 1; unloading: 2 / 0.5 = 4 at every depth, also d = 0
    np.testing.assert_allclose(label_scale(depth, loading, source, target), [1.5, 2.0, 1.0, 4.0, 4.0, 3.0])
    force = np.tile([1.0, -1.0, -2.0], (6, 1))
    np.testing.assert_allclose(compensate(force, depth, loading, source, target)[:, 2],
                               [-3.0, -4.0, -2.0, -8.0, -8.0, -6.0])
    with pytest.raises(ValueError, match=r"\[5\]"):
        loading_mask([0, 5])


def test_curves_with_a_constant_term_divide_as_they_are():
    """The authors' coefficient files are plain np.poly1d coefficients (a constant term too):
    r = P_t(d) / P_s(d) where P_s is above eps, 1 below; a calibration that carries the
    coefficients gives them back as Curves."""
    source = Curves(loading=(1.0, 2.0, 0.5), unloading=(0.0, 1.0, -0.2))
    target = Curves(loading=(2.0, 0.0, 1.0), unloading=(0.0, 2.0, 0.0))
    depth = np.array([0.0, 0.5, 1.0, 0.1, 0.5])
    loading = np.array([True, True, True, False, False])
    # loading: (2 d^2 + 1) / (d^2 + 2 d + 0.5) = 2, 1.5 / 1.75, 3 / 3.5; unloading: P_s(0.1) < 0 -> 1,
    # 2 * 0.5 / 0.3
    np.testing.assert_allclose(label_scale(depth, loading, source, target),
                               [2.0, 1.5 / 1.75, 3.0 / 3.5, 1.0, 1.0 / 0.3], rtol=1e-12)
    cal = {"loading_coefficients": np.array([1.0, 2.0, 0.5]), "unloading_coefficients": [0.0, 1.0, -0.2]}
    assert curves_from_calibration(cal) == source
    assert Curves.from_dict(source.as_dict()) == source


# ---------------------------------------------------------------------------- metrics

def test_a_shear_leg_is_off_the_curves_and_gives_the_shear_ratio():
    """curves_from_calibration fits the press and release frames only; shear_ratio reads
    |(Fx, Fy)| / |Fz| where the leg reaches farthest."""
    from stages.force.compensation import shear_ratio
    d, f, load = _calibration(1.0)
    phase = np.where(load, 0, 3).astype(np.int8)
    plain = {"normalised_depth": d, "force": f, "phase": phase, "shift": np.zeros((d.size, 2))}
    k = int(np.argmax(d))                                  # the leg: 4 frames at the peak depth
    leg_f = np.array([[0.3, 0.4, -2.0], [0.6, 0.8, -2.0], [0.3, 0.4, -2.0], [0.0, 0.0, -2.0]])
    leg = {"normalised_depth": np.r_[d[:k + 1], np.full(4, d[k]), d[k + 1:]],
           "force": np.r_[f[:k + 1], leg_f, f[k + 1:]],
           "phase": np.r_[phase[:k + 1], [1, 1, 2, 2], phase[k + 1:]].astype(np.int8),
           "shift": np.r_[np.zeros((k + 1, 2)), [[0.5, 0], [1.0, 0], [0.5, 0], [0, 0]], np.zeros((d.size - k - 1, 2))]}
    assert curves_from_calibration(leg) == curves_from_calibration(plain)
    assert shear_ratio(leg) == pytest.approx(1.0 / 2.0)
    assert shear_ratio(plain) is None and shear_ratio({"loading_coefficients": [1, 0]}) is None
    unread = dict(leg, force=np.where(leg["phase"][:, None] == 1, leg["force"] * [0, 0, 1], leg["force"]))
    assert shear_ratio(unread) is None                     # a leg whose F/T read no shear


def test_shear_calibration_scales_the_shear_read_alone(trained):
    """genforce_plus's shear_calibration multiplies the model's shear by target / source
    shear-to-normal ratio and leaves Fz; without both ratios the model reads as it did."""
    model, _, images, _, _ = trained
    seq = images[0]
    before = predict_sequence(model, seq)
    scaled = plus.apply(model, plus.TargetView(REF, {"source": 0.5, "target": 0.2}), ["shear_calibration"])
    got, info = scaled
    assert info["shear_calibration"]["scale"] == pytest.approx(0.4) and info["shear_calibration"]["calibrated"]
    after = predict_sequence(got, seq)
    np.testing.assert_allclose(after[:, :2], 0.4 * before[:, :2], rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(after[:, 2], before[:, 2], rtol=1e-6)
    np.testing.assert_array_equal(predict_sequence(from_arrays(to_arrays(got), got.config), seq), after)
    same, info = plus.apply(model, plus.TargetView(REF, None), ["shear_calibration"])
    assert info["shear_calibration"] == {"scale": 1.0, "calibrated": False}
    np.testing.assert_array_equal(predict_sequence(same, seq), before)


def test_metrics_match_sklearn_and_hand_values():
    true = np.array([[0.0, 1.0, -1.0], [1.0, 1.0, -2.0], [2.0, 1.0, -3.0], [3.0, 1.0, -6.0]])
    pred = np.array([[0.5, 1.0, -1.0], [1.0, 1.5, -2.0], [2.0, 1.0, -4.0], [2.5, 1.0, -6.0]])
    m = force_metrics(pred, true)
    assert list(m) == [*METRICS, "mae_fz_light"]
    assert m["mae_fz_light"] == 0.0                            # light: the 1 N and 2 N frames
    assert m["mae_fx"] == pytest.approx(0.25) and m["mae_fy"] == pytest.approx(0.125)
    assert m["mae_fz"] == pytest.approx(0.25) and m["mae_total"] == pytest.approx(0.625 / 3)
    assert m["r2_fx"] == pytest.approx(1 - 0.5 / 5.0)          # SSres 0.5, SStot 5
    assert m["r2_fy"] == 0.0                                   # constant truth, imperfect
    assert m["r2_fz"] == pytest.approx(1 - 1.0 / 14.0)         # mean -3: SStot 4+1+0+9
    for k, axis in enumerate(("fx", "fy", "fz")):
        assert m[f"mae_{axis}"] == pytest.approx(mean_absolute_error(true[:, k], pred[:, k]))
        assert m[f"r2_{axis}"] == pytest.approx(r2_score(true[:, k], pred[:, k]))
    with pytest.raises(ValueError, match=r"\(N,3\)"):
        force_metrics(pred[:, :2], true[:, :2])
    # the light band (0.05, 2] N of true normal force: 0.04 N and 2.5 N frames are outside it
    true[:, 2], pred[:, 2] = [-0.04, -0.8, -2.0, -2.5], [-3.0, -1.1, -1.5, -9.0]
    assert force_metrics(pred, true)["mae_fz_light"] == pytest.approx((0.3 + 0.5) / 2)
    true[:, 2] = [-0.04, -0.8, -2.5, -3.0]                     # one light frame: no light MAE
    assert "mae_fz_light" not in force_metrics(pred, true)


# ---------------------------------------------------------------------------- nodes

NAMES = ["sphere", "prism", "cone", "torus"]


@pytest.fixture(scope="module")
def skins(blobs):
    """Two 'skins' sharing one synthetic physics; contact k pressed by NAMES[k % 4]."""
    images, forces = blobs(12, seed=3)
    a = contact_artifact(images, forces, [NAMES[k % 4] for k in range(12)])
    b = dict(a, images=255 - a["images"], reference=np.full((32, 32), 255, np.uint8))
    dim = dict(a, images=a["images"] // 2)          # A's frames as a dimmer camera shows them
    return {"A": a, "B": b, "A_dim": dim}


def _calibration_art(scale):
    d, f, load = _calibration(scale)
    return {"normalised_depth": d, "force": f, "loading": load}


def test_contact_runs_split_by_indenter(skins):
    runs = contact_runs(skins["A"], ["sphere", "cone"])
    assert runs == [(k * 14, k * 14 + 14) for k in (0, 2, 4, 6, 8, 10)]
    with pytest.raises(KeyError, match="tetrahedron"):
        contact_runs(skins["A"], ["tetrahedron"])


@pytest.fixture(scope="module")
def nodes_out(skins, tiny_config):
    kw = dict(config={**tiny_config, "seq_len": 10}, steps=4, batch_size=2, lr=0.05, seed=0)
    train = ["sphere", "prism"]                  # cone: validation, torus: test
    own = {s: fit_own(markers=skins[s], skin=s, train_indenters=train, **kw) for s in ("A", "B")}
    same = fit_transfer(translated=skins["B"], source_calibration=_calibration_art(1.0),
                        target_calibration=_calibration_art(1.0), source="A", target="B",
                        finetune_steps=2, train_indenters=train, **kw)
    stiffer = fit_transfer(translated=skins["A"], source_calibration=_calibration_art(1.0),
                           target_calibration=_calibration_art(2.0), source="B", target="A",
                           finetune_steps=0, train_indenters=train, target_markers=skins["A_dim"],
                           additions=list(plus.ADDITIONS), source_punch=_calibration_art(1.0),
                           target_punch=_calibration_art(3.0), **kw)
    return own, same, stiffer


def test_fit_own_outputs(nodes_out, skins):
    own, _, _ = nodes_out
    out = own["A"]
    assert out["attrs"]["config"]["input_size"] == 16 and out["attrs"]["train"]["seq_len"] == 10
    assert out["attrs"]["config"]["mirror_read"] == "none"                   # the plain regressor
    assert out["attrs"]["history"]["contacts"] == 6 and len(out["attrs"]["history"]["loss"]) == 4
    # timings go to the provenance (out of the digest), the rest of the history stays in attrs
    assert set(out["timing"]) == {"seconds", "samples_per_s", "frames_per_s"}
    assert out["timing"]["seconds"] > 0 and not set(out["attrs"]["history"]) & set(out["timing"])
    assert bytes(out["figures"]["loss"][:8]) == PNG
    model = load_model(out)
    assert np.array_equal(model.reference.numpy(), skins["A"]["reference"])
    json.dumps(out["attrs"])                                     # attrs are JSON-able

    class Stored(dict):
        """What a store hands over: flat 'group/name' datasets, nested attrs decoded."""
        attrs = json.loads(json.dumps({"config": out["attrs"]["config"]}))

    stored = Stored({f"weights/{k}": v for k, v in out["weights"].items()})
    assert out["weights"]["encoder.stem.1.num_batches_tracked"].shape == (1,)   # no 0-d datasets
    images = skins["A"]["images"][:14]
    np.testing.assert_array_equal(predict_sequence(load_model(stored), images),
                                  predict_sequence(model, images))
    np.testing.assert_array_equal(load_predictor(stored).step(images[3]),
                                  StreamingPredictor(model).step(images[3]))


def test_fit_transfer_identity_copies_genforce(nodes_out):
    _, same, stiffer = nodes_out
    assert same["attrs"]["compensation_identity"] is True
    for m in ("genforce_comp", "genforce_plus"):             # no additions: plus is comp is genforce
        assert set(same["genforce"]) == set(same[m])
        for k, v in same["genforce"].items():
            np.testing.assert_array_equal(v, same[m][k])
    assert same["attrs"]["plus"] == {"additions": []}
    assert "genforce_comp" not in same["attrs"]["history"]
    assert set(same["attrs"]["history"]["genforce"]) == {"pretrain", "finetune"}
    assert "seconds" not in same["attrs"]["history"]["genforce"]["finetune"]
    assert same["timing"]["genforce"]["finetune"]["seconds"] > 0
    assert stiffer["attrs"]["compensation_identity"] is False
    assert stiffer["attrs"]["label_scale"]["min"] == pytest.approx(2.0)
    assert any(not np.array_equal(v, stiffer["genforce_comp"][k]) for k, v in stiffer["genforce"].items())
    assert bytes(stiffer["figures"]["compensation"][:8]) == PNG
    json.dumps(stiffer["attrs"])


def test_genforce_plus_is_genforce_comp_with_each_addition_applied(nodes_out, skins):
    """genforce_plus's stored weights are plus.apply of genforce_comp on the target's view, bit
    for bit; each addition leaves its mark: the mirror read in the config, the shear range
    scaled by the calibrations' ratios and the whole range by the punch calibrations' (the
    prism's curves are 2x, the punch's 3x: 1.5); the encoder's weights and batch norms are
    genforce_comp's."""
    _, _, stiffer = nodes_out
    info = stiffer["attrs"]["plus"]
    assert info["additions"] == list(plus.ADDITIONS) == ["mirror_shear", "shear_calibration", "punch_calibration"]
    assert stiffer["attrs"]["punch_scale"] == pytest.approx(1.5, rel=1e-9)
    assert info["punch_calibration"] == {"scale": 1.5, "calibrated": True}
    # nothing is retrained: genforce_plus has no training history of its own
    assert set(stiffer) >= {"genforce", "genforce_comp", "genforce_plus"} and "plus_base" not in stiffer
    assert "genforce_plus" not in stiffer["attrs"]["history"]
    comp, got = load_model(stiffer, "genforce_comp"), load_model(stiffer, "genforce_plus")
    assert comp.config["mirror_read"] == "none" and got.config["mirror_read"] == "auto"
    assert info["mirror_shear"] == {"mirrors": []}              # a blank reference has no pattern to mirror
    ratios = stiffer["attrs"]["shear_ratios"]
    if ratios is None:
        assert info["shear_calibration"] == {"scale": 1.0, "calibrated": False}
        scale = 1.0
    else:
        scale = ratios["target"] / ratios["source"]
        assert info["shear_calibration"]["scale"] == pytest.approx(scale, rel=1e-5)
    np.testing.assert_allclose(got.config["force_min"][:2], np.multiply(comp.config["force_min"][:2], 1.5 * scale),
                               rtol=1e-5)
    assert got.config["force_min"][2] == pytest.approx(1.5 * comp.config["force_min"][2], rel=1e-5)
    assert got.config["force_max"][2] == pytest.approx(1.5 * comp.config["force_max"][2], rel=1e-5)
    assert torch.equal(got.encoder.stem[1].running_mean, comp.encoder.stem[1].running_mean)
    again, again_info = plus.apply(comp, plus.target_view(skins["A_dim"], ratios, punch_scale=1.5), plus.ADDITIONS)
    for k, v in to_arrays(again).items():
        np.testing.assert_array_equal(v, stiffer["genforce_plus"][k], err_msg=k)
    assert again_info == {k: v for k, v in info.items() if k != "additions"}
    with pytest.raises(InputError, match=r"plus.additions \['ensemble'\] are not among"):
        plus.check_additions(["ensemble"], "t")
    with pytest.raises(InputError, match="names one twice"):
        plus.check_additions(["mirror_shear", "mirror_shear"], "t")
    with pytest.raises(ValueError, match=r"genforce_plus needs the target's own collection \(target_markers\)"):
        plus.target_view({"images": skins["A"]["images"]})


def test_punch_scale_is_the_least_squares_factor_between_the_two_compensations():
    """Prism curves 2x (target over source) at every depth; punch curves d^2 + 2d against
    2 (d^2 + 2d) on the source, d^2 + 6d on the target: ratio (d + 6) / (2 d + 4) per frame.
    The factor is sum(p q) / sum(q q) over the compensated labels, the shear axes included."""
    from stages.force.compensation import fit_curves
    curves = {k: fit_curves(*_calibration(v)) for k, v in (("one", 1.0), ("two", 2.0))}
    target_punch = Curves((1.0, 6.0, 0.0), (1.0, 6.0, 0.0))
    force = np.c_[0.2 * np.ones(5), -0.1 * np.ones(5), -np.arange(1.0, 6.0)]
    depth, loading = np.linspace(0.2, 1.0, 5), np.ones(5, bool)
    q = force * 2.0
    p = force * ((depth + 6) / (2 * depth + 4))[:, None]
    got = plus.punch_scale(force, depth, loading, {"source": curves["one"], "target": curves["two"]},
                           {"source": curves["two"], "target": target_punch})
    assert got == pytest.approx(float((p * q).sum() / (q * q).sum()), rel=1e-9)
    assert 0.58 < got < 0.71                                      # (d + 6) / (2 d + 4) / 2 at d 0.2..1
    same = plus.punch_scale(force, depth, loading, {"source": curves["one"], "target": curves["two"]},
                            {"source": curves["one"], "target": curves["two"]})
    assert same == pytest.approx(1.0, rel=1e-12)
    assert plus.punch_scale(np.zeros((5, 3)), depth, loading, {"source": curves["one"], "target": curves["two"]},
                            {"source": curves["two"], "target": target_punch}) == 1.0
    with pytest.raises(ValueError, match="punch_calibration: scale -1.0 must be positive"):
        plus.scale_read(None, -1.0)


def test_the_ablation_takes_each_addition_away(nodes_out, skins):
    """Each variant is plus.apply of the transfer's genforce_comp with the other additions; the
    delta is the variant's validation MAE less the full model's, the spread over the seeds'
    means (one model thrice: 0)."""
    from stages.force.data import scoring_set
    from stages.force.study import ablation_study
    _, _, stiffer = nodes_out
    transfer = {f"source=B,target=A,seed={k}": stiffer for k in range(3)}
    groups = {"g": [["B", "A"]]}
    out = ablation_study(homo=groups, material=groups, hetero=groups, transfer=transfer,
                         markers={"A": skins["A_dim"]}, val_indenters=["cone"], additions=list(plus.ADDITIONS))
    val = scoring_set(skins["A_dim"], ["cone"], "validation")
    view = plus.target_view(skins["A_dim"], stiffer["attrs"]["shear_ratios"],
                            punch_scale=stiffer["attrs"]["punch_scale"])

    def mae(used):
        model, _ = plus.apply(load_model(stiffer, "genforce_comp"), view, used)
        return force_metrics(predict_contacts(model, val["images"], val["contact_id"], val["reference"]),
                             val["force"])["mae_total"]

    full = mae(plus.ADDITIONS)
    m = out["metrics"]
    assert m["ablation/homo/genforce_plus/mae_total"] == pytest.approx(full, rel=1e-6)
    assert m["ablation/homo/punch_calibration/delta_mae_total"] == pytest.approx(
        mae(["mirror_shear", "shear_calibration"]) - full, rel=1e-5, abs=1e-7)
    assert m["ablation/homo/mirror_shear/delta_mae_total"] == pytest.approx(
        mae(["shear_calibration", "punch_calibration"]) - full, rel=1e-5, abs=1e-7)
    assert abs(m["ablation/homo/punch_calibration/delta_mae_total"]) > 1e-4     # a 1.5x read moves it
    assert m["ablation/homo/genforce_comp/mae_total"] == pytest.approx(mae([]), rel=1e-6)
    assert m["ablation/homo/seed_spread/mae_total"] == 0.0


def test_predict_rows_reads_each_row_in_its_whole_contact(trained):
    model, _, images, _, _ = trained
    art = {"images": np.concatenate(images), "reference": REF,
           "contact_id": np.repeat(np.arange(len(images)), [len(x) for x in images])}
    rows = np.array([40, 3, 17, 90, 91, 60])                            # any order, several contacts
    full = predict_contacts(model, art["images"], art["contact_id"], REF)
    np.testing.assert_allclose(predict_rows(model, art, rows), full[rows], rtol=1e-5, atol=1e-6)


def test_force_study_scores_every_method_on_validation_and_test(nodes_out, skins):
    own, same, stiffer = nodes_out
    out = force_study(study="s", pairs=[["A", "B"], ["B", "A"]],
                      own={f"skin={k},seed=3": v for k, v in own.items()},
                      transfer={"source=A,target=B,seed=3": same, "source=B,target=A,seed=3": stiffer},
                      markers=skins, test_indenters=["torus"], val_indenters=["cone"], trace_frames=20)
    m = out["metrics"]
    # every method's prediction on the target's torus (test) and cone (validation) contacts, by hand
    for prefix, indenter in (("s", "torus"), ("s_val", "cone")):
        rows = np.concatenate([np.arange(a, b) for a, b in contact_runs(skins["A"], [indenter])])
        for method, art, group in (("source_only", own["B"], "weights"), ("oracle", own["A"], "weights"),
                                   ("genforce_plus", stiffer, "genforce_plus")):
            pred = predict_contacts(load_model(art, group), skins["A"]["images"][rows],
                                    skins["A"]["contact_id"][rows], skins["A"]["reference"])
            true = skins["A"]["force"][rows]
            assert m[f"{prefix}/B_A/{method}/mae_total"] == pytest.approx(
                force_metrics(pred, true)["mae_total"], rel=1e-6)
            light = (-true[:, 2] > 0.05) & (-true[:, 2] <= 2.0)             # the light band, by hand
            assert light.sum() >= 2
            assert m[f"{prefix}/B_A/{method}/mae_fz_light"] == pytest.approx(
                np.abs(pred[light, 2] - true[light, 2]).mean(), rel=1e-6)
        for k in METRICS:
            assert m[f"{prefix}/mean/genforce/{k}"] == pytest.approx(
                np.mean([m[f"{prefix}/A_B/genforce/{k}"], m[f"{prefix}/B_A/genforce/{k}"]]))
    assert set(METHODS) == {"source_only", "genforce", "genforce_comp", "genforce_plus", "oracle"}
    # one seed: no spread; every split of this stub has light contacts, so each gets mae_fz_light
    assert len(m) == 2 * (2 + 1) * len(METHODS) * (len(METRICS) + 1)
    assert {k.rsplit("/", 1)[1] for k in m} == set(METRICS) | {"mae_fz_light"}
    assert out["attrs"]["seeds"] == [3]
    assert out["mae"]["genforce_plus"].shape == (2, 4) and out["r2"]["oracle"].shape == (2, 3)
    assert out["attrs"]["val_frames"] == {"B": 42, "A": 42} and out["attrs"]["test_frames"]["A"] == 42
    for name in ("radar", "r2_hist", "trace", "violin"):
        assert bytes(out["figures"][name][:8]) == PNG
    with pytest.raises(InputError, match=r"indenters \['prism'\] are in both the train and the validation split"):
        force_study(study="s", pairs=[["B", "A"]], own={f"skin={k},seed=0": v for k, v in own.items()},
                    transfer={"source=B,target=A,seed=0": stiffer},
                    markers=skins, test_indenters=["torus"], val_indenters=["prism"])
    with pytest.raises(ValueError, match=r"own holds seeds \[0, 1\], transfer \[0\]: every method needs the same seeds"):
        force_study(study="s", pairs=[["B", "A"]],
                    own={f"skin={k},seed={i}": v for k, v in own.items() for i in (0, 1)},
                    transfer={"source=B,target=A,seed=0": stiffer},
                    markers=skins, test_indenters=["torus"], val_indenters=["cone"])


def test_seed_statistics_on_a_stub_study():
    """Per pair and per group: the mean over seeds of the metric (a group's: of its pairs'
    mean) and `_sd`, the standard deviation over seeds (ddof 1), of the MAE and R2 axes."""
    from stages.force.study import seed_statistics
    per_seed = [{"s/a_b/genforce/mae_fz": 1.0, "s/b_a/genforce/mae_fz": 3.0, "s/a_b/genforce/r2_fz": 0.5,
                 "s/b_a/genforce/r2_fz": 0.7},
                {"s/a_b/genforce/mae_fz": 2.0, "s/b_a/genforce/mae_fz": 2.0, "s/a_b/genforce/r2_fz": 0.6,
                 "s/b_a/genforce/r2_fz": 0.6},
                {"s/a_b/genforce/mae_fz": 1.5, "s/b_a/genforce/mae_fz": 4.5, "s/a_b/genforce/r2_fz": 0.3,
                 "s/b_a/genforce/r2_fz": 0.9}]
    out = seed_statistics(per_seed, "s", {"mean": ["a_b", "b_a"], "one": ["b_a"]})
    assert out["s/mean/genforce/mae_fz"] == pytest.approx(14 / 6)               # seeds' means 2, 2, 3
    assert out["s/mean/genforce/mae_fz_sd"] == pytest.approx(np.std([2.0, 2.0, 3.0], ddof=1))
    assert out["s/one/genforce/mae_fz"] == pytest.approx(9.5 / 3)
    assert out["s/one/genforce/mae_fz_sd"] == pytest.approx(np.std([3.0, 2.0, 4.5], ddof=1))
    assert out["s/a_b/genforce/r2_fz"] == pytest.approx(1.4 / 3)
    assert out["s/a_b/genforce/r2_fz_sd"] == pytest.approx(np.std([0.5, 0.6, 0.3], ddof=1))
    assert out["s/mean/genforce/r2_fz_sd"] == pytest.approx(0.0, abs=1e-12)     # every seed's mean 0.6
    assert len(out) == 4 * 2 * 2
    assert "s/mean/genforce/mae_fz_sd" not in seed_statistics(per_seed[:1], "s", {"mean": ["a_b", "b_a"]})


def test_splits_must_be_disjoint_and_not_empty():
    check_splits(["a", "b"], ["c"], ["d", "e"], "t")
    with pytest.raises(InputError, match=r"t: indenters \['d'\] are in both the validation and the test split"):
        check_splits(["a"], ["c", "d"], ["d"], "t")
    with pytest.raises(InputError, match=r"t: indenters \['a'\] are in both the train and the test split"):
        check_splits(["a"], ["c"], ["a"], "t")
    with pytest.raises(InputError, match="t: the validation split names no indenter"):
        check_splits(["a"], [], ["d"], "t")


def test_the_default_splits_are_disjoint_and_test_is_the_authors_unseen_set():
    from pathlib import Path

    from pipeline.params import load
    p = load(Path(__file__).resolve().parents[3] / "params.yaml")["splits"]
    check_splits(p["train_indenters"], p["val_indenters"], p["test_indenters"], "params")
    assert sorted(p["test_indenters"]) == ["cone", "pacman", "sphere_s", "torus", "triangle", "wave"]
    assert set(p["m2m_indenters"]) == set(p["train_indenters"]) - {"dots"}


def test_ablation_arithmetic_on_a_stub_study():
    """delta = mean over seeds of (the variant without it - all); spread = sd over seeds of all,
    each seed's figure the mean over the study's pairs."""
    adds = ["mirror_shear", "shear_calibration"]
    assert ablation_variants(adds) == {"all": adds, "none": [], "-mirror_shear": ["shear_calibration"],
                                       "-shear_calibration": ["mirror_shear"]}
    scores = {"all": [[1.0, 3.0], [2.0, 2.0], [1.5, 3.5]],          # per seed: 2.0, 2.0, 2.5
              "none": [[3.0, 3.0], [3.0, 3.0], [3.0, 3.0]],
              "-mirror_shear": [[1.5, 3.5], [2.5, 2.5], [2.0, 4.0]],   # +0.5 each: delta 0.5
              "-shear_calibration": [[1.0, 3.0], [2.0, 2.0], [1.0, 3.0]]}      # 2, 2, 2: delta -1/6
    m = ablation_metrics("s", scores, adds)
    assert m["ablation/s/seed_spread/mae_total"] == pytest.approx(np.std([2.0, 2.0, 2.5], ddof=1))
    assert m["ablation/s/mirror_shear/delta_mae_total"] == pytest.approx(0.5)
    assert m["ablation/s/shear_calibration/delta_mae_total"] == pytest.approx(-1 / 6)
    assert m["ablation/s/genforce_plus/mae_total"] == pytest.approx(13 / 6)
    assert m["ablation/s/genforce_comp/mae_total"] == pytest.approx(3.0)
    with pytest.raises(ValueError, match="2 seeds; the seed spread needs 3 or more"):
        ablation_metrics("s", {k: v[:2] for k, v in scores.items()}, adds)
    light = ablation_metrics("s", scores, adds, "mae_fz_light")          # the same arithmetic, renamed
    assert light["ablation/s/shear_calibration/delta_mae_fz_light"] == pytest.approx(-1 / 6)
    assert light["ablation/s/seed_spread/mae_fz_light"] == pytest.approx(np.std([2.0, 2.0, 2.5], ddof=1))
    assert not any("mae_total" in k for k in light)
    # a pair whose validation set has no light contact (NaN): no light figures for the study
    assert ablation_metrics("s", {**scores, "all": [[1.0, np.nan], [2.0, 2.0], [1.5, 3.5]]}, adds,
                            "mae_fz_light") == {}


# ---------------------------------------------------------------------------- checkpoints

def _transfer_run(skins, tiny_config, checkpoint=None, steps=6):
    """fit_transfer with compensation: four fits (genforce and genforce_comp, two stages each)."""
    return fit_transfer(translated=skins["A"], source_calibration=_calibration_art(1.0),
                        target_calibration=_calibration_art(2.0), source="B", target="A",
                        config={**tiny_config, "seq_len": 10}, steps=steps, batch_size=2, lr=0.05,
                        seed=0, finetune_steps=3, train_indenters=["sphere", "prism", "cone"],
                        checkpoint=checkpoint)


def _counting_batches(monkeypatch, die_at=None):
    """Count the fits' batch draws; raise KeyboardInterrupt (a kill) on draw number `die_at`."""
    import stages.force.train as train
    real, calls = train._batch, []

    def batch(*a, **k):
        calls.append(1)
        if len(calls) == die_at:
            raise KeyboardInterrupt
        return real(*a, **k)
    monkeypatch.setattr(train, "_batch", batch)
    return calls


def _same_node_output(a, b):
    for method in ("genforce", "genforce_comp", "genforce_plus"):
        assert set(a[method]) == set(b[method])
        for k, v in a[method].items():
            np.testing.assert_array_equal(v, b[method][k], err_msg=f"{method} {k}")
    assert a["attrs"] == b["attrs"]          # histories (every step's loss), ranges, curves


def test_transfer_killed_in_its_third_fit_resumes_it_and_ends_as_if_never_stopped(
        skins, tiny_config, tmp_path, monkeypatch):
    """Draws 1-6 are genforce's pretrain, 7-9 its fine-tune, 10-15 genforce_comp's pretrain:
    killed at draw 13 (a checkpoint at every step's end), the node run again re-runs neither
    genforce fit, resumes genforce_comp's pretrain at its step 3 (6 draws left with the
    fine-tune's 3) and gives the uninterrupted node's weights and losses bit for bit."""
    import stages.force.train as train
    calls = _counting_batches(monkeypatch)
    whole = _transfer_run(skins, tiny_config)
    assert len(calls) == 18 and "resumed_at_step" not in whole["timing"]
    monkeypatch.setattr(train, "CHECKPOINT_EVERY_S", 0.0)
    path = tmp_path / "k.ckpt"
    _counting_batches(monkeypatch, die_at=13)
    with pytest.raises(KeyboardInterrupt):
        _transfer_run(skins, tiny_config, checkpoint=str(path))
    saved = torch.load(path, weights_only=True)
    assert sorted(saved["done"]) == ["genforce/finetune", "genforce/pretrain"]
    assert (saved["current"]["label"], saved["current"]["step"]) == ("genforce_comp/pretrain", 3)
    calls = _counting_batches(monkeypatch)
    again = _transfer_run(skins, tiny_config, checkpoint=str(path))
    assert len(calls) == 6
    assert again["timing"]["resumed_at_step"] == {"genforce_comp/pretrain": 3}
    _same_node_output(again, whole)


def test_an_unreadable_or_foreign_force_checkpoint_is_set_aside_or_ignored(skins, tiny_config, tmp_path,
                                                                           monkeypatch):
    """A truncated file is renamed .bad with a warning; a state saved by a 6-step pretrain does
    not serve an 8-step one (warning); either way the node trains from scratch, as without."""
    import stages.force.train as train
    whole = _transfer_run(skins, tiny_config, steps=8)
    path = tmp_path / "k.ckpt"
    path.write_bytes(b"PK\x03\x04 truncated")
    with pytest.warns(UserWarning, match=r"k\.ckpt set aside as \.bad and training starts over"):
        out = _transfer_run(skins, tiny_config, checkpoint=str(path), steps=8)
    assert (tmp_path / "k.ckpt.bad").read_bytes() == b"PK\x03\x04 truncated"
    _same_node_output(out, whole)
    path.unlink()
    monkeypatch.setattr(train, "CHECKPOINT_EVERY_S", 0.0)
    _counting_batches(monkeypatch, die_at=3)
    with pytest.raises(KeyboardInterrupt):
        _transfer_run(skins, tiny_config, checkpoint=str(path), steps=6)
    _counting_batches(monkeypatch)
    with pytest.warns(UserWarning, match=r"fit 'genforce/pretrain' was saved for 6 steps of 2, "
                                         r"not 8 of 2; it starts over"):
        out = _transfer_run(skins, tiny_config, checkpoint=str(path), steps=8)
    assert "resumed_at_step" not in out["timing"]
    _same_node_output(out, whole)


