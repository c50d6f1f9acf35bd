"""The force regressor, material compensation, force metrics and the force nodes, on tiny
synthetic contact sequences (see conftest.blob_contacts)."""
import json

import numpy as np
import pytest
import torch
from sklearn.metrics import mean_absolute_error, r2_score

from stages.common import InputError, torch_device
from stages.force.compensation import (Curves, compensate, curves_from_calibration, fit_curves, label_scale,
                                       loading_mask, shear_ratio)
from stages.force.metrics import METRICS, force_metrics
from stages.force.model import (ForceRegressor, MeanPredictor, StreamingPredictor, from_arrays, load_model,
                                load_predictor, model_config, predict_contacts, predict_sequence,
                                mirror_group, resolve_range, to_arrays)
from stages.force.nodes import (METHODS, contact_runs, ensemble_weights, fit_own, fit_transfer, fit_transfer_seed,
                                force_study, recorded_compensation, scale_fz)
from stages.force.train import fit, make_sequences, mirrored

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


def test_mirrored_copies_reverse_the_image_axes_and_negate_their_force(tiny_config):
    image = np.zeros((2, 32, 32), np.uint8)
    image[:, 3, 20] = 255                                  # row 3, column 20
    force = np.array([[1.0, -2.0, -3.0], [0.5, 0.25, -1.0]], np.float32)
    seqs = mirrored(make_sequences([image], [force], REF, tiny_config))
    assert len(seqs) == 4
    peaks = [tuple(np.argwhere(s.inputs[0, 0].numpy() == s.inputs[0, 0].numpy().max())[0]) for s in seqs]
    # 32 px area-resized to 16: row 3 -> 1, column 20 -> 10; reversed: 14 and 5
    assert peaks == [(1, 10), (1, 5), (14, 10), (14, 5)]
    for s, sign in zip(seqs, ([1, 1], [-1, 1], [1, -1], [-1, -1])):
        np.testing.assert_array_equal(s.force, force * np.array(sign + [1], np.float32))
    with pytest.raises(InputError, match="mirror must be true or false, got 'yes'"):
        fit_own(markers=contact_artifact([image], [force], ["a"]), skin="s", config={**tiny_config,
                "mirror": "yes"}, steps=1, batch_size=1, lr=0.01, seed=0, train_indenters=None)


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
    with pytest.raises(ValueError, match="mirror_read 'both' is not one of"):
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


def test_mirror_reads_shear_on_the_side_training_never_pressed(blobs, tiny_config):
    images, forces = blobs(64, seed=3)
    right = [k for k, f in enumerate(forces) if f[:, 0].mean() > 0]           # Fx > 0 only
    left = [k for k in range(64) if k not in right]
    auto = {**tiny_config, "force_min": "auto", "force_max": "auto"}
    seqs = make_sequences([images[k] for k in right], [forces[k] for k in right], REF, auto)
    true = np.concatenate([forces[k] for k in left])
    mae = {}
    for mirror in (False, True):
        model, history = fit(seqs, auto, steps=300, batch_size=4, lr=0.1, seq_len=14, seed=0, mirror=mirror)
        pred = predict_contacts(model, np.concatenate([images[k] for k in left]),
                                np.repeat(np.arange(len(left)), 14), REF)
        mae[mirror] = np.abs(pred - true).mean(0)
        assert history["contacts"] == len(right) == 32 and history["mirror"] is mirror
    # the mirrored labels make the shear ranges symmetric; without, Fx stops a little below 0
    np.testing.assert_allclose(model.config["force_min"][:2], -np.asarray(model.config["force_max"][:2]))
    assert mae[True][0] < 0.4 * mae[False][0] and mae[True][0] < 0.3, mae   # 0.23 against 0.69 N
    assert mae[True][2] < 1.2 * mae[False][2], mae


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


def test_paired_depth_maps_the_source_depth_onto_the_target_curve():
    """A sensor calibrated deeper than it was collected (d_max 1.4 mm, collected to 1 mm: its
    frames reach 1/1.4) paired with one calibrated to its collection depth: the target's curve
    is read at k d, k = 1.4, and k = 1 is the shared-depth formula exactly."""
    from stages.force.compensation import depth_ratio
    k = depth_ratio(np.linspace(0, 1 / 1.4, 9), np.linspace(0, 1, 9))
    assert k == pytest.approx(1.4)
    assert depth_ratio([0.0, 0.5, 1.0], [0.0, 0.25, 0.5]) == 0.5
    source = Curves(loading=(0.0, 2.0, 0.0), unloading=(0.0, 1.0, 0.0))   # P_s = 2 d, d on unloading
    target = Curves(loading=(1.0, 1.0, 0.0), unloading=(0.0, 3.0, 0.0))   # P_t = d^2 + d, 3 d
    depth, loading = np.array([0.5, 0.25, 0.0, 0.5]), np.array([True, True, True, False])
    # P_t(1.4 d) / P_s(d): (0.49 + 0.7) / 1 = 1.19; (0.1225 + 0.35) / 0.5 = 0.945; d -> 0: 1.4 / 2
    # = 0.7; unloading 3 * 0.7 / 0.5 = 4.2
    np.testing.assert_allclose(label_scale(depth, loading, source, target, depth_ratio=k),
                               [1.19, 0.945, 0.7, 4.2], rtol=1e-9)
    np.testing.assert_array_equal(label_scale(depth, loading, source, target, depth_ratio=1.0),
                                  label_scale(depth, loading, source, target))
    force = np.tile([1.0, -1.0, -2.0], (4, 1)).astype(np.float32)
    same = compensate(force, depth, loading, source, source, depth_ratio=k)    # same curves, k != 1
    np.testing.assert_allclose(same[:, 2], -2.0 * np.array([1.4, 1.4, 1.4, 1.4]), rtol=1e-6)
    with pytest.raises(ValueError, match="target collection's normalised depth"):
        depth_ratio([0.2, 0.5], [0.0, 0.0])
    with pytest.raises(ValueError, match="depth_ratio must be a positive"):
        label_scale(depth, loading, source, target, depth_ratio=-1.0)


def _sheared_calibration(scale, gain, n=10, m=4):
    """_calibration's loading and unloading with a shear leg at d = 1 between them (phases 1,
    2): |F_xy| = gain * |Fz| * j / m at step j of m out and back, Fz held."""
    d, f, load = _calibration(scale, n=n)
    fz1 = f[n - 1, 2]
    j = np.r_[np.arange(1, m + 1), np.arange(m - 1, -1, -1)] / m
    leg = np.c_[gain * abs(fz1) * j * 0.6, gain * abs(fz1) * j * 0.8, np.full(2 * m, fz1)]
    phase = np.r_[np.zeros(n), np.ones(m), np.full(m, 2), np.full(n, 3)].astype(np.int8)
    return (np.r_[d[:n], np.ones(2 * m), d[n:]], np.r_[f[:n], leg, f[n:]],
            np.r_[load[:n], np.ones(2 * m, bool), load[n:]], phase)


def test_shear_gain_and_axes_mode():
    src = fit_curves(*_sheared_calibration(1.0, gain=0.5))
    tgt = fit_curves(*_sheared_calibration(2.0, gain=0.1))
    # gain: sum |F_xy| / sum |Fz| over the shear-out frames; the leg is not on the curves
    assert src.shear_gain == pytest.approx(0.5 * np.mean([1, 2, 3, 4]) / 4)
    np.testing.assert_allclose(src.loading, [1.0, 2.0, 0.0], atol=1e-9)
    assert fit_curves(*_calibration(1.0)).shear_gain is None
    assert shear_ratio(src, tgt, "axes") == pytest.approx(0.2)
    assert shear_ratio(src, tgt, "normal") == 1.0
    assert shear_ratio(src, tgt, "axes", 1.4) == pytest.approx(0.2 / 1.4)     # gains read deeper
    assert shear_ratio(src, tgt, "normal", 1.4) == 1.0
    assert shear_ratio(src, fit_curves(*_calibration(2.0)), "axes") == 1.0     # no leg: normal
    with pytest.raises(ValueError, match="depth_ratio 0.0 must be positive"):
        shear_ratio(src, tgt, "axes", 0.0)
    with pytest.raises(ValueError, match="'both'"):
        shear_ratio(src, tgt, "both")
    force = np.array([[1.0, -2.0, -4.0]], np.float32)
    depth, loading = np.array([0.5]), np.array([True])
    np.testing.assert_allclose(compensate(force, depth, loading, src, tgt, mode="axes"),
                               [[0.4, -0.8, -8.0]], rtol=1e-6)       # r = 2; shear x 2 x 0.2
    np.testing.assert_allclose(compensate(force, depth, loading, src, tgt), [[2.0, -4.0, -8.0]], rtol=1e-6)
    # depth ratio 2: Fz by the target's curve at 2 d (r), shear by r times 0.2 / 2
    deep = compensate(force, depth, loading, src, tgt, mode="axes", depth_ratio=2.0)
    r = deep[0, 2] / -4.0
    assert r > 4.0
    np.testing.assert_allclose(deep[0, :2], [1.0 * r * 0.1, -2.0 * r * 0.1], rtol=1e-6)
    assert Curves.from_dict(src.as_dict()) == src


# ---------------------------------------------------------------------------- metrics

def test_metrics_match_sklearn_and_hand_values():
    true = np.array([[0.0, 1.0, -1.0], [1.0, 1.0, -2.0], [2.0, 1.0, -3.0], [3.0, 1.0, -6.0]])
    pred = np.array([[0.5, 1.0, -1.0], [1.0, 1.5, -2.0], [2.0, 1.0, -4.0], [2.5, 1.0, -6.0]])
    m = force_metrics(pred, true)
    assert list(m) == list(METRICS)
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


# ---------------------------------------------------------------------------- nodes

NAMES = ["sphere", "prism", "cone", "torus"]


