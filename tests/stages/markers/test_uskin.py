"""uSkin: taxel signals from displacement, signal-to-marker geometry, XELA message parsing."""
import json

import cv2
import numpy as np
import pytest

from stages.markers.patterns import USKIN_PAD_MM, rasterize, uskin_pattern
from stages.markers.uskin import (BASE_AREA, GAINS, MID_SCALE, _dots, dot_changes, dot_features, load_moments,
                                  parse_xela, read_dots, redraw, signal_to_marker, taxel_centres, taxel_sequence, taxel_signals,
                                  taxel_weights)
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
    # redraw keeps what the skin can show: the shrunken dot stays, an erased one comes back at min_area
    floor[96:, 96:] = 0                       # taxel 15's dot erased
    back = redraw(floor[None], {**kw, "min_area": 0.5})[0]
    assert _dot(back, 5)[2] == pytest.approx(_dot(floor, 5)[2], rel=0.1)
    assert _dot(back, 15)[2] == pytest.approx(_dot(floor, 6)[2], rel=0.1)
    assert _dot(redraw(floor[None], kw)[0], 15) == pytest.approx(_dot(ref, 15))
    with pytest.raises(ValueError, match=r"need 0 < min_area <= base_area, got 3.0, 2.0"):
        signal_to_marker(raw, BASE, min_area=3.0, **kw)


def test_z_only_markers_ignore_xy():
    raw = BASE.copy()
    raw[:, 0] += 3000
    raw[:, 1] -= 2000
    ref = signal_to_marker(BASE, BASE, size=SIZE)
    assert np.array_equal(signal_to_marker(raw, BASE, size=SIZE, z_only=True), ref)
    assert not np.array_equal(signal_to_marker(raw, BASE, size=SIZE), ref)


def _random_raw(n, lateral_std, seed=0, common=None, area=(0, 1500)):
    """(n, 16, 3) raw readings: each dot moved by normal(0, lateral_std) counts per axis, plus a
    frame's common normal(0, common) where given, and pressed by uniform(area) counts, drawn in
    that order from seed (an int, or a Generator the caller draws from further)."""
    rng = np.random.default_rng(seed)
    move = rng.normal(0, lateral_std, (n, 16, 2))
    if common is not None:
        move = move + rng.normal(0, common, (n, 1, 2))
    return BASE + np.concatenate([move, rng.uniform(*area, (n, 16, 1))], -1)


# a 3-axis skin's marker settings for the redraw tests (dots up to 16 mm^2, 0.8 pitch offsets)
REDRAW_KW = dict(size=SIZE, s_xy=20000.0, s_z=150.0, base_area=BASE_AREA, max_area=16.0, max_offset=0.8)


@pytest.mark.parametrize("z_only", [False, True])
def test_read_dots_recovers_what_signal_to_marker_drew(z_only):
    kw = dict(size=SIZE, s_xy=20000.0, s_z=150.0, base_area=2.0 if z_only else BASE_AREA,
              max_area=16.0, max_offset=0.8, z_only=z_only)
    raw = _random_raw(40, 3000)               # 0.15 grid units, about 5 px, per axis
    images = signal_to_marker(raw, BASE, **kw)
    centres, areas = _dots(raw, BASE, pad_mm=USKIN_PAD_MM, **{k: v for k, v in kw.items() if k not in ("size", "z_only")},
                           z_only=z_only)
    got_c, got_a = read_dots(images)
    # a pixel is 0.034 mm^2; a dot's rasterised edge gains or loses a few of them
    assert np.abs(got_a - areas).mean() < 0.2 and np.median(np.abs(got_a - areas) / areas) < 0.03
    assert np.abs(got_c - centres).mean() < 0.03 and np.abs(got_c - centres).max() < (1e-6 if z_only else 0.8)
    redrawn = redraw(images, kw)
    assert (redrawn != images).sum((1, 2)).mean() < (30 if z_only else 80)   # of 16384 pixels


