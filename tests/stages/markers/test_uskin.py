"""uSkin: taxel signals from displacement, signal-to-marker geometry, XELA message parsing."""

import cv2
import numpy as np
import pytest

from stages.markers.patterns import USKIN_PAD_MM, rasterize, uskin_pattern
from stages.markers.uskin import (BASE_AREA, GAINS, MID_SCALE, signal_to_marker, taxel_centres,
                                  taxel_sequence, taxel_signals, taxel_weights)
from tests.helpers import drain

PAD_W, PAD_H = USKIN_PAD_MM
GRID_X = (np.arange(31) - 15) * 0.8          # the ci grid of the uskin twin
GRID_Y = (np.arange(29) - 14) * 0.8
SIZE = (128, 128)
PX_PER_MM2 = (SIZE[1] / PAD_W) * (SIZE[0] / PAD_H)
BASE = np.full((16, 3), MID_SCALE, np.int32)


def uniform(n, ux=0.0, uy=0.0, uz=0.0):
    disp = np.zeros((n, GRID_Y.size, GRID_X.size, 3), np.float32)
    disp[..., 0], disp[..., 1], disp[..., 2] = ux, uy, uz
    return disp


def test_uniform_shear_and_press_read_gain_times_displacement():
    sig = taxel_signals(uniform(50, ux=0.5), GRID_X, GRID_Y, noise=5.0, seed=1)
    assert sig.shape == (50, 16, 3) and sig.dtype == np.int32
    mean = sig.mean(0)
    np.testing.assert_allclose(mean[:, 0], MID_SCALE + GAINS[0] * 0.5, atol=5)   # 37768 on every taxel
    np.testing.assert_allclose(mean[:, 1:], MID_SCALE, atol=5)                   # y, z unchanged
    assert 4.0 < (sig - mean).std() < 6.0                                        # the noise
    press = taxel_signals(uniform(1, uz=-0.25), GRID_X, GRID_Y, noise=0.0)[0]
    assert (press[:, 2] == MID_SCALE + GAINS[2] * 0.25).all()                    # pressing raises z
    assert (press[:, :2] == MID_SCALE).all()


def test_z_variant_ignores_lateral_motion():
    sig = taxel_signals(uniform(40, ux=0.5, uy=-0.3, uz=-0.1), GRID_X, GRID_Y, noise=5.0,
                        variant="z", seed=3)
    np.testing.assert_allclose(sig[..., :2].mean(0), MID_SCALE, atol=5)
    np.testing.assert_allclose(sig[..., 2].mean(0), MID_SCALE + GAINS[2] * 0.1, atol=5)


def test_signals_are_seeded_and_clipped():
    a = taxel_signals(uniform(2, ux=0.1), GRID_X, GRID_Y, seed=7)
    assert np.array_equal(a, taxel_signals(uniform(2, ux=0.1), GRID_X, GRID_Y, seed=7))
    assert not np.array_equal(a, taxel_signals(uniform(2, ux=0.1), GRID_X, GRID_Y, seed=8))
    big = taxel_signals(uniform(1, ux=10.0, uy=-10.0), GRID_X, GRID_Y)[0]
    assert (big[:, 0] == 65535).all() and (big[:, 1] == 0).all()


def test_cell_mean_and_gaussian_weighting():
    """Displacement only inside cell (row 1, col 2) reaches taxel 6 alone with cell means; a
    Gaussian-weighted reading spreads some of it to the neighbours."""
    disp = uniform(1)
    cx, cy = taxel_centres()[6]
    inside = (np.abs(GRID_X - cx) < 1.5)[None, :] & (np.abs(GRID_Y - cy) < 1.5)[:, None]
    disp[0, inside, 0] = 1.0
    plain = taxel_signals(disp, GRID_X, GRID_Y, noise=0.0)[0, :, 0] - MID_SCALE
    # the cell [x0, x1) x [y0, y1): points on its lower edges belong to it
    in_x = (GRID_X >= cx - PAD_W / 8) & (GRID_X < cx + PAD_W / 8)
    in_y = (GRID_Y >= cy - PAD_H / 8) & (GRID_Y < cy + PAD_H / 8)
    cell = in_x[None, :] & in_y[:, None]
    assert cell.sum() == 8 * 7
    assert plain[6] == round(GAINS[0] * inside.sum() / cell.sum())
    assert (np.delete(plain, 6) == 0).all()
    spread = taxel_signals(disp, GRID_X, GRID_Y, noise=0.0, sigma_mm=3.0)[0, :, 0] - MID_SCALE
    assert spread[6] == spread.max() and spread[5] > 0 and spread[7] > 0
    np.testing.assert_allclose(taxel_weights(GRID_X, GRID_Y, sigma_mm=3.0).sum(1), 1.0)
    with pytest.raises(ValueError, match="leaves a taxel cell"):
        taxel_weights(np.array([0.0]), np.array([0.0]))


