"""scripts/indenter_labels.py: the calibration fit it falls back on for curved indenters."""
import numpy as np
import pytest

from stages.force.compensation import curves_from_calibration
from tests.helpers import load_script


@pytest.fixture(scope="module")
def script():
    return load_script("indenter_labels")


def cone_calibration(c=3.0, gain=0.4):
    """A cone's press (F = c d^2, phase 0), its release (F = 0.8 c d^2, phase 3) and a shear
    leg at d = 1 (phase 1) whose shear force is `gain` times its normal force."""
    d = np.r_[np.linspace(0.1, 1, 10), np.linspace(0.9, 0, 10), np.ones(3)]
    phase = np.r_[np.zeros(10), np.full(10, 3), np.ones(3)].astype(np.int8)
    fz = np.where(phase == 3, 0.8, 1.0) * c * d ** 2
    force = np.zeros((d.size, 3))
    force[:, 2] = -fz
    force[phase == 1, 0] = gain * c
    return {"normalised_depth": d, "force": force, "loading": phase != 3, "phase": phase}


def test_a_cone_calibration_is_fitted_with_nonnegative_terms(script):
    cal = cone_calibration()
    cal["force"][:10, 2] -= 0.02 * np.sin(np.arange(10))        # a convex curve that dips: b < 0
    with pytest.raises(ValueError, match="loading curve is not positive"):
        curves_from_calibration(cal)
    curves = script._nonnegative_curves(cal)
    a, b, c0 = curves.loading
    assert a == pytest.approx(3.0, rel=0.02) and b == pytest.approx(0.01 * a) and c0 == 0.0
    assert curves.unloading[0] == pytest.approx(2.4, rel=1e-6)
    assert curves.shear_gain == pytest.approx(0.4)