def test_redraw_puts_z_only_dots_back_at_their_taxels():
    """A translation that moved a z-only dot (which the skin cannot show) is redrawn with the
    dot at its taxel centre and the same area; for the 3-axis skin the move stays, clipped to
    max_offset; empty cells get base_area dots, oversized ones max_area."""
    kw = dict(size=SIZE, base_area=2.0, max_area=12.0, max_offset=0.5)
    raw = BASE.copy()
    raw[6, 0] += 4000                         # taxel 6 moved 0.2 grid units (6.4 px) in x
    raw[6, 2] += 900                          # and 6 mm^2 larger
    moved = signal_to_marker(raw, BASE, s_xy=20000.0, s_z=150.0, **kw)
    moved[100:128, 100:128] = 0               # taxel 15's dot erased
    moved[0:32, 0:32] = 255                   # taxel 0's cell filled: 34.7 mm^2
    z = redraw(moved[None], {**kw, "z_only": True})[0]
    x, y, a = _dot(z, 6)
    assert (x, y) == pytest.approx(((2 + 0.5) * 32, (1 + 0.5) * 32), abs=0.05)
    assert a == pytest.approx(8.0 * PX_PER_MM2, rel=0.04)
    ref = signal_to_marker(BASE, BASE, **kw)
    assert _dot(z, 15) == pytest.approx(_dot(ref, 15))          # a base_area dot again
    assert _dot(z, 0)[2] == pytest.approx(12.0 * PX_PER_MM2, rel=0.03)
    three = redraw(moved[None], {**kw, "z_only": False})[0]
    assert _dot(three, 6, near=(6, 0))[0] - 80 == pytest.approx(6.4, abs=0.3)
    with pytest.raises(ValueError, match=r"redraw: images are \(128, 128\), the skin draws \(64, 64\)"):
        redraw(moved[None], {**kw, "size": [64, 64]})


def test_redraw_gain_scales_the_dots_motion_and_area_change():
    """gain (x, y, area) multiplies what redraw reads before it draws: dots read back at twice
    their x offset, half their y offset and 1.5 times their area change; gain 1 is redraw."""
    kw = REDRAW_KW          # 0.075 grid units per axis, up to 4 mm^2 more area: no clip
    images = signal_to_marker(_random_raw(24, 1500, 3, area=(0, 600)), BASE, **kw)
    off, change = dot_changes(images, kw)
    assert np.abs(off).mean() > 0.1 and np.abs(change).mean() > 1.0     # mm, mm^2
    np.testing.assert_array_equal(redraw(images, kw, gain=(1, 1, 1)), redraw(images, kw))
    got_off, got_change = dot_changes(redraw(images, kw, gain=(2.0, 0.5, 1.5)), kw)
    for k, g in ((0, 2.0), (1, 0.5)):
        assert np.polyfit(off[..., k].ravel(), got_off[..., k].ravel(), 1)[0] == pytest.approx(g, rel=0.05)
    assert np.polyfit(change.ravel(), got_change.ravel(), 1)[0] == pytest.approx(1.5, rel=0.05)
    with pytest.raises(ValueError, match=r"redraw: gain must be 3 positive numbers \(x, y, area\), got \(1, 0, 1\)"):
        redraw(images, kw, gain=(1, 0, 1))


def test_redraw_shift_gain_scales_only_the_dots_common_shift():
    """shift_gain (x, y) multiplies the mean offset of a frame's 16 dots, gain the rest of each
    dot's offset: read back, the common shift is 2x in x and 0.5x in y, the rest and the areas
    are as they were."""
    kw = REDRAW_KW
    images = signal_to_marker(_random_raw(24, 1000, 4, common=1000, area=(0, 600)), BASE, **kw)
    off, change = dot_changes(images, kw)
    got_off, got_change = dot_changes(redraw(images, kw, shift_gain=(2.0, 0.5)), kw)
    shift, got_shift = off.mean(1), got_off.mean(1)
    for k, g in ((0, 2.0), (1, 0.5)):
        assert np.polyfit(shift[:, k], got_shift[:, k], 1)[0] == pytest.approx(g, rel=0.05)
        rest, got_rest = off[..., k] - shift[:, None, k], got_off[..., k] - got_shift[:, None, k]
        assert np.polyfit(rest.ravel(), got_rest.ravel(), 1)[0] == pytest.approx(1.0, rel=0.05)
    assert np.polyfit(change.ravel(), got_change.ravel(), 1)[0] == pytest.approx(1.0, rel=0.05)
    with pytest.raises(ValueError, match=r"redraw: shift_gain must be 2 positive numbers \(x, y\), got \(1, -1\)"):
        redraw(images, kw, shift_gain=(1, -1))