def _dot(image, taxel, near=(0.0, 0.0)):
    """(centroid x, y px, area px) of the dot nearest taxel's cell centre + near (px); x, y
    measured from the image's corner (pixel i spans [i, i+1))."""
    n, _, stats, cents = cv2.connectedComponentsWithStats(image, connectivity=8)
    cents = cents + 0.5
    cx, cy = (taxel_centres()[taxel] / USKIN_PAD_MM + 0.5) * (SIZE[1], SIZE[0]) + near
    k = 1 + np.argmin(np.hypot(cents[1:, 0] - cx, cents[1:, 1] - cy))
    return cents[k, 0], cents[k, 1], stats[k, cv2.CC_STAT_AREA]


def test_signal_to_marker_moves_and_grows_one_dot():
    s_xy, s_z = 4000.0, 150.0
    raw = BASE.copy()
    raw[6, 0] += int(0.5 * s_xy)              # taxel (row 1, col 2): +0.5 grid units in x
    raw[6, 2] += int(3.0 * s_z)               # and +3 mm^2 of dot area
    img = signal_to_marker(raw, BASE, size=SIZE, s_xy=s_xy, s_z=s_z)
    ref = signal_to_marker(BASE, BASE, size=SIZE, s_xy=s_xy, s_z=s_z)
    x0, y0, a0 = _dot(ref, 6)
    x1, y1, a1 = _dot(img, 6, near=(16, 0))
    pitch_px = SIZE[1] / 4                    # one grid unit in x = 32 px
    assert x0 == pytest.approx((2 + 0.5) * pitch_px, abs=0.05)      # cell centre, column 2
    assert y0 == pytest.approx((1 + 0.5) * SIZE[0] / 4, abs=0.05)   # row 1
    assert x1 - x0 == pytest.approx(0.5 * pitch_px, abs=0.1)        # +16 px
    assert y1 == pytest.approx(y0, abs=0.05)
    assert a0 == pytest.approx(BASE_AREA * PX_PER_MM2, rel=0.03)    # about 118 px
    assert a1 == pytest.approx((BASE_AREA + 3.0) * PX_PER_MM2, rel=0.03)   # about 206 px
    for other in (0, 5, 7, 15):                                     # the rest stay put
        assert _dot(img, other) == pytest.approx(_dot(ref, other))


def test_signal_to_marker_clips_offset_and_area():
    # small dots, so that a dot moved 0.8 grid units stays clear of its neighbour
    kw = dict(size=SIZE, s_xy=4000.0, s_z=150.0, base_area=0.5, max_area=12.0)
    raw = BASE.copy()
    raw[5, 0] -= 10 * 4000                    # taxel (1, 1): -10 grid units asked, -0.8 drawn
    raw[5, 1] += 10 * 4000                    # and +0.8 in y
    raw[10, 2] += 10 ** 5                     # taxel (2, 2): far past max_area
    raw[15, 2] -= 10 ** 4                     # pulling never shrinks a dot
    img = signal_to_marker(raw, BASE, **kw)
    ref = signal_to_marker(BASE, BASE, **kw)
    x0, y0, _ = _dot(ref, 5)
    x1, y1, _ = _dot(img, 5, near=(-25, 25))
    assert (x0, y0) == pytest.approx((48.0, 48.0), abs=0.05)
    assert (x1 - x0, y1 - y0) == pytest.approx((-0.8 * 32, 0.8 * 32), abs=0.3)   # -25.6, +25.6 px
    assert _dot(img, 10)[2] == pytest.approx(12.0 * PX_PER_MM2, rel=0.03)
    assert _dot(img, 15) == pytest.approx(_dot(ref, 15))
    assert img.shape == SIZE and img.dtype == np.uint8 and set(np.unique(img)) == {0, 255}