@pytest.fixture(scope="module")
def skins(blobs):
    """Two 'skins' sharing one synthetic physics; contact k pressed by NAMES[k % 4]."""
    images, forces = blobs(12, seed=3)
    a = contact_artifact(images, forces, [NAMES[k % 4] for k in range(12)])
    b = dict(a, images=255 - a["images"], reference=np.full((32, 32), 255, np.uint8))
    return {"A": a, "B": b}


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
    train = ["sphere", "prism", "cone"]
    own = {s: fit_own(markers=skins[s], skin=s, train_indenters=train, **kw) for s in ("A", "B")}
    same = fit_transfer(translated=skins["B"], source_calibration=_calibration_art(1.0),
                        target_calibration=_calibration_art(1.0), source="A", target="B",
                        finetune_steps=2, train_indenters=train, **kw)
    stiffer = fit_transfer(translated=skins["A"], source_calibration=_calibration_art(1.0),
                           target_calibration=_calibration_art(2.0), source="B", target="A",
                           finetune_steps=0, train_indenters=train, **kw)
    return own, same, stiffer


def test_fit_own_outputs(nodes_out, skins):
    own, _, _ = nodes_out
    out = own["A"]
    assert out["attrs"]["config"]["input_size"] == 16 and out["attrs"]["train"]["seq_len"] == 10
    assert out["attrs"]["history"]["contacts"] == 9 and len(out["attrs"]["history"]["loss"]) == 4
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
    assert set(same["genforce"]) == set(same["genforce_comp"])
    for k, v in same["genforce"].items():
        np.testing.assert_array_equal(v, same["genforce_comp"][k])
    assert "genforce_comp" not in same["attrs"]["history"]
    assert set(same["attrs"]["history"]["genforce"]) == {"pretrain", "finetune"}
    assert "seconds" not in same["attrs"]["history"]["genforce"]["finetune"]
    assert same["timing"]["genforce"]["finetune"]["seconds"] > 0
    assert stiffer["attrs"]["compensation_identity"] is False
    assert stiffer["attrs"]["label_scale"]["min"] == pytest.approx(2.0)
    assert any(not np.array_equal(v, stiffer["genforce_comp"][k]) for k, v in stiffer["genforce"].items())
    assert bytes(stiffer["figures"]["compensation"][:8]) == PNG
    json.dumps(stiffer["attrs"])


def test_transfer_seed_reproduces_transfer_and_mean_predictor(nodes_out, skins, tiny_config):
    """transfer_seed at the transfer's own seed rebuilds its genforce_comp bit for bit (same
    compensated labels from the stored curves, same schedule); another seed differs; the
    MeanPredictor reads the mean of its members."""
    _, same, stiffer = nodes_out
    kw = dict(config={**tiny_config, "seq_len": 10}, steps=4, batch_size=2, lr=0.05,
              train_indenters=["sphere", "prism", "cone"])
    transfer = json.loads(json.dumps({"attrs": stiffer["attrs"]}))     # as a store hands it over
    again = fit_transfer_seed(transfer=transfer, translated=skins["A"], seed=0, finetune_steps=0, **kw)
    assert set(again["genforce_comp"]) == set(stiffer["genforce_comp"])
    for k, v in stiffer["genforce_comp"].items():
        np.testing.assert_array_equal(again["genforce_comp"][k], v)
    assert again["attrs"]["seed"] == 0 and (again["attrs"]["source"], again["attrs"]["target"]) == ("B", "A")
    # the identity pair (finetune stage included) too
    again = fit_transfer_seed(transfer={"attrs": same["attrs"]}, translated=skins["B"], seed=0,
                              finetune_steps=2, **kw)
    for k, v in same["genforce_comp"].items():
        np.testing.assert_array_equal(again["genforce_comp"][k], v)
    other = fit_transfer_seed(transfer=transfer, translated=skins["A"], seed=1, finetune_steps=0, **kw)
    assert any(not np.array_equal(v, other["genforce_comp"][k]) for k, v in stiffer["genforce_comp"].items())
    json.dumps(other["attrs"])
    members = [load_predictor(stiffer, prefix="genforce_comp"), load_predictor(other, prefix="genforce_comp")]
    mean = MeanPredictor([load_predictor(stiffer, prefix="genforce_comp"),
                          load_predictor(other, prefix="genforce_comp")])
    for image in skins["A"]["images"][:5]:            # the GRU states carry on in every member
        np.testing.assert_allclose(mean.step(image), (members[0].step(image) + members[1].step(image)) / 2,
                                   rtol=1e-6, atol=1e-6)
    mean.reset()
    members[0].reset()
    members[1].reset()
    image = skins["A"]["images"][7]
    np.testing.assert_allclose(mean.step(image), (members[0].step(image) + members[1].step(image)) / 2,
                               rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="at least one predictor"):
        MeanPredictor([])
    with pytest.raises(ValueError, match=r"transfer\[B->A\] seed 1: no translated contacts"):
        fit_transfer_seed(transfer=transfer, translated=skins["A"], seed=1, finetune_steps=0,
                          **{**kw, "train_indenters": []})


def test_recorded_compensation_matches_the_transfers_labels(nodes_out, skins):
    """recorded_compensation reads a stored transfer's attrs: its Fz gain over the training
    rows is the label scale fit_transfer recorded; rows pick the same frames; the identity
    pair's labels come back bit for bit."""
    _, same, stiffer = nodes_out
    attrs = json.loads(json.dumps(stiffer["attrs"]))
    force = np.asarray(skins["A"]["force"], np.float32)
    comp = recorded_compensation(skins["A"], attrs)
    rows = np.concatenate([np.arange(a, b) for a, b in contact_runs(skins["A"], attrs["train_indenters"])])
    loaded = np.abs(force[rows, 2]) > 1e-3
    gain = comp[rows, 2][loaded] / force[rows, 2][loaded]
    assert gain.min() == pytest.approx(attrs["label_scale"]["min"], rel=1e-4)
    assert gain.max() == pytest.approx(attrs["label_scale"]["max"], rel=1e-4)
    np.testing.assert_array_equal(recorded_compensation(skins["A"], attrs, rows[::3]), comp[rows[::3]])
    np.testing.assert_array_equal(recorded_compensation(skins["B"], same["attrs"]),
                                  np.asarray(skins["B"]["force"], np.float32))


def test_fit_transfer_axes_mode_and_auto_ranges(skins, tiny_config):
    """Mode "axes" with shear legs scales the shear labels by the gain ratio (attrs
    shear_ratio); each model's auto force range follows its own labels."""
    kw = dict(config={**tiny_config, "seq_len": 10, "force_min": "auto", "force_max": "auto"},
              steps=2, batch_size=2, lr=0.05, seed=0, finetune_steps=0, train_indenters=["sphere"],
              source="B", target="A", translated=skins["A"])
    cal = {}
    for name, (scale, gain) in {"s": (1.0, 0.5), "t": (2.0, 0.1)}.items():
        d, f, load, phase = _sheared_calibration(scale, gain)
        cal[name] = {"normalised_depth": d, "force": f, "loading": load, "phase": phase}
    out = fit_transfer(source_calibration=cal["s"], target_calibration=cal["t"], compensation="axes", **kw)
    assert out["attrs"]["shear_ratio"] == pytest.approx(0.2)
    rows = np.concatenate([np.arange(a, b) for a, b in contact_runs(skins["A"], ["sphere"])])
    labels = skins["A"]["force"][rows].astype(float)
    comp = compensate(labels, skins["A"]["normalised_depth"][rows], loading_mask(skins["A"]["phase"][rows]),
                      fit_curves(*_sheared_calibration(1.0, 0.5)), fit_curves(*_sheared_calibration(2.0, 0.1)),
                      mode="axes")
    for method, y in (("genforce", labels), ("genforce_comp", comp)):
        span = y.max(0) - y.min(0)
        span = np.where(span < 1e-3, np.nan, span)
        lo = np.array(out["attrs"]["force_range"][method]["min"])
        np.testing.assert_allclose(lo, np.where(np.isnan(span), lo, y.min(0) - 0.05 * span), rtol=1e-4, atol=1e-5)
    plain = fit_transfer(source_calibration=cal["s"], target_calibration=cal["t"], compensation="normal", **kw)
    assert plain["attrs"]["shear_ratio"] == 1.0
    assert plain["attrs"]["compensation_depth"] == "shared" and plain["attrs"]["depth_ratio"] == 1.0


def test_fit_transfer_paired_depth(skins, tiny_config):
    """compensation_depth "paired" reads k from the target collection's normalised depth; the
    same calibration on both sides is then no identity when k != 1."""
    kw = dict(config={**tiny_config, "seq_len": 10}, steps=1, batch_size=2, lr=0.05, seed=0,
              finetune_steps=0, train_indenters=["sphere"], source="B", target="A",
              translated=skins["A"], source_calibration=_calibration_art(1.0),
              target_calibration=_calibration_art(1.0))
    deeper = {"normalised_depth": 2.0 * skins["A"]["normalised_depth"]}
    out = fit_transfer(compensation_depth="paired", target_markers=deeper, **kw)
    assert out["attrs"]["depth_ratio"] == pytest.approx(2.0)
    assert out["attrs"]["compensation_identity"] is False
    # P(d) = d^2 + 2 d on both branches (unloading x 0.8): r = 2 (2 d + 2) / (d + 2), increasing
    rows = np.concatenate([np.arange(a, b) for a, b in contact_runs(skins["A"], ["sphere"])])
    d = np.asarray(skins["A"]["normalised_depth"], float)[rows]
    r = lambda x: 2 * (2 * x + 2) / (x + 2)
    assert out["attrs"]["label_scale"]["min"] == pytest.approx(r(d.min()))
    assert out["attrs"]["label_scale"]["max"] == pytest.approx(r(d.max()))
    same = fit_transfer(compensation_depth="paired", target_markers=skins["A"], **kw)
    assert same["attrs"]["depth_ratio"] == 1.0 and same["attrs"]["compensation_identity"] is True
    with pytest.raises(ValueError, match=r"fit_transfer\[B->A\]: compensation_depth 'paired' needs"):
        fit_transfer(compensation_depth="paired", **kw)
    with pytest.raises(ValueError, match="compensation_depth 'deepest' is not one of"):
        fit_transfer(compensation_depth="deepest", target_markers=skins["A"], **kw)