def test_redraw_shift_sets_each_frames_common_shift():
    """redraw's shift sets a frame's common shift (the mean offset of its 16 dots) to the given
    (N, 2) mm and keeps the rest of each dot's offset and its area; dot_features is dot_changes'
    offsets (x, then y) and area changes in one row; a wrong shape, shift_gain beside it or a
    z-only skin is refused."""
    kw, rng = REDRAW_KW, np.random.default_rng(6)
    images = signal_to_marker(_random_raw(20, 600, rng, common=1500, area=(0, 600)), BASE, **kw)
    off, change = dot_changes(images, kw)
    feats = dot_features(images, kw)
    assert feats.shape == (20, 48)
    np.testing.assert_array_equal(feats, np.concatenate([off[..., 0], off[..., 1], change], 1))
    want = rng.uniform(-0.6, 0.6, (20, 2))                            # mm, within max_offset
    got_off, got_change = dot_changes(redraw(images, kw, shift=want), kw)
    np.testing.assert_allclose(got_off.mean(1), want, atol=0.05)
    rest, got_rest = off - off.mean(1, keepdims=True), got_off - got_off.mean(1, keepdims=True)
    assert np.abs(got_rest - rest).mean() < 0.05 < np.abs(rest).mean()
    assert np.abs(got_change - change).mean() < 0.15
    np.testing.assert_array_equal(redraw(images, kw, shift=off.mean(1)), redraw(images, kw))
    with pytest.raises(ValueError, match=r"redraw: shift must be \(20, 2\) finite numbers \(mm\), "
                                         r"one row per image, got shape \(2,\)"):
        redraw(images, kw, shift=(0.1, 0.2))
    with pytest.raises(ValueError, match="redraw: shift sets the common shift that shift_gain scales: give one"):
        redraw(images, kw, shift=want, shift_gain=(1.0, 1.0))
    with pytest.raises(ValueError, match="redraw: shift moves dots, and a z-only skin's dots cannot move"):
        redraw(images, {**kw, "z_only": True}, shift=want)


def test_redraw_tilt_moves_a_drawn_shear_into_a_z_only_skins_load():
    """tilt ((a_x, b_x), (a_y, b_y)) redraws a translation's moving dots into a z-only skin with
    the first moment of their area changes a times its read value plus b times the dots' read
    common shift (load_moments), the total area kept and the dots at their taxels; without it
    the moment ignores the shift."""
    kw = {**REDRAW_KW, "min_area": 0.5}
    images = signal_to_marker(_random_raw(24, 300, 5, common=2000, area=(100, 500)), BASE, **kw)
    moment, shift = load_moments(*dot_changes(images, kw), USKIN_PAD_MM)
    assert np.abs(shift).mean() > 0.3                                   # mm: the dots moved
    z_kw, tilt = {**kw, "z_only": True}, ((0.5, 30.0), (0.5, -30.0))
    want = np.stack([a * moment[:, k] + b * shift[:, k] for k, (a, b) in enumerate(tilt)], 1)
    off, change = dot_changes(redraw(images, z_kw, tilt=tilt), z_kw)
    got, got_shift = load_moments(off, change, USKIN_PAD_MM)
    assert np.abs(got_shift).max() < 1e-9
    for k in (0, 1):
        assert np.corrcoef(want[:, k], got[:, k])[0, 1] > 0.98
        assert np.polyfit(want[:, k], got[:, k], 1)[0] == pytest.approx(1.0, abs=0.1)
    plain_off, plain_change = dot_changes(redraw(images, z_kw), z_kw)
    assert np.abs(change.sum(1) - plain_change.sum(1)).mean() < 0.3     # mm^2, of ~3.5 sd
    plain, _ = load_moments(plain_off, plain_change, USKIN_PAD_MM)
    assert max(abs(np.corrcoef(want[:, k], plain[:, k])[0, 1]) for k in (0, 1)) < 0.8
    with pytest.raises(ValueError, match=r"redraw: tilt must be 2x2 numbers \(\(a_x, b_x\), \(a_y, b_y\)\), got \(1, 2\)"):
        redraw(images, z_kw, tilt=(1, 2))