def test_min_area_lets_a_lifted_taxel_shrink_its_dot():
    """Below base_area only with min_area: z 300 counts under the rest reading at s_z 300 is
    1 mm^2 off a 2 mm^2 dot; a reading far below stops at min_area; the reference and a
    pressed dot are the same with or without it."""
    kw = dict(size=SIZE, s_xy=20000.0, s_z=300.0, base_area=2.0, max_area=16.0, z_only=True)
    raw = BASE.copy()
    raw[5, 2] -= 300                          # the pad lifted off taxel 5
    raw[6, 2] -= 10 ** 4                      # far off taxel 6
    raw[9, 2] += 900                          # taxel 9 pressed: 2 + 3 mm^2
    floor = signal_to_marker(raw, BASE, min_area=0.5, **kw)
    plain = signal_to_marker(raw, BASE, **kw)
    ref = signal_to_marker(BASE, BASE, **kw)
    assert np.array_equal(signal_to_marker(BASE, BASE, min_area=0.5, **kw), ref)
    # small dots: the rasterised edge is a larger share of them
    assert _dot(floor, 5)[2] == pytest.approx(1.0 * PX_PER_MM2, rel=0.12)       # about 29 px
    assert _dot(floor, 6)[2] == pytest.approx(0.5 * PX_PER_MM2, rel=0.2)        # about 15 px
    assert _dot(floor, 6)[2] < _dot(floor, 5)[2] < _dot(ref, 5)[2] / 1.6
    assert _dot(plain, 5) == pytest.approx(_dot(ref, 5)) and _dot(plain, 6) == pytest.approx(_dot(ref, 6))
    assert _dot(floor, 9) == pytest.approx(_dot(plain, 9))
    assert _dot(floor, 9)[2] == pytest.approx(5.0 * PX_PER_MM2, rel=0.03)
    with pytest.raises(ValueError, match=r"need 0 < min_area <= base_area, got 3.0, 2.0"):
        signal_to_marker(raw, BASE, min_area=3.0, **kw)


def test_z_only_markers_ignore_xy():
    raw = BASE.copy()
    raw[:, 0] += 3000
    raw[:, 1] -= 2000
    ref = signal_to_marker(BASE, BASE, size=SIZE)
    assert np.array_equal(signal_to_marker(raw, BASE, size=SIZE, z_only=True), ref)
    assert not np.array_equal(signal_to_marker(raw, BASE, size=SIZE), ref)


def test_reference_is_the_uskin_pattern_and_batches_work():
    ref = signal_to_marker(BASE, BASE, size=SIZE)
    assert np.array_equal(ref, rasterize(uskin_pattern(), size=SIZE))
    batch = signal_to_marker(np.stack([BASE, BASE + 500]), BASE, size=(48, 64))
    assert batch.shape == (2, 48, 64)
    with pytest.raises(ValueError, match=r"raw must be \(N,16,3\)"):
        signal_to_marker(np.zeros((3, 16, 2)), BASE)


def test_taxel_sequence_streams_signals_and_labels(monkeypatch):
    import stages.markers.uskin as uskin
    monkeypatch.setattr(uskin, "CHUNK", 3)
    n = 7
    deform = {"displacement": uniform(n, ux=0.2, uz=-0.1), "grid_x": GRID_X, "grid_y": GRID_Y,
              "force": np.arange(3 * n, dtype=np.float32).reshape(n, 3),
              "frame": np.arange(n, dtype=np.int64) + 100, "contact_id": np.zeros(n, np.int32),
              "indenters": np.array(["sphere", "prism"])}
    spec = {"variant": "3axis", "noise": 0.0, "offset_std": 100.0, "seed": 4}
    chunks, out = drain(taxel_sequence(deform=deform, skin="uskin-3axis", spec=spec))
    assert [len(c["signals"]) for c in chunks] == [3, 3, 1]
    signals = np.concatenate([c["signals"] for c in chunks])
    assert np.array_equal(np.concatenate([c["frame"] for c in chunks]), deform["frame"])
    assert np.array_equal(np.concatenate([c["force"] for c in chunks]), deform["force"])
    base = out["baseline"]
    assert base.shape == (16, 3) and np.abs(base - MID_SCALE).max() > 0      # per-taxel offsets
    np.testing.assert_array_equal(signals - base, np.broadcast_to([2000, 0, 800], (n, 16, 3)))
    assert out["attrs"]["variant"] == "3axis" and out["attrs"]["gains"] == list(GAINS)
    assert list(out["indenters"]) == ["sphere", "prism"]
    with pytest.raises(ValueError, match="variant must be one of"):
        drain(taxel_sequence(deform=deform, skin="uskin-x", spec={"variant": "xy"}))