def test_force_study_metrics_and_figures(nodes_out, skins):
    own, same, stiffer = nodes_out
    out = force_study(study="toy", pairs=[["A", "B"], ["B", "A"]], own=own,
                      transfer={"source=A,target=B": same, "source=B,target=A": stiffer},
                      markers=skins, test_indenters=["torus"], trace_frames=20)
    m = out["metrics"]
    assert len(m) == 2 * 5 * 7 + 5 * 7                   # 4 methods and labels_comp, 2 pairs + mean
    rows = np.flatnonzero(np.isin(skins["A"]["contact_id"], [3, 7, 11]))     # the torus contacts
    truth = skins["A"]["force"][rows]
    # labels_comp: A -> B is the identity on shared labels; B -> A doubles them (target 2x stiffer)
    assert m["toy/A_B/labels_comp/mae_total"] == 0.0 and m["toy/A_B/labels_comp/r2_fz"] == 1.0
    doubled = compensate(truth, skins["A"]["normalised_depth"][rows], loading_mask(skins["A"]["phase"][rows]),
                         fit_curves(*_calibration(1.0)), fit_curves(*_calibration(2.0)))
    np.testing.assert_allclose(doubled, 2.0 * truth, rtol=1e-5)
    assert m["toy/B_A/labels_comp/mae_fz"] == pytest.approx(np.abs(truth[:, 2]).mean(), rel=1e-5)
    assert m["toy/mean/labels_comp/mae_fz"] == pytest.approx(m["toy/B_A/labels_comp/mae_fz"] / 2)
    oracle = predict_contacts(load_model(own["A"]), skins["A"]["images"][rows],
                              skins["A"]["contact_id"][rows], skins["A"]["reference"])
    assert m["toy/B_A/oracle/mae_fz"] == pytest.approx(force_metrics(oracle, truth)["mae_fz"])
    assert m["toy/A_B/genforce_comp/r2_fx"] == m["toy/A_B/genforce/r2_fx"]   # identity: same model
    assert m["toy/mean/source_only/mae_total"] == pytest.approx(
        (m["toy/A_B/source_only/mae_total"] + m["toy/B_A/source_only/mae_total"]) / 2)
    assert out["mae"]["oracle"].shape == (2, 4) and out["r2"]["genforce"].shape == (2, 3)
    assert out["pairs"] == ["A_B", "B_A"] and out["trace"]["true"].shape == (20, 3)
    assert set(out["mae"]) == set(METHODS)
    for name in ("radar", "r2_hist", "trace", "violin"):
        assert bytes(out["figures"][name][:8]) == PNG, name
    with pytest.raises(KeyError, match="source=A,target=C"):
        force_study(study="toy", pairs=[["A", "C"]], own={**own, "C": own["A"]}, transfer={},
                    markers={**skins, "C": skins["A"]}, test_indenters=["torus"])


def test_force_study_seeds_average_genforce_comp_over_the_seed_models(nodes_out, skins):
    """A pair with seed models gets genforce_comp_seeds: each metric's mean and sd over
    transfer's genforce_comp and the seeds' (here seed 1 = another model, seed 2 = the same),
    and genforce_comp_ensemble: the metrics of their mean prediction; a pair without them gets
    neither, nor does the study's mean."""
    own, same, stiffer = nodes_out
    seeds = {"source=A,target=B,seed=2": same, "source=A,target=B,seed=1": stiffer}
    m = force_study(study="toy", pairs=[["A", "B"], ["B", "A"]], own=own,
                    transfer={"source=A,target=B": same, "source=B,target=A": stiffer},
                    markers=skins, test_indenters=["torus"], trace_frames=20, seeds=seeds)["metrics"]
    rows = np.flatnonzero(np.isin(skins["B"]["contact_id"], [3, 7, 11]))     # the torus contacts
    model = load_model(stiffer, "genforce_comp", device=torch_device())    # where force_study predicts
    other_pred = predict_contacts(model, skins["B"]["images"][rows], skins["B"]["contact_id"][rows],
                                  skins["B"]["reference"])
    other = force_metrics(other_pred, skins["B"]["force"][rows])
    base = m["toy/A_B/genforce_comp/mae_total"]
    assert other["mae_total"] != pytest.approx(base)
    assert m["toy/A_B/genforce_comp_seeds/mae_total"] == pytest.approx((2 * base + other["mae_total"]) / 3)
    assert m["toy/A_B/genforce_comp_seeds/sd_mae_total"] == pytest.approx(
        np.std([base, other["mae_total"], base], ddof=1))
    assert m["toy/A_B/genforce_comp_seeds/r2_fz"] == pytest.approx(
        (2 * m["toy/A_B/genforce_comp/r2_fz"] + other["r2_fz"]) / 3)
    assert not any("/B_A/genforce_comp_seeds/" in k or "/mean/genforce_comp_seeds/" in k for k in m)
    # genforce_comp_ensemble: the metrics of the three models' mean prediction
    same_pred = predict_contacts(load_model(same, "genforce_comp", device=torch_device()),
                                 skins["B"]["images"][rows], skins["B"]["contact_id"][rows],
                                 skins["B"]["reference"])
    ensemble = force_metrics((2 * same_pred + other_pred) / 3, skins["B"]["force"][rows])
    assert m["toy/A_B/genforce_comp_ensemble/mae_total"] == pytest.approx(ensemble["mae_total"], rel=1e-5)
    assert m["toy/A_B/genforce_comp_ensemble/r2_fx"] == pytest.approx(ensemble["r2_fx"], rel=1e-5)
    assert m["toy/A_B/genforce_comp_ensemble/mae_total"] != pytest.approx(
        m["toy/A_B/genforce_comp_seeds/mae_total"])
    assert not any("/B_A/genforce_comp_ensemble/" in k or "/mean/genforce_comp_ensemble/" in k for k in m)


def _paired(skins):
    """The toy skins with every frame location-paired (their frames are the same locations)."""
    return {k: dict(v, paired=np.ones(len(v["frame"]), bool)) for k, v in skins.items()}


def test_ensemble_weights_favour_the_member_that_reads_the_paired_frames_better(nodes_out, skins):
    """Per axis, each member's inverse mean squared error on the target's paired frames,
    normalised: identical members share equally; a member whose Fz is tripled loses Fz weight
    and keeps its shear weight where the transfer has no read-out labels; a member that
    reproduces the read-out labels takes (nearly) all the shear weight; the read-out frames must
    be the paired frames."""
    _, same, _ = nodes_out
    p = _paired(skins)
    train = ["sphere", "prism", "cone"]
    model = load_model(same, "genforce_comp")
    np.testing.assert_array_equal(ensemble_weights([model, model], same, p["B"], p["B"], train, 8),
                                  np.full((2, 3), 0.5))
    tripled = load_model(same, "genforce_comp")
    scale_fz(tripled, 3.0)
    w = ensemble_weights([model, tripled], same, p["B"], p["B"], train, 8)
    np.testing.assert_allclose(w.sum(0), 1.0)
    assert w[0, 2] > 0.6 and w[1, 2] < 0.4 and list(w[:, 0]) == [0.5, 0.5] == list(w[:, 1])
    # the Fz weights from the members' whole-collection predictions and the labels there
    # ("same" is the identity compensation: the labels are B's own)
    from stages.m2m.data import paired_table
    _, rows = paired_table({"t": p["B"]}, ["t"], train, 8)
    truth = p["B"]["force"][rows[0], 2]
    err = [np.mean((predict_contacts(m, p["B"]["images"], p["B"]["contact_id"], p["B"]["reference"])[rows[0], 2]
                    - truth) ** 2) for m in (model, tripled)]
    assert w[0, 2] == pytest.approx(err[1] / (err[0] + err[1]), rel=1e-4)
    # read-out labels equal to the first member's own shear there: it takes the shear weight
    shear = predict_contacts(model, p["B"]["images"], p["B"]["contact_id"], p["B"]["reference"])[rows[0], :2]
    labelled = dict(same, readout_frame=p["B"]["frame"][rows[0]], readout_shear=shear)
    other = load_model(nodes_out[2], "genforce_comp")
    w = ensemble_weights([model, other], labelled, p["B"], p["B"], train, 8)
    assert w[0, 0] > 0.999 and w[0, 1] > 0.999
    with pytest.raises(ValueError, match=r"the transfer's read-out frames are not the paired frames of "
                                         r"indenters \['sphere', 'prism', 'cone'\] \(4 pairs\)"):
        ensemble_weights([model], labelled, p["B"], p["B"], train, 4)