def test_reference_is_the_uskin_pattern_and_batches_work():
    ref = signal_to_marker(BASE, BASE, size=SIZE)
    assert np.array_equal(ref, rasterize(uskin_pattern(), size=SIZE))
    batch = signal_to_marker(np.stack([BASE, BASE + 500]), BASE, size=(48, 64))
    assert batch.shape == (2, 48, 64)
    with pytest.raises(ValueError, match=r"raw must be \(N,16,3\)"):
        signal_to_marker(np.zeros((3, 16, 2)), BASE)


def xela_message(data, **extra):
    return json.dumps({"message": 17, "time": 1.7e9, "sensors": 1,
                       "1": {"data": data, "sensor": "1", "taxels": 16, "model": "uSPa44",
                             "calibrated": None, **extra}})


def test_parse_xela_ints_and_hex():
    values = (MID_SCALE + np.arange(48)).tolist()
    expected = np.asarray(values).reshape(16, 3)
    out = parse_xela(xela_message(values, calibrated=[0.1] * 48))
    assert list(out) == ["1"] and out["1"].shape == (16, 3)
    assert np.array_equal(out["1"], expected)
    hexes = [format(v, "04X") for v in values]
    assert np.array_equal(parse_xela(xela_message(hexes))["1"], expected)
    assert np.array_equal(parse_xela(xela_message(",".join(hexes)).encode())["1"], expected)
    msg = json.loads(xela_message(values))
    msg["2"] = {"data": values[::-1]}
    assert np.array_equal(parse_xela(msg)["2"], expected.ravel()[::-1].reshape(16, 3))
    assert parse_xela('{"message": "Welcome"}') == {}


@pytest.mark.parametrize("message, error", [
    ("{not json", r"parse_xela: message is not JSON \(Expecting property name"),
    ("[1, 2]", "parse_xela: message must be a JSON object, got list"),
    (xela_message([1] * 45), r"parse_xela: sensor '1': expected 48 values \(16 taxels x 3\), got 45"),
    (xela_message(["80G0"] * 48), "parse_xela: sensor '1': value '80G0' is not a hex string"),
    (xela_message([1.5] * 48), "parse_xela: sensor '1': value 1.5 is not an integer or a hex string"),
    (xela_message([70000] * 48), r"parse_xela: sensor '1': values outside 0..65535"),
    ('{"3": {"sensor": "3"}}', "parse_xela: sensor '3' has no `data` list"),
])
def test_parse_xela_rejects_malformed(message, error):
    with pytest.raises(ValueError, match=error) as info:
        parse_xela(message)
    assert "\n" not in str(info.value)


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


def test_shrink_centroids_and_tilt_changes():
    """shrink_centroids: the area dots lose below their rest size (clipped at min_area) and its
    centroid, 0 where none shrinks; tilt_changes adds a plane summing to 0 that sets the moment."""
    from stages.markers.uskin import _taxel_positions, shrink_centroids, tilt_changes
    grid = _taxel_positions(USKIN_PAD_MM)
    kw = {"base_area": 2.0, "min_area": 0.5, "max_area": 16.0}
    changes = np.zeros((3, 16))
    changes[0, 5] = -1.0                            # one dot shrinks by 1 mm^2
    changes[1, [0, 15]] = [-3.0, -0.5]              # clipped at 0.5 mm^2: loses 1.5, and 0.5
    changes[2, 7] = 4.0                             # grows only
    centroid, lost = shrink_centroids(changes, kw)
    assert lost == pytest.approx([1.0, 2.0, 0.0])
    assert centroid[0] == pytest.approx(grid[5])
    assert centroid[1] == pytest.approx((1.5 * grid[0] + 0.5 * grid[15]) / 2.0)
    assert centroid[2] == pytest.approx([0.0, 0.0])
    assert shrink_centroids(changes, {**kw, "min_area": 2.0})[1] == pytest.approx([0.0, 0.0, 0.0])
    moment = changes @ grid
    want = moment + np.array([[10.0, -5.0], [0.0, 0.0], [-2.0, 3.0]])
    tilted = tilt_changes(changes, moment, want)
    assert tilted @ grid == pytest.approx(want) and tilted.sum(1) == pytest.approx(changes.sum(1))
