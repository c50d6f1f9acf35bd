"""scripts/transfer_variants.py: the place part of a z-only skin's load moment, and the linear Fz
read on the statistics a dot's motion leaves alike."""
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