def test_force_study_paired_ensemble_weighs_its_members(nodes_out, skins):
    """ensemble "paired": the ensemble's metrics are those of the members' predictions weighted
    per axis by ensemble_weights (attrs ensemble_weights, the transfer's model first); identical
    members weigh alike; an unknown mode, or "paired" without seen indenters or without the
    pair's translation, is a one-line error."""
    own, same, _ = nodes_out
    p = _paired(skins)
    tripled = load_model(same, "genforce_comp")
    scale_fz(tripled, 3.0)                                # a member that reads Fz three times over
    tripled = {"genforce_comp": to_arrays(tripled), "attrs": {"config": tripled.config}}
    seeds = {"source=A,target=B,seed=2": same, "source=A,target=B,seed=1": tripled}
    kw = dict(study="toy", pairs=[["A", "B"]], own=own, transfer={"source=A,target=B": same},
              markers=p, test_indenters=["torus"], trace_frames=20, seeds=seeds,
              seen_indenters=["sphere", "prism", "cone"])
    out = force_study(**kw, translated={"source=A,target=B": p["B"]}, ensemble="paired", ensemble_pairs=8)
    w = np.array(out["attrs"]["ensemble_weights"]["A_B"])
    assert w.shape == (3, 3) and list(w[0]) == list(w[2])
    np.testing.assert_allclose(w[:, :2], 1 / 3, atol=1e-6)   # no read-out labels: shear alike
    assert w[1, 2] < 0.2 < 0.4 < w[0, 2]
    np.testing.assert_allclose(w.sum(0), 1.0, atol=1e-5)
    rows = np.flatnonzero(np.isin(skins["B"]["contact_id"], [3, 7, 11]))     # the torus contacts
    pred = [predict_contacts(load_model(a, "genforce_comp", device=torch_device()), skins["B"]["images"][rows],
                             skins["B"]["contact_id"][rows], skins["B"]["reference"]) for a in (same, tripled)]
    weighted = (w[0] + w[2]) * pred[0] + w[1] * pred[1]
    want = force_metrics(weighted.astype(np.float32), skins["B"]["force"][rows])
    m = out["metrics"]
    assert m["toy/A_B/genforce_comp_ensemble/mae_total"] == pytest.approx(want["mae_total"], rel=1e-4)
    assert m["toy/A_B/genforce_comp_ensemble/r2_fz"] == pytest.approx(want["r2_fz"], rel=1e-4)
    plain = force_study(**kw)["metrics"]
    assert plain["toy/A_B/genforce_comp_ensemble/mae_fz"] > 1.2 * m["toy/A_B/genforce_comp_ensemble/mae_fz"]
    assert {k: v for k, v in m.items() if "ensemble" not in k} == {k: v for k, v in plain.items()
                                                                 if "ensemble" not in k}
    with pytest.raises(InputError, match=r"force_study\[toy\]: ensemble 'median' is not one of \('mean', 'paired'\)"):
        force_study(**kw, ensemble="median")
    with pytest.raises(ValueError, match="ensemble 'paired' weighs the members on paired frames of the "
                                         "training indenters, and seen_indenters names none"):
        force_study(**{**kw, "seen_indenters": ()}, ensemble="paired")
    with pytest.raises(KeyError, match=r"ensemble 'paired' needs translated\['source=A,target=B'\]"):
        force_study(**kw, ensemble="paired", ensemble_pairs=8)


def test_force_study_scores_the_seen_indenters_too(nodes_out, skins):
    """seen_indenters: source_only, genforce and genforce_comp scored on the target's contacts
    of those indenters as well (<method>_seen, and their mean over pairs), never the oracle,
    which trained on them; the unseen metrics are those of a study without them."""
    own, same, stiffer = nodes_out
    kw = dict(study="toy", pairs=[["A", "B"], ["B", "A"]], own=own,
              transfer={"source=A,target=B": same, "source=B,target=A": stiffer},
              markers=skins, test_indenters=["torus"], trace_frames=20)
    plain = force_study(**kw)["metrics"]
    out = force_study(**kw, seen_indenters=["sphere", "cone"])
    m = out["metrics"]
    assert {k: m[k] for k in plain} == plain
    assert len(m) == len(plain) + 3 * 7 * 3                   # 3 methods x 7 metrics x (2 pairs + mean)
    assert not any("oracle_seen" in k for k in m)
    rows = np.flatnonzero(np.isin(skins["A"]["contact_id"], [0, 2, 4, 6, 8, 10]))  # sphere and cone
    pred = predict_contacts(load_model(stiffer, "genforce_comp", device=torch_device()), skins["A"]["images"][rows],
                            skins["A"]["contact_id"][rows], skins["A"]["reference"])
    want = force_metrics(pred, skins["A"]["force"][rows])
    assert m["toy/B_A/genforce_comp_seen/mae_fz"] == pytest.approx(want["mae_fz"])
    assert m["toy/B_A/genforce_comp_seen/r2_fx"] == pytest.approx(want["r2_fx"])
    assert m["toy/B_A/genforce_comp_seen/mae_fz"] != pytest.approx(m["toy/B_A/genforce_comp/mae_fz"])
    assert m["toy/mean/source_only_seen/mae_total"] == pytest.approx(
        (m["toy/A_B/source_only_seen/mae_total"] + m["toy/B_A/source_only_seen/mae_total"]) / 2)
    assert out["attrs"]["seen_frames"] == {"B": len(rows), "A": len(rows)}
    assert bytes(out["figures"]["seen_unseen"][:8]) == PNG
    with pytest.raises(ValueError, match=r"\['torus'\] are both seen and test indenters"):
        force_study(**kw, seen_indenters=["sphere", "torus"])


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
    for method in ("genforce", "genforce_comp"):
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


# ---------------------------------------------------------------------------- paired alignment

def test_batchnorm_alignment_reads_an_affine_copy_of_the_frames_as_the_frames(trained):
    """Target frames drawn at half intensity (an affine copy of their translations in the
    network's input): unaligned, the model reads them far off; aligned on 4 paired contacts,
    it reads 4 other contacts' dimmed frames as it reads their originals."""
    from stages.force.align import align_batchnorm
    model, _, images, _, _ = trained
    frames = np.concatenate(images)
    ids = np.repeat(np.arange(8), 14)
    paired, held = ids < 4, ids >= 4
    dim = frames // 2                                        # markers at 127 instead of 255
    before = {k: v.clone() for k, v in model.state_dict().items()}
    aligned = align_batchnorm(model, frames[paired], dim[paired], REF)
    for k, v in model.state_dict().items():                 # the model itself is untouched
        assert torch.equal(v, before[k]), k
    truth = predict_contacts(model, frames[held], ids[held], REF)
    off = np.abs(predict_contacts(model, dim[held], ids[held], REF) - truth).max()
    on = np.abs(predict_contacts(aligned, dim[held], ids[held], REF) - truth).max()
    assert off > 1.0 and on < 1e-3, (off, on)          # 5.0 N against 1e-4 N here
    same = align_batchnorm(model, frames[paired], frames[paired], REF)   # no gap: no change
    np.testing.assert_allclose(predict_contacts(same, frames[held], ids[held], REF), truth, atol=1e-4)
    with pytest.raises(ValueError, match="paired frames"):
        align_batchnorm(model, frames[:5], frames[:6], REF)


