"""scripts/transfer_variants.py: the place part of a z-only skin's load moment, the linear Fz
read on the statistics a dot's motion leaves alike, and the cell cues of any marker image."""
import sys

import numpy as np
import pytest

from tests.helpers import load_script


@pytest.fixture(scope="module")
def variants():
    return load_script("transfer_variants")


def test_places_are_each_contacts_centroid_times_its_frames_load(variants):
    load = np.array([1.0, 3.0, 2.0, -0.5, 4.0, 2.0])
    contact = np.array([0, 0, 0, 0, 1, 1])
    centre = np.where(contact[:, None] == 0, [2.0, -1.0], [-3.0, 0.5])
    moment = centre * load[:, None]
    centroid, place = variants._places(moment, load, contact)
    np.testing.assert_allclose(centroid, centre, atol=1e-12)      # the lifted frame does not weigh
    np.testing.assert_allclose(place, moment, atol=1e-12)
    drift = np.zeros_like(moment)
    drift[1] = [0.6, 0.0]                       # one frame drifts: its contact's centroid follows
    centroid, place = variants._places(moment + drift, load, contact)
    np.testing.assert_allclose(centroid[0], [2.0 + 0.6 * 3.0 / 14.0, -1.0], atol=1e-12)
    np.testing.assert_allclose(centroid[4], [-3.0, 0.5], atol=1e-12)


def test_shift_free_read_reads_net_change_at_the_targets_scale(variants):
    rng = np.random.default_rng(3)
    x = rng.uniform(0.0, 1.0, (400, 4))
    fz = 5.0 * (x[:, 0] - x[:, 1]) - 2.0 * (x[:, 2] - x[:, 3]) + 0.5
    paired = rng.uniform(0.0, 1.0, (64, 4))
    coef, intercept = variants.fit_shift_free(x, fz, paired, paired)
    np.testing.assert_allclose(coef, [5.0, -5.0, -2.0, 2.0], rtol=1e-3)
    assert intercept == pytest.approx(0.5, abs=1e-3)
    # the target shows brightening less darkening at twice the translations' size: the read,
    # which applies to the target's own statistics, halves that coefficient
    target = paired.copy()
    target[:, 0] = paired[:, 1] + 2.0 * (paired[:, 0] - paired[:, 1])
    coef, intercept = variants.fit_shift_free(x, fz, paired, target)
    np.testing.assert_allclose(coef, [2.5, -2.5, -2.0, 2.0], rtol=1e-3)
    # a dot that only moves brightens and darkens alike: the read does not change
    moved = np.array([0.3, 0.3, 0.1, 0.1])
    assert float(coef @ moved) == pytest.approx(0.0, abs=1e-6)


def test_a_shift_gain_that_is_not_two_positive_numbers_is_refused(variants, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["transfer_variants", "uskin-z:uskin-3axis", "--shift-gain", "1.5,-1"])
    with pytest.raises(SystemExit):
        variants._args()
    assert "--shift-gain takes two positive numbers X,Y, got (1.5, -1.0)" in capsys.readouterr().err


def test_cell_cues_read_a_dots_motion_as_its_cells_first_moment(variants):
    """A 5x5 px square moved 3 px right in the second cell of a 4x4 grid over 32x32 px: that
    cell's area change is 0 and its x first moment grows by area times 3 px (y: 0); a dot that
    grows adds its new pixels to its cell's area."""
    ref = np.zeros((32, 32), np.uint8)
    ref[1:6, 9:14] = 255                         # cell (0, 1): rows 0-7, columns 8-15
    moved = np.zeros_like(ref)
    moved[1:6, 12:17] = 255                      # 3 px right, one column into cell (0, 2)
    grown = ref.copy()
    grown[6, 9:14] = 255
    cues = variants.cell_cues(np.stack([ref, moved, grown]), ref)
    assert cues.shape == (3, 48)
    np.testing.assert_allclose(cues[0], 0.0)
    area, mx, my = cues[1, :16], cues[1, 16:32], cues[1, 32:]
    assert area[1] == pytest.approx(-5.0) and area[2] == pytest.approx(5.0)   # one column crossed
    # x from the cell's centre: columns 9-13 at -2.5..1.5 px, then 12-15 at 0.5..3.5 px, 5 rows
    assert mx[1] == pytest.approx(5 * (0.5 + 1.5 + 2.5 + 3.5) - 5 * (-2.5 - 1.5 - 0.5 + 0.5 + 1.5))
    # y: rows 1-5 at -2.5..1.5 px (sum -2.5 a column): cell (0, 1) loses a column, (0, 2) gains it
    assert my[1] == pytest.approx(2.5) and my[2] == pytest.approx(-2.5)
    assert cues[2, 1] == pytest.approx(5.0) and cues[2, 33] == pytest.approx(5 * 2.5)