def test_fit_transfer_aligns_its_models_on_paired_target_frames(nodes_out, skins, tiny_config):
    """align "encoder": the transfer trains as before and then moves only its encoder's
    batch-norm statistics, from 20 location-paired frames, so that a target drawing every
    frame at half intensity reads as the unaligned models read the translations; the seed
    models align the same way."""
    _, _, stiffer = nodes_out
    kw = dict(config={**tiny_config, "seq_len": 10}, steps=4, batch_size=2, lr=0.05, seed=0,
              train_indenters=["sphere", "prism", "cone"])
    translated = dict(skins["A"], paired=np.arange(len(skins["A"]["force"])) % 3 == 0)
    dim = dict(translated, images=translated["images"] // 2)
    out = fit_transfer(translated=translated, source_calibration=_calibration_art(1.0),
                       target_calibration=_calibration_art(2.0), source="B", target="A",
                       finetune_steps=0, target_markers=dim, align="encoder", align_pairs=20, **kw)
    assert out["attrs"]["align"] == {"layers": "encoder", "pairs": 20}
    assert stiffer["attrs"]["align"] == {"layers": "none"}
    for method in ("genforce", "genforce_comp"):
        moved = {k for k, v in out[method].items() if not np.array_equal(v, stiffer[method][k])}
        assert moved and all(k.startswith("encoder.") and k.endswith(("running_mean", "running_var"))
                             for k in moved), moved
    ids = skins["A"]["contact_id"]
    frames, dimmed = skins["A"]["images"], dim["images"]
    truth = predict_contacts(load_model(stiffer, "genforce_comp"), frames, ids)
    off = np.abs(predict_contacts(load_model(stiffer, "genforce_comp"), dimmed, ids) - truth).max()
    on = np.abs(predict_contacts(load_model(out, "genforce_comp"), dimmed, ids) - truth).max()
    assert off > 5e-3 and on < 1e-4, (off, on)           # 0.012 N against 3e-6 N here
    transfer = json.loads(json.dumps({"attrs": stiffer["attrs"]}))
    seed = fit_transfer_seed(transfer=transfer, translated=translated, seed=0, finetune_steps=0,
                             target_markers=dim, align="encoder", align_pairs=20,
                             **{k: v for k, v in kw.items() if k != "seed"})
    for k, v in out["genforce_comp"].items():
        np.testing.assert_array_equal(seed["genforce_comp"][k], v)
    with pytest.raises(ValueError, match=r"transfer\[B->A\]: align 'encoder' needs the target's own frames"):
        fit_transfer(translated=skins["A"], source_calibration=_calibration_art(1.0),
                     target_calibration=_calibration_art(2.0), source="B", target="A",
                     finetune_steps=0, align="encoder", **kw)
    with pytest.raises(InputError, match=r"align 'head' is not one of \('none', 'encoder', 'all'\)"):
        fit_transfer(translated=skins["A"], source_calibration=_calibration_art(1.0),   # before training
                     target_calibration=_calibration_art(2.0), source="B", target="A",
                     finetune_steps=0, target_markers=dim, align="head", checkpoint="/nonexistent/x", **kw)


def test_splice_paired_puts_the_targets_own_frames_where_their_locations_are(skins):
    """splice_paired replaces exactly the chosen location-paired frames of the training contacts
    with the target's frame of the same `frame` value, wherever the target's artifact holds it,
    and leaves every other frame as translated."""
    from stages.force.nodes import _read_runs, splice_paired
    n = len(skins["A"]["force"])
    translated = dict(skins["A"], paired=np.arange(n) % 3 == 0)
    order = np.random.default_rng(0).permutation(n)              # the target's rows in another order
    target = {k: (v[order] if isinstance(v, np.ndarray) and len(v) == n else v)
              for k, v in dict(skins["B"], paired=translated["paired"]).items()}
    train = ["sphere", "prism", "cone"]
    runs = contact_runs(translated, train)
    images = _read_runs(translated, "images", runs)
    out, done = splice_paired(images, runs, translated, target, train, 5, "t")
    assert done == 5 and len(out) == len(images)
    changed = [(i, j) for i, (a, b) in enumerate(zip(images, out)) for j in range(len(a))
               if not np.array_equal(a[j], b[j])]
    assert len(changed) == 5
    where = {int(f): r for r, f in enumerate(target["frame"])}
    for i, j in changed:
        row = runs[i][0] + j
        assert translated["paired"][row]
        np.testing.assert_array_equal(out[i][j], target["images"][where[int(translated["frame"][row])]])
    assert np.array_equal(images[0], _read_runs(translated, "images", runs)[0])   # input untouched
    _, every = splice_paired(images, runs, translated, target, train, 0, "t")
    assert every == int(sum(translated["paired"][a:b].sum() for a, b in runs))
    with pytest.raises(ValueError, match=r"t: splice needs the target's own frames"):
        splice_paired(images, runs, translated, None, train, 5, "t")


def test_fit_transfer_splices_the_paired_target_frames(skins, tiny_config):
    """splice "replace": both methods (and the seed models) train on sequences holding the
    target's own paired frames, which changes the weights; "mix" draws every contact as
    translated or as spliced (twice the sequences, the same labels); an unknown mode is the
    user's one-line error before any training."""
    kw = dict(config={**tiny_config, "seq_len": 10}, steps=4, batch_size=2, lr=0.05, seed=0,
              train_indenters=["sphere", "prism", "cone"], source_calibration=_calibration_art(1.0),
              target_calibration=_calibration_art(2.0), source="B", target="A", finetune_steps=0)
    n = len(skins["A"]["force"])
    translated = dict(skins["A"], paired=np.arange(n) % 3 == 0)
    target = dict(translated, images=255 - translated["images"])
    plain = fit_transfer(translated=translated, target_markers=target, **kw)
    spliced = fit_transfer(translated=translated, target_markers=target, splice="replace", align_pairs=8, **kw)
    mixed = fit_transfer(translated=translated, target_markers=target, splice="mix", align_pairs=8, **kw)
    assert (plain["attrs"]["spliced"], spliced["attrs"]["spliced"], mixed["attrs"]["spliced"]) == (0, 8, 8)
    contacts = [out["attrs"]["history"]["genforce_comp"]["pretrain"]["contacts"] for out in (plain, spliced, mixed)]
    assert contacts == [9, 9, 18]
    for method in ("genforce", "genforce_comp"):
        for other in (spliced, mixed):
            assert any(not np.array_equal(v, plain[method][k]) for k, v in other[method].items())
    transfer = json.loads(json.dumps({"attrs": mixed["attrs"]}))
    seed = fit_transfer_seed(transfer=transfer, translated=translated, seed=0, target_markers=target,
                             splice="mix", align_pairs=8,
                             **{k: kw[k] for k in ("config", "steps", "batch_size", "lr", "finetune_steps",
                                                   "train_indenters")})
    assert seed["attrs"]["spliced"] == 8
    for k, v in mixed["genforce_comp"].items():
        np.testing.assert_array_equal(seed["genforce_comp"][k], v)
    with pytest.raises(InputError, match=r"transfer\[B->A\]: splice True is not one of \('none', 'replace', 'mix'\)"):
        fit_transfer(translated=translated, target_markers=target, splice=True, checkpoint="/nonexistent/x", **kw)


# ---------------------------------------------------------------------------- contact shear

def _mesh_art(names):
    """An `indenters` artifact's layout (meshes/<name>/vertices, faces) as a flat mapping."""
    from stages.sim.indenters import indenter_set
    meshes = indenter_set(names)["meshes"]
    return {f"meshes/{n}/{k}": v for n, m in meshes.items() for k, v in m.items()}


def _stick_calibration(stiffness=0.3, depth_mm=2.0, mu=0.8, m=4):
    """A calibration with a shear leg along +x: F_x = stiffness * shift (N/mm), and the attrs
    of a flat 30 mm pad on a 0.1 mm grid pressed by calib_punch to depth_mm."""
    d, f, load, phase = _sheared_calibration(1.0, 0.1, m=m)
    shift = np.zeros((d.size, 2))
    j = np.r_[np.arange(1, m + 1), np.arange(m - 1, -1, -1)] / m
    shift[phase != 0, 0] = np.r_[j, np.zeros(int(np.sum(phase == 3)))][: int(np.sum(phase != 0))]
    shift[phase == 3] = 0.0
    f = f.copy()
    f[(phase == 1) | (phase == 2), 0] = stiffness * shift[(phase == 1) | (phase == 2), 0]
    f[(phase == 1) | (phase == 2), 1] = 0.0
    return {"normalised_depth": d, "force": f, "loading": load, "phase": phase, "shift": shift,
            "depth": d * depth_mm,
            "attrs": {"max_depth_mm": depth_mm, "spacing_mm": 0.1, "pad_mm": [30.0, 30.0],
                      "curvature_radius_mm": 0.0, "indenter": "calib_punch", "mu": mu}}


def test_shear_stiffness_and_contact_shear():
    from stages.force.compensation import contact_shear, shear_stiffness
    assert shear_stiffness(_stick_calibration(0.3)) == pytest.approx(0.3)
    with pytest.raises(ValueError, match="no shear leg"):
        shear_stiffness(_calibration_art(1.0))
    shift = np.array([[0.5, 0.0], [0.0, -1.0], [1.0, 1.0], [1.0, 0.0]])
    # contact radius 1x, 2x (4x the area), 1x, 0 (no contact): F = k sqrt(A / A_p) shift
    area, normal = np.array([12.0, 48.0, 12.0, 0.0]), np.array([-10.0, -10.0, -10.0, -10.0])
    free = contact_shear(shift, area, normal, stiffness=0.3, punch_area=12.0)
    np.testing.assert_allclose(free, [[0.15, 0.0], [0.0, -0.6], [0.3, 0.3], [0.0, 0.0]])
    # capped at mu |Fz| = 0.4 N: the third frame (0.42 N) slides along its own direction
    capped = contact_shear(shift, area, np.full(4, -1.0), stiffness=0.3, punch_area=12.0, mu=0.4)
    np.testing.assert_allclose(capped, [[0.15, 0.0], [0.0, -0.4], [0.4 / np.sqrt(2)] * 2, [0.0, 0.0]])
    with pytest.raises(ValueError, match="calibration contact's area must be positive"):
        contact_shear(shift, area, normal, stiffness=0.3, punch_area=0.0)
    with pytest.raises(ValueError, match=r"must be \(N,2\), \(N,\), \(N,\)"):
        contact_shear(shift[:, :1], area, normal, stiffness=0.3, punch_area=12.0)


def test_slip_shear_carries_the_slip_through_each_contact():
    """slip_shear walks each contact from rest: sticking steps of stiffness * sqrt(A / A_p) times
    the shift's step, the force held to mu |Fz| where it would exceed it, and the slip kept, so a
    pad that slid out is sheared back when the indenter returns (contact_shear reads 0 there)."""
    from stages.force.compensation import contact_shear, slip_shear
    # one contact out 1.5 mm along x and back, k = 0.4 N/mm (area = the punch's), cap 0.3 N
    shift = np.array([[0.0, 0.0], [0.5, 0.0], [1.0, 0.0], [1.5, 0.0], [1.0, 0.0], [0.5, 0.0], [0.0, 0.0]])
    area, normal = np.full(7, 12.0), np.full(7, -0.6)
    out = slip_shear(shift, area, normal, np.zeros(7, int), stiffness=0.4, punch_area=12.0, mu=0.5)
    # 0, 0.2, 0.3 (slides: 0.4 wanted), 0.3 (slides on), then back 0.1, -0.1, -0.3 (slides back)
    np.testing.assert_allclose(out[:, 0], [0.0, 0.2, 0.3, 0.3, 0.1, -0.1, -0.3], atol=1e-12)
    assert np.all(out[:, 1] == 0)
    frame = contact_shear(shift, area, normal, stiffness=0.4, punch_area=12.0, mu=0.5)
    np.testing.assert_allclose(frame[:, 0], [0.0, 0.2, 0.3, 0.3, 0.3, 0.2, 0.0], atol=1e-12)
    # a second contact starts from rest: the same walk, along -y, at 4x the area (2x stiffer)
    # and a 1 N cap: 0, -0.4, -0.8, -1 (slides), -0.6, -0.2, +0.2
    two = slip_shear(np.r_[shift, -shift[:, ::-1]], np.r_[area, 4 * area], np.r_[normal, np.full(7, -2.0)],
                     np.repeat([3, 8], 7), stiffness=0.4, punch_area=12.0, mu=0.5)
    np.testing.assert_array_equal(two[:7], out)
    np.testing.assert_allclose(two[7:, 1], [0.0, -0.4, -0.8, -1.0, -0.6, -0.2, 0.2], atol=1e-12)
    # a diagonal slide keeps its direction on the friction circle
    diag = slip_shear(np.array([[0.0, 0.0], [2.0, 2.0]]), np.full(2, 12.0), np.full(2, -1.0), np.zeros(2, int),
                      stiffness=1.0, punch_area=12.0, mu=0.5)
    np.testing.assert_allclose(diag[1], [0.5 / np.sqrt(2)] * 2)
    with pytest.raises(ValueError, match="slip_shear: a contact's frames are not contiguous"):
        slip_shear(shift[:3], area[:3], normal[:3], np.array([0, 1, 0]), stiffness=0.4, punch_area=12.0, mu=0.5)
    with pytest.raises(ValueError, match="slip_shear: friction coefficient mu must be positive, got 0.0"):
        slip_shear(shift, area, normal, np.zeros(7, int), stiffness=0.4, punch_area=12.0, mu=0.0)
    with pytest.raises(ValueError, match=r"contact_id \(6,\) must be \(N,2\), \(N,\), \(N,\), \(N,\)"):
        slip_shear(shift, area, normal, np.zeros(6, int), stiffness=0.4, punch_area=12.0, mu=0.5)


def test_contact_areas_match_the_indenters_geometry():
    """The rigid overlap with a flat pad: a 4 mm flat punch touches its whole face at any depth,
    a sphere of radius 4 mm the disc of radius sqrt(2 R d - d^2)."""
    from stages.force.nodes import _pad_spec, contact_areas
    spec = _pad_spec(_stick_calibration()["attrs"])
    assert spec["grid"] == [301, 301]
    depth = np.array([0.1, 0.5, 1.0, 0.1, 0.5, 1.0])
    area = contact_areas(_mesh_art(["sphere", "calib_punch"]), ["sphere", "calib_punch"],
                         [0, 0, 0, 1, 1, 1], [0, 0, 0, 1, 1, 1], np.zeros((6, 2)), depth, spec)
    hertz = np.pi * (2 * 4.0 * depth[:3] - depth[:3] ** 2)
    np.testing.assert_allclose(area[:3], hertz, rtol=0.05)
    np.testing.assert_allclose(area[3:], np.pi * 2.0 ** 2, rtol=0.03)


def _contact_translated(depth_mm):
    """Two contacts (sphere, then calib_punch) of 6 frames each: pressed to depth_mm in 3 steps
    (phase 0), sheared 1 mm along +y (phase 1), released (phase 3); normalised depth = depth /
    depth_mm; F_z = -2 N per normalised depth, F_y = 0.5 N per mm of shift (a sliding source)."""
    nd = np.array([1 / 3, 2 / 3, 1.0, 1.0, 1.0, 0.5])
    phase = np.array([0, 0, 0, 1, 1, 3], np.int8)
    shift = np.zeros((6, 2))
    shift[3:5, 1] = [0.5, 1.0]
    nd, phase, shift = np.tile(nd, 2), np.tile(phase, 2), np.tile(shift, (2, 1))
    force = np.c_[np.zeros(12), 0.5 * shift[:, 1], -2.0 * nd].astype(np.float32)
    position = np.c_[shift + np.array([1.0, -1.0]), -nd * depth_mm]
    return {"force": force, "normalised_depth": nd, "depth": nd * depth_mm, "phase": phase,
            "shift": shift, "position": position, "contact_id": np.repeat([0, 1], 6),
            "indenter_id": np.repeat([0, 1], 6), "indenters": np.array(["sphere", "calib_punch"], object),
            "frame": np.arange(12)}


def test_contact_labels_by_which_collection_presses_deeper():
    """Mode "contact" gives the target's sticking-contact shear at the chosen frames where its
    collection presses deeper than the source's (source 1 mm, target 3 mm), the compensated
    shear where it presses as deep (within 10%), and where it presses shallower its sliding
    contact's (slip_shear; none without a friction coefficient)."""
    from stages.force.compensation import contact_shear, slip_shear
    from stages.force.nodes import _pad_spec, contact_areas, contact_labels
    meshes = _mesh_art(["sphere", "calib_punch"])
    tgt = _stick_calibration(0.2, depth_mm=3.0, mu=0.9)
    translated = _contact_translated(1.0)
    comp = translated["force"] * np.float32(1.5)
    rows = np.array([1, 3, 4, 10, 11])
    shear, info = contact_labels(translated, tgt, comp, 1.0, indenters=meshes, rows=rows, name="t")
    assert info["labels"] == "contact" and info["source_depth_mm"] == 1.0 and info["target_depth_mm"] == 3.0
    assert info["stiffness_n_per_mm"] == pytest.approx(0.2) and info["mu"] == 0.9
    assert info["punch_area_mm2"] == pytest.approx(np.pi * 4.0, rel=0.03)
    spec = _pad_spec(tgt["attrs"])
    area = contact_areas(meshes, translated["indenters"], translated["indenter_id"][rows],
                         translated["contact_id"][rows], np.tile([1.0, -1.0], (rows.size, 1)),
                         translated["normalised_depth"][rows] * 3.0, spec)
    want = contact_shear(translated["shift"][rows], area, comp[rows, 2], stiffness=0.2,
                         punch_area=info["punch_area_mm2"], mu=0.9)
    assert shear.shape == (5, 2)
    np.testing.assert_allclose(shear, want, rtol=1e-6)
    # the sphere pressed 3 mm: a contact radius sqrt(15) = 3.9 mm against the punch's 2 mm
    assert shear[2, 1] == pytest.approx(0.2 * np.sqrt(15.0) / 2.0, rel=0.05)
    assert shear[3, 1] == pytest.approx(0.2, rel=0.02)                  # the punch: the calibration's
    assert np.all(shear[[0, 4]] == 0)                                   # no shift, no shear
    for depth_mm in (1.0, 1.08, 0.93):                                  # as deep, within 10%
        same, info = contact_labels(translated, _stick_calibration(0.2, depth_mm=depth_mm), comp, 1.0,
                                    indenters=None, rows=rows, name="t")
        np.testing.assert_array_equal(same, comp[rows, :2])
        assert info == {"labels": "compensated", "source_depth_mm": 1.0, "target_depth_mm": depth_mm}
    # shallower: the slip law, walked over the whole contacts the rows fall in (both here)
    shallow = _stick_calibration(0.2, depth_mm=0.5, mu=0.05)
    slip, info = contact_labels(translated, shallow, comp, 1.0, indenters=meshes, rows=rows, name="t")
    assert info["labels"] == "slip" and info["target_depth_mm"] == 0.5 and info["mu"] == 0.05
    whole = contact_areas(meshes, translated["indenters"], translated["indenter_id"], translated["contact_id"],
                          np.tile([1.0, -1.0], (12, 1)), translated["normalised_depth"] * 0.5, spec)
    walked = slip_shear(translated["shift"], whole, comp[:, 2], translated["contact_id"], stiffness=0.2,
                        punch_area=info["punch_area_mm2"], mu=0.05)
    np.testing.assert_allclose(slip, walked[rows], rtol=1e-6)
    # the punch (|Fz| 3 N pressed): 0.1 N at 0.5 mm, at 1 mm the 0.2 N it wants held to 0.05 x 3 N
    # = 0.15 N (it slid 0.25 mm), and back at the start, released to |Fz| 1.5 N, -0.05 N
    assert slip[3, 1] == pytest.approx(0.15) and slip[4, 1] == pytest.approx(-0.05, abs=0.01)
    none, info = contact_labels(translated, dict(shallow, attrs={**shallow["attrs"], "mu": None}), comp, 1.0,
                                indenters=None, rows=rows, name="t")
    assert none is None and info == {"labels": "none", "source_depth_mm": 1.0, "target_depth_mm": 0.5}
    # k scales the target's depth: 1 mm calibration, collection twice as deep
    assert contact_labels(translated, _stick_calibration(0.2, depth_mm=1.0), comp, 2.0, indenters=meshes,
                          rows=rows, name="t")[1]["labels"] == "contact"
    with pytest.raises(ValueError, match="t: compensation 'contact' needs the indenters' meshes"):
        contact_labels(translated, tgt, comp, 1.0, indenters=None, rows=rows, name="t")
    with pytest.raises(ValueError, match=r"needs the target calibration's attrs \['spacing_mm'\]"):
        bad = dict(tgt, attrs={k: v for k, v in tgt["attrs"].items() if k != "spacing_mm"})
        contact_labels(translated, bad, comp, 1.0, indenters=meshes, rows=rows, name="t")


def test_shear_readout_gains_and_scale_shear(trained):
    """scale_shear multiplies a model's Fx, Fy output by its gains and leaves Fz; shear_readout
    finds the gain from the model's reading of the frames to their shear, clipped to
    READOUT_GAIN_RANGE, 1 where the model reads none."""
    from stages.force.nodes import READOUT_GAIN_RANGE, _target_predictions, scale_shear, shear_readout
    model, _, images, _, _ = trained
    art = {"images": np.concatenate(images), "reference": REF,
           "contact_id": np.repeat(np.arange(len(images)), [len(x) for x in images])}
    rows = np.array([40, 3, 17, 90, 91, 60])                            # any order, several contacts
    full = predict_contacts(model, art["images"], art["contact_id"], REF)
    np.testing.assert_allclose(_target_predictions(model, art, rows), full[rows], rtol=1e-5, atol=1e-6)
    read = full[rows, :2]
    assert shear_readout(model, art, rows, read * [3.0, 0.5]) == pytest.approx((3.0, 0.5), rel=1e-5)
    assert shear_readout(model, art, rows, read * [10.0, -1.0]) == READOUT_GAIN_RANGE[::-1]
    with pytest.raises(ValueError, match="5 shear labels for 6 frames"):
        shear_readout(model, art, rows, read[:5])
    copy = from_arrays(to_arrays(model), model.config)
    scale_shear(copy, (2.0, 0.5))
    np.testing.assert_allclose(predict_contacts(copy, art["images"], art["contact_id"], REF),
                               full * [2.0, 0.5, 1.0], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(copy.config["force_min"][:2], np.multiply(model.config["force_min"][:2], [2.0, 0.5]),
                               rtol=1e-5)
    assert copy.config["force_max"][2] == pytest.approx(model.config["force_max"][2])


def test_fit_transfer_shear_readout_scales_the_shear_it_reads(skins, tiny_config):
    """readout "shear": genforce_comp is readout "none"'s model with its shear range scaled by
    the read-out gains on the paired frames (stored, with the shear they were fitted to: in
    mode "contact", where the target presses deeper, its contact shear), which a seed model of
    the same seed reproduces bit for bit; where the target presses shallower, its sliding
    contact's shear (slip_shear), and nothing without a friction coefficient."""
    from stages.force.nodes import _paired_rows, contact_labels, recorded_compensation, shear_readout
    n = len(skins["A"]["force"])
    shift = 0.5 * np.asarray(skins["A"]["force"], float)[:, :2]        # mm: the synthetic shear's cause
    nd = np.asarray(skins["A"]["normalised_depth"], float)
    translated = dict(skins["A"], paired=np.arange(n) % 2 == 0, shift=shift, depth=nd * 1.0,
                      position=np.c_[shift + 2.0, -nd])
    target = dict(skins["B"], paired=translated["paired"])
    train = ["sphere", "prism", "cone"]
    kw = dict(config={**tiny_config, "seq_len": 10}, steps=4, batch_size=2, lr=0.05, seed=0,
              finetune_steps=0, train_indenters=train, source="B", target="A", translated=translated,
              target_markers=target, source_calibration=_stick_calibration(0.5, depth_mm=1.0, mu=0.5),
              indenters=_mesh_art([*train, "calib_punch"]), align_pairs=12, splice="replace")
    deeper = _stick_calibration(1.0, depth_mm=3.0, mu=0.9)
    axes = fit_transfer(target_calibration=deeper, compensation="contact", readout="none", **kw)
    contact = fit_transfer(target_calibration=deeper, compensation="contact", readout="shear", **kw)
    info = contact["attrs"]["shear_readout"]
    assert info["labels"] == "contact" and info["pairs"] == 12 and "shear_readout" not in axes["attrs"]
    assert all(0.25 <= g <= 4.0 and g != 1.0 for g in info["gain"])    # in range, and applied
    frames, rows = _paired_rows(translated, target, train, 12)
    np.testing.assert_array_equal(contact["readout_frame"], frames)
    assert contact["readout_shear"].shape == (12, 2) and np.abs(contact["readout_shear"]).max() > 0
    model = load_model({"genforce_comp": axes["genforce_comp"], "attrs": axes["attrs"]}, "genforce_comp")
    gains = shear_readout(model, target, rows[1], contact["readout_shear"])
    assert info["gain"] == pytest.approx(list(gains))
    for k, v in axes["genforce_comp"].items():
        want = v * np.array([*gains, 1.0], np.float32) if k in ("force_min", "force_max") else v
        np.testing.assert_allclose(contact["genforce_comp"][k], want, rtol=1e-6)
    for k, v in axes["genforce"].items():
        np.testing.assert_array_equal(contact["genforce"][k], v)
    stored = {"attrs": json.loads(json.dumps(contact["attrs"])), "readout_frame": contact["readout_frame"],
              "readout_shear": contact["readout_shear"]}
    seed_kw = {k: kw[k] for k in ("config", "steps", "batch_size", "lr", "finetune_steps", "train_indenters",
                                  "target_markers", "align_pairs", "splice")}
    seed = fit_transfer_seed(transfer=stored, translated=translated, seed=0, **seed_kw)
    assert seed["attrs"]["shear_readout"]["gain"] == info["gain"]
    for k, v in contact["genforce_comp"].items():
        np.testing.assert_array_equal(seed["genforce_comp"][k], v)
    with pytest.raises(ValueError, match="shear read-out frames are not this node's paired frames"):
        fit_transfer_seed(transfer={**stored, "readout_frame": frames + 1}, translated=translated, seed=0,
                          **seed_kw)
    shallower = _stick_calibration(0.2, depth_mm=0.5, mu=0.9)
    slid = fit_transfer(target_calibration=shallower, compensation="contact", readout="shear", **kw)
    info = slid["attrs"]["shear_readout"]
    assert info["labels"] == "slip" and info["pairs"] == 12 and info["target_depth_mm"] == pytest.approx(0.5 * nd.max())
    comp = recorded_compensation(translated, slid["attrs"])
    want, _ = contact_labels(translated, shallower, comp, 1.0, indenters=kw["indenters"], rows=rows[0], name="t")
    np.testing.assert_array_equal(slid["readout_shear"], want)
    plain = fit_transfer(target_calibration=shallower, compensation="contact", readout="none", **kw)
    read = shear_readout(load_model({"genforce_comp": plain["genforce_comp"], "attrs": plain["attrs"]},
                                    "genforce_comp"), target, rows[1], want)
    assert info["gain"] == pytest.approx(list(read)) and read != (1.0, 1.0)
    # no friction coefficient recorded: nothing is read
    frictionless = dict(shallower, attrs={**shallower["attrs"], "mu": None})
    none = fit_transfer(target_calibration=frictionless, compensation="contact", readout="shear", **kw)
    assert none["attrs"]["shear_readout"] == {"labels": "none", "source_depth_mm": pytest.approx(nd.max()),
                                              "target_depth_mm": pytest.approx(0.5 * nd.max()), "pairs": 12}
    assert "readout_shear" not in none
    for k, v in plain["genforce_comp"].items():
        np.testing.assert_array_equal(none["genforce_comp"][k], v)
    # as deep: the compensated labels' shear; mode "axes": those, whatever the depths
    for cal, mode in ((_stick_calibration(0.2, depth_mm=1.0), "contact"), (deeper, "axes")):
        out = fit_transfer(target_calibration=cal, compensation=mode, readout="shear", **kw)
        assert out["attrs"]["shear_readout"]["labels"] == "compensated"
        comp = compensate(np.asarray(translated["force"], np.float32), nd, loading_mask(translated["phase"]),
                          curves_from_calibration(kw["source_calibration"]), curves_from_calibration(cal),
                          mode=mode)
        np.testing.assert_allclose(out["readout_shear"], comp[rows[0], :2], rtol=1e-6)
    # one material: genforce_comp is genforce, read out as one model
    same = {k: kw[k] for k in kw if k != "source_calibration"} | {"source_calibration": kw["source_calibration"],
                                                                  "target_calibration": kw["source_calibration"]}
    one = fit_transfer(compensation="contact", readout="shear", **same)
    unread = fit_transfer(compensation="contact", readout="none", **same)
    assert one["attrs"]["compensation_identity"] and one["attrs"]["shear_readout"]["labels"] == "compensated"
    gain = np.array([*one["attrs"]["shear_readout"]["gain"], 1.0], np.float32)
    for k, v in unread["genforce"].items():
        np.testing.assert_array_equal(one["genforce_comp"][k], one["genforce"][k])
        np.testing.assert_allclose(one["genforce"][k], v * gain if k in ("force_min", "force_max") else v, rtol=1e-6)
    with pytest.raises(InputError, match=r"transfer\[B->A\]: readout 'axes' is not one of \('none', 'shear'\)"):
        fit_transfer(target_calibration=deeper, readout="axes", checkpoint="/nonexistent/x", **kw)


def test_fz_readout_gain_raises_only_and_scale_fz(trained):
    """fz_readout: raw is the least-squares gain from the model's Fz on the target's frames to
    its Fz on the translations paired with them; the gain raises only (clipped to [1, 4]);
    scale_fz multiplies Fz by it and leaves the shear."""
    from stages.force.nodes import _target_predictions, fz_readout, scale_fz
    model, _, images, _, _ = trained
    art = {"images": np.concatenate(images), "reference": REF,
           "contact_id": np.repeat(np.arange(len(images)), [len(x) for x in images])}
    full = predict_contacts(model, art["images"], art["contact_id"], REF)
    order = np.argsort(np.abs(full[:, 2]))
    weak, strong = order[:6], order[-6:]                       # the target reads these low, those high
    fz = lambda rows: _target_predictions(model, art, rows)[:, 2].astype(float)
    want = float(np.sum(fz(weak) * fz(strong)) / np.sum(fz(weak) ** 2))
    assert want > 1.5
    gain, raw = fz_readout(model, art, art, np.stack([strong, weak]))
    assert raw == pytest.approx(want, rel=1e-5) and gain == pytest.approx(min(want, 4.0), rel=1e-5)
    gain, raw = fz_readout(model, art, art, np.stack([weak, strong]))      # reads the target higher
    assert raw == pytest.approx(1.0 / want, rel=0.5) and raw < 1.0 and gain == 1.0
    assert fz_readout(model, art, art, np.stack([weak, weak])) == (1.0, pytest.approx(1.0, abs=1e-6))
    copy = from_arrays(to_arrays(model), model.config)
    scale_fz(copy, 1.5)
    np.testing.assert_allclose(predict_contacts(copy, art["images"], art["contact_id"], REF),
                               full * [1.0, 1.0, 1.5], rtol=1e-5, atol=1e-5)
    assert copy.config["force_min"][:2] == model.config["force_min"][:2]


def test_fit_transfer_fz_readout_up(skins, tiny_config):
    """fz_readout "up": genforce_comp is fz_readout "none"'s model with its Fz range scaled by
    max(1, raw), raw read on the paired frames without labels (attrs fz_readout); genforce is
    untouched; a seed of the same seed reproduces it bit for bit; a bad mode is the user's
    one-line error before any training."""
    from stages.force.nodes import _paired_rows, fz_readout
    kw = dict(config={**tiny_config, "seq_len": 10}, steps=40, batch_size=2, lr=0.05, seed=0,
              train_indenters=["sphere", "prism", "cone"], source_calibration=_calibration_art(1.0),
              target_calibration=_calibration_art(2.0), source="B", target="A", finetune_steps=0)
    n = len(skins["A"]["force"])
    translated = dict(skins["A"], paired=np.arange(n) % 3 == 0)
    fainter = (np.asarray(translated["images"], np.float32) * 0.6).astype(np.uint8)   # weaker contacts
    target = dict(translated, images=fainter)
    common = dict(translated=translated, target_markers=target, align_pairs=8, **kw)
    plain = fit_transfer(fz_readout="none", **common)
    up = fit_transfer(fz_readout="up", **common)
    assert "fz_readout" not in plain["attrs"]
    info = up["attrs"]["fz_readout"]
    _, rows = _paired_rows(translated, target, kw["train_indenters"], 8)
    gain, raw = fz_readout(load_model(plain, "genforce_comp"), translated, target, rows)
    assert info == {"mode": "up", "gain": pytest.approx(gain), "raw": pytest.approx(raw), "pairs": 8}
    assert info["gain"] == pytest.approx(max(1.0, info["raw"])) and info["raw"] > 1.0   # fainter: read lower
    for k, v in plain["genforce_comp"].items():
        want = v * np.array([1.0, 1.0, gain], np.float32) if k in ("force_min", "force_max") else v
        np.testing.assert_allclose(up["genforce_comp"][k], want, rtol=1e-6)
    for k, v in plain["genforce"].items():
        np.testing.assert_array_equal(up["genforce"][k], v)
    transfer = json.loads(json.dumps({"attrs": up["attrs"]}))
    seed = fit_transfer_seed(transfer=transfer, translated=translated, seed=0, target_markers=target,
                             align_pairs=8, **{k: kw[k] for k in ("config", "steps", "batch_size", "lr",
                                                                 "finetune_steps", "train_indenters")})
    assert seed["attrs"]["fz_readout"] == info
    for k, v in up["genforce_comp"].items():
        np.testing.assert_array_equal(seed["genforce_comp"][k], v)
    with pytest.raises(InputError, match=r"transfer\[B->A\]: fz_readout 'down' is not one of \('none', 'up'\)"):
        fit_transfer(fz_readout="down", checkpoint="/nonexistent/x", **common)


# ---------------------------------------------------------------------------- linear Fz read

def test_image_statistics_of_a_known_change(tiny_config):
    """A frame that brightens 8 of 64 pixels by 0.5 and darkens 4 by 0.02 (under the 0.05
    threshold): mean brightening 4/64, darkening 0.08/64, shares 8/64 and 0."""
    from stages.force.model import image_statistics
    x = torch.zeros(2, 1, 8, 8)
    x[1, 0, 0, :] = 0.5
    x[1, 0, 1, :4] = -0.02
    s = image_statistics(x).numpy()
    np.testing.assert_allclose(s, [[0, 0, 0, 0], [4 / 64, 0.08 / 64, 8 / 64, 0]], rtol=1e-6, atol=1e-9)
    stacked = torch.cat([x + 0.25, torch.full_like(x, 0.25)], 1)     # "stack": image and reference
    np.testing.assert_allclose(image_statistics(stacked, "stack").numpy(), s, rtol=1e-5, atol=1e-7)


def test_fit_linear_fz_recovers_a_linear_law_and_the_targets_scale():
    """Labels linear in the statistics give back their coefficients; where the target shows a
    statistic at twice the translations' size (paired frames), that coefficient halves, so the
    read of the target's frames gives the labels."""
    from stages.force.model import fit_linear_fz
    rng = np.random.default_rng(0)
    X = rng.uniform(0, 0.2, (200, 4))
    c, b = np.array([-30.0, -5.0, 10.0, 2.0]), 0.7
    coef, intercept, info = fit_linear_fz(X, X @ c + b)
    np.testing.assert_allclose(coef, c, rtol=1e-3)
    assert abs(intercept - b) < 1e-3 and info["r2"] > 0.9999 and info["scale"] == [1.0] * 4
    paired = X[:30]
    coef2, intercept2, info2 = fit_linear_fz(X, X @ c + b, translated=paired, target=paired * [2, 1, 1, 1])
    np.testing.assert_allclose(info2["scale"], [2, 1, 1, 1], rtol=1e-6)
    np.testing.assert_allclose(coef2, c / [2, 1, 1, 1], rtol=1e-3)
    target_frames = X * [2, 1, 1, 1]
    np.testing.assert_allclose(target_frames @ coef2 + intercept2, X @ c + b, atol=1e-2)
    with pytest.raises(ValueError, match=r"fit_linear_fz: statistics \(200, 3\) and labels \(200,\)"):
        fit_linear_fz(X[:, :3], X @ c)


def test_linear_fz_read_blends_fz_past_the_range_and_leaves_shear(trained):
    """With weight w the model's Fz is (1 - w) x the network's + w x the linear read, which is
    not clipped to the force range; shear is unchanged; streaming reads the same; the read
    travels with the arrays, and arrays stored without it load with the network's Fz alone."""
    from stages.force.model import image_statistics, prepare
    model, _, images, _, _ = trained
    seq = images[0]
    plain = predict_sequence(model, seq)
    blended = from_arrays(to_arrays(model), model.config)
    coef, b = np.array([-900.0, 50.0, -20.0, 0.0], np.float32), -0.5
    blended.set_linear_fz(coef, b, 0.25)
    got = predict_sequence(blended, seq)
    lin = image_statistics(prepare(seq, REF, model.config)).numpy() @ coef + b
    np.testing.assert_allclose(got[:, :2], plain[:, :2], atol=1e-6)
    np.testing.assert_allclose(got[:, 2], 0.75 * plain[:, 2] + 0.25 * lin, atol=1e-4)
    assert got[:, 2].min() < blended.config["force_min"][2]          # read past the range
    stream = StreamingPredictor(blended)
    np.testing.assert_allclose(np.stack([stream.step(f) for f in seq]), got, atol=1e-4)
    back = from_arrays(to_arrays(blended), blended.config)
    np.testing.assert_allclose(predict_sequence(back, seq), got, atol=1e-6)
    old = {k: v for k, v in to_arrays(blended).items() if k not in ("fz_linear", "fz_weight")}
    np.testing.assert_allclose(predict_sequence(from_arrays(old, model.config), seq), plain, atol=1e-6)
    with pytest.raises(ValueError, match=r"linear Fz read: weight 1.5 is not in \[0, 1\]"):
        blended.set_linear_fz(coef, b, 1.5)
    with pytest.raises(ValueError, match=r"linear Fz read: 4 finite coefficients"):
        blended.set_linear_fz(coef[:3], b, 0.5)


def test_fit_transfer_linear_fz_on_the_looks_it_names_only(skins, tiny_config):
    """linear_fz {"taxel": 0.5, "tactip": 0.5}: a target skin of a look it names gets the linear
    read in both models (fitted on the translations, scaled on the paired frames; attrs
    linear_fz), a GelSight none, the same weights either way; the seed models read the
    transfer's; a bad weight or a key that is no look is the user's one-line error before any
    training."""
    kw = dict(config={**tiny_config, "seq_len": 10}, steps=4, batch_size=2, lr=0.05, seed=0,
              train_indenters=["sphere", "prism", "cone"], source_calibration=_calibration_art(1.0),
              target_calibration=_calibration_art(2.0), source="B", target="A", finetune_steps=0)
    n = len(skins["A"]["force"])
    translated = dict(skins["A"], paired=np.arange(n) % 3 == 0)
    wider = np.maximum(translated["images"], np.roll(translated["images"], 1, axis=-1))   # wider blobs
    target = dict(translated, images=wider)
    looks = {"taxel": 0.5, "tactip": 0.5}
    taxels = fit_transfer(translated=translated, target_markers=target, align_pairs=8,
                          linear_fz=looks, target_spec={"source": "taxels", "look": "taxel"}, **kw)
    render = fit_transfer(translated=translated, target_markers=target, align_pairs=8,
                          linear_fz=looks, target_spec={"source": "render", "look": "gelsight"}, **kw)
    assert "linear_fz" not in render["attrs"]
    info = taxels["attrs"]["linear_fz"]
    assert set(info) == {"genforce", "genforce_comp"} and info["genforce_comp"]["pairs"] == 8
    assert info["genforce_comp"]["weight"] == 0.5 and info["genforce_comp"]["scale"] != [1.0] * 4
    for m in ("genforce", "genforce_comp"):
        assert float(taxels[m]["fz_weight"][0]) == 0.5 and float(render[m]["fz_weight"][0]) == 0.0
        for k, v in render[m].items():
            if k not in ("fz_linear", "fz_weight"):
                np.testing.assert_array_equal(taxels[m][k], v)
    ids = target["contact_id"]
    a = predict_contacts(load_model(taxels, "genforce_comp"), target["images"], ids)
    b = predict_contacts(load_model(render, "genforce_comp"), target["images"], ids)
    np.testing.assert_array_equal(a[:, :2], b[:, :2])
    assert np.abs(a[:, 2] - b[:, 2]).max() > 1e-3
    transfer = json.loads(json.dumps({"attrs": taxels["attrs"]}))
    seed = fit_transfer_seed(transfer=transfer, translated=translated, seed=0, target_markers=target,
                             align_pairs=8, **{k: kw[k] for k in ("config", "steps", "batch_size", "lr",
                                                                 "finetune_steps", "train_indenters")})
    for k, v in taxels["genforce_comp"].items():
        np.testing.assert_array_equal(seed["genforce_comp"][k], v)
    with pytest.raises(InputError, match=r"transfer\[B->A\]: linear_fz\['tactip'\] must be a number in \[0, 1\], got 'half'"):
        fit_transfer(translated=translated, target_markers=target, linear_fz={"tactip": "half"},
                     target_spec={"look": "tactip"}, checkpoint="/nonexistent/x", **kw)
    with pytest.raises(InputError, match=r"transfer\[B->A\]: linear_fz names \['taxels'\], which are not looks "
                                         r"\['none', 'gelsight', 'tactip', 'taxel'\]"):
        fit_transfer(translated=translated, target_markers=target, linear_fz={"taxels": 0.5},
                     target_spec={"look": "taxel"}, checkpoint="/nonexistent/x", **kw)


def test_fit_own_linear_fz_on_a_taxel_skin(nodes_out, skins):
    """The skin's own model (oracle, source-only) of a taxel-drawn skin reads Fz with the linear
    read too, fitted on its own frames and labels (no paired frames, scale 1); the network's
    weights are those of the plain fit."""
    own, _, _ = nodes_out
    kw = dict(config=own["A"]["attrs"]["config"] | own["A"]["attrs"]["train"], steps=4, batch_size=2,
              lr=0.05, seed=0, train_indenters=["sphere", "prism", "cone"])
    kw["config"] = {k: v for k, v in kw["config"].items() if k not in ("force_min", "force_max")}
    out = fit_own(markers=skins["A"], skin="A", linear_fz={"taxel": 0.5}, skin_spec={"look": "taxel"}, **kw)
    info = out["attrs"]["linear_fz"]
    assert info["pairs"] == 0 and info["scale"] == [1.0] * 4 and info["weight"] == 0.5 and 0 < info["r2"] <= 1
    assert float(out["weights"]["fz_weight"][0]) == 0.5 and float(own["A"]["weights"]["fz_weight"][0]) == 0.0
    for k, v in own["A"]["weights"].items():
        if k not in ("fz_linear", "fz_weight"):
            np.testing.assert_array_equal(out["weights"][k], v)
    with pytest.raises(InputError, match=r"own\[A\]: linear_fz must map a skin's look to a weight"):
        fit_own(markers=skins["A"], skin="A", linear_fz=[0.5], skin_spec={"look": "taxel"}, **kw)
