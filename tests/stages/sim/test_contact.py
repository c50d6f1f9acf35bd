"""Checks of the FFT boundary-element contact solver against closed-form contact mechanics."""
import numpy as np
import pytest

from stages.sim.contact import ContactResult, solve_contact, solve_contact_batch, solve_sequence
from stages.sim.kernels import unit_kernels

E, NU = 1.45e5, 0.45
E_STAR = E / (1 - NU ** 2)
G = E / (2 * (1 + NU))
R = 5.0


def grid(n, width):
    h = width / n
    x = (np.arange(n) - (n - 1) / 2) * h
    xx, yy = np.meshgrid(x, x)
    return h, xx, yy


def paraboloid(n=128, width=8.0, radius=R):
    """Hertz's sphere (the paraboloid r^2 / 2R that Hertz theory assumes)."""
    h, xx, yy = grid(n, width)
    return h, (xx ** 2 + yy ** 2) / (2 * radius)


def hertz_force(d, radius=R):
    return 4 / 3 * E_STAR * np.sqrt(radius) * d ** 1.5 * 1e-6      # Pa * mm^2 -> N


def contact_radius(res, h):
    return np.sqrt((res.pressure > 0).sum() * h * h / np.pi)


@pytest.mark.parametrize("d", [0.2, 0.5, 1.0])
def test_hertz_sphere_half_space(d):
    h, height = paraboloid()
    res = solve_contact(height, d, spacing=h, E=E, nu=NU)
    assert isinstance(res, ContactResult)
    assert res.force[2] < 0                                          # paper's sign
    assert -res.force[2] == pytest.approx(hertz_force(d), rel=0.02)
    assert contact_radius(res, h) == pytest.approx(np.sqrt(R * d), rel=0.05)
    assert abs(res.force[0]) < 1e-12 and abs(res.force[1]) < 1e-12
    # force is the pressure integral: N = Pa * mm^2 * 1e-6
    assert -res.force[2] == pytest.approx(res.pressure.sum() * h * h * 1e-6, rel=1e-12)


def test_hertz_pressure_profile():
    h, height = paraboloid()
    d = 0.5
    res = solve_contact(height, d, spacing=h, E=E, nu=NU)
    a = np.sqrt(R * d)
    p0 = 2 * E_STAR * a / (np.pi * R)                                # peak Hertz pressure, Pa
    assert res.pressure.max() == pytest.approx(p0, rel=0.02)


def test_flat_punch():
    # F = 2 a E* d; the edge singularity makes the grid error first order in h (~0.5% here)
    h, xx, yy = grid(128, 8.0)
    r = np.hypot(xx, yy)
    inside = r <= 1.5
    height = np.where(inside, 0.0, np.nan)
    a_eff = np.sqrt(inside.sum() * h * h / np.pi)                    # area of the pixel disk
    res = solve_contact(height, 0.1, spacing=h, E=E, nu=NU)
    assert -res.force[2] == pytest.approx(2 * a_eff * E_STAR * 0.1 * 1e-6, rel=0.015)
    assert (res.pressure[inside] > 0).all()
    # the punch face is flat: uz = -depth across it
    assert np.allclose(res.displacement[inside, 2], -0.1, atol=1e-5)
    # +inf marks absence as well as NaN
    res_inf = solve_contact(np.where(inside, 0.0, np.inf), 0.1, spacing=h, E=E, nu=NU)
    np.testing.assert_allclose(res_inf.force, res.force)


@pytest.mark.parametrize("shift", [0.02, 0.06, 0.15])
def test_cattaneo_mindlin_stick_radius(shift):
    h, height = paraboloid(n=96, width=6.0)
    d, mu = 0.5, 0.5
    res = solve_contact(height, d, spacing=h, E=E, nu=NU, shift=(shift, 0.0), mu=mu)
    P, Q = -res.force[2], res.force[0]
    assert 0 < Q < mu * P
    q = np.hypot(res.traction[..., 0], res.traction[..., 1])
    assert (q <= mu * res.pressure * (1 + 1e-9) + 1e-9).all()        # Coulomb holds
    stick = (res.pressure > 0) & (q < mu * res.pressure * (1 - 1e-4))
    c = np.sqrt(stick.sum() * h * h / np.pi)
    a = contact_radius(res, h)
    assert c == pytest.approx(a * (1 - Q / (mu * P)) ** (1 / 3), rel=0.03)
    assert abs(res.force[1]) < 1e-6 * Q


def test_full_stick_tangential_stiffness():
    # uniform tangential displacement over a circle: Q = 8 G a delta / (2 - nu)
    h, height = paraboloid(n=128, width=20.0)
    res = solve_contact(height, 1.0, spacing=h, E=E, nu=NU, shift=(0.2, 0.0))
    a = np.sqrt(R * 1.0)
    assert res.force[0] == pytest.approx(8 * G * a * 0.2 / (2 - NU) * 1e-6, rel=0.02)
    inside = res.pressure > 0
    # stuck points follow the indenter (coupling from the pressure aside, it is radial & odd)
    ux = res.displacement[..., 0][inside]
    assert ux.mean() == pytest.approx(0.2, rel=0.01)


def test_shift_direction_sign():
    h, height = paraboloid(n=64, width=8.0)
    plus = solve_contact(height, 0.5, spacing=h, E=E, nu=NU, shift=(0.1, 0.0))
    minus = solve_contact(height, 0.5, spacing=h, E=E, nu=NU, shift=(-0.1, 0.0))
    assert plus.force[0] > 0 and minus.force[0] < 0
    assert plus.force[0] == pytest.approx(-minus.force[0], rel=1e-6)
    assert abs(plus.force[1]) < 1e-6 * plus.force[0]
    assert plus.force[2] == pytest.approx(minus.force[2], rel=1e-9)
    along_y = solve_contact(height, 0.5, spacing=h, E=E, nu=NU, shift=(0.0, 0.1))
    assert along_y.force[1] == pytest.approx(plus.force[0], rel=1e-3)
    assert abs(along_y.force[0]) < 1e-6 * along_y.force[1]


def dimitriadis(chi, nu):
    """Bonded-layer sphere indentation series (Dimitriadis et al. 2002), chi = sqrt(R d)/t."""
    a0 = -(1.2876 - 1.4678 * nu + 1.3442 * nu ** 2) / (1 - nu)
    b0 = (0.6387 - 1.0277 * nu + 1.5164 * nu ** 2) / (1 - nu)
    pi = np.pi
    return (1 - 2 * a0 / pi * chi + 4 * a0 ** 2 / pi ** 2 * chi ** 2
            - 8 / pi ** 3 * (a0 ** 3 + 4 * pi ** 2 * b0 / 15) * chi ** 3
            + 16 * a0 / pi ** 4 * (a0 ** 3 + 3 * pi ** 2 * b0 / 5) * chi ** 4)


def test_finite_layer_stiffer_and_converges():
    h, height = paraboloid()
    d = 0.5
    half = -solve_contact(height, d, spacing=h, E=E, nu=NU).force[2]
    forces = {t: -solve_contact(height, d, spacing=h, E=E, nu=NU, thickness=t).force[2]
              for t in (4.0, 20.0, 100.0, 1000.0)}
    assert forces[4.0] > 1.3 * half                                  # 4 mm pad: much stiffer
    assert forces[4.0] > forces[20.0] > forces[100.0] > forces[1000.0] > half
    assert forces[1000.0] == pytest.approx(half, rel=0.005)
    # small chi: the series is accurate and the layer kernel must reproduce it
    for t in (20.0, 100.0):
        chi = np.sqrt(R * d) / t
        assert forces[t] / hertz_force(d) == pytest.approx(dimitriadis(chi, NU), rel=0.01)


def test_layer_kernel_uniform_load_limits():
    # a load wide compared with the layer: oedometric compression and simple shear
    t = 6.0
    k = unit_kernels((240, 240), NU, t)
    assert k["zz"].sum() == pytest.approx(t * (1 + NU) * (1 - 2 * NU) / (1 - NU), rel=2e-3)
    assert k["xx"].sum() == pytest.approx(2 * (1 + NU) * t, rel=2e-3)
    assert abs(k["xy"].sum()) < 1e-9 and abs(k["xz"].sum()) < 1e-9


def test_pressure_nonnegative_and_zero_outside():
    h, xx, yy = grid(96, 8.0)
    rng = np.random.default_rng(0)
    height = (xx ** 2 + yy ** 2) / 10 + 0.05 * rng.standard_normal(xx.shape)   # rough sphere
    height[:, :20] = np.nan
    res = solve_contact(height, 0.4, spacing=h, E=E, nu=NU, shift=(0.05, 0.02), mu=0.3)
    assert (res.pressure >= 0).all()
    outside = res.pressure == 0
    assert outside.any() and (res.pressure > 0).any()
    assert (res.traction[outside] == 0).all()
    assert (res.pressure[:, :20] == 0).all()
    # no penetration anywhere, closed gap where loaded
    gap = np.where(np.isfinite(height), height - 0.4 - res.displacement[..., 2], np.inf)
    loaded = res.pressure > 0
    # shear tractions add a (1 - 2 nu) uz coupling that the decoupled solve does not see
    assert gap.min() > -0.01 * 0.4
    assert np.abs(gap[loaded]).max() < 0.01 * 0.4


def test_uz_under_indenter():
    h, height = paraboloid(n=128, width=20.0)
    d = 1.0
    res = solve_contact(height, d, spacing=h, E=E, nu=NU)
    uz = res.displacement[..., 2]
    inside = res.pressure > 0
    assert (uz[inside] < 0).all()
    np.testing.assert_allclose(uz[inside], height[inside] - d, atol=1e-4)
    assert uz.min() == pytest.approx(-d, abs=0.01)
    # the surface sinks outside the contact too, less than inside, and recovers far away
    assert (uz[~inside] > -d).all() and (uz < 0).all()
    assert uz[0, 0] > 0.1 * uz.min()
    # normal load pulls the half-space surface radially inward (Boussinesq, 1 - 2 nu)
    centre = np.array(height.shape) // 2
    assert res.displacement[centre[0], centre[1] + 20, 0] < 0


def test_curved_pad_gap_profile():
    # flat indenter on a domed pad of radius R == sphere on a flat pad (gap is additive)
    h, xx, yy = grid(96, 8.0)
    dome = (xx ** 2 + yy ** 2) / (2 * R) + 0.3                       # min(height) = 0.3 != 0
    res = solve_contact(dome, 0.8, spacing=h, E=E, nu=NU)
    ref = solve_contact(dome - 0.3, 0.5, spacing=h, E=E, nu=NU)
    np.testing.assert_allclose(res.force, ref.force, rtol=1e-6)
    no_touch = solve_contact(dome, 0.25, spacing=h, E=E, nu=NU)
    assert (no_touch.pressure == 0).all() and (no_touch.force == 0).all()


def trajectory():
    depths = np.array([0.2, 0.4, 0.6, 0.6, 0.6, 0.6, 0.6, 0.4, 0.2, 0.0])
    shifts = np.zeros((10, 2))
    shifts[3:7, 0] = [0.05, 0.1, 0.05, 0.0]
    phases = np.array([0, 0, 0, 1, 1, 2, 2, 3, 3, 3], np.int8)
    return depths, shifts, phases


def test_sequence_hysteresis():
    h, height = paraboloid(n=64, width=8.0)
    depths, shifts, phases = trajectory()
    kw = dict(spacing=h, E=E, nu=NU)
    plain = solve_sequence(height, depths, shifts, phases, **kw)
    soft = solve_sequence(height, depths, shifts, phases, hysteresis=0.3, **kw)
    # loading frames 0, 1 and unloading frames 8, 7 have equal depths 0.2, 0.4
    for load, unload in ((0, 8), (1, 7)):
        assert plain.force[unload, 2] == pytest.approx(plain.force[load, 2], rel=2e-5)
        assert -soft.force[load, 2] > -soft.force[unload, 2] > 0
        assert soft.force[unload, 2] == pytest.approx(0.7 * soft.force[load, 2], rel=2e-5)
    np.testing.assert_array_equal(soft.force[:7], plain.force[:7])
    assert (soft.force[9] == 0).all()
    # full stick: shear out and back retrace each other, back to zero shear force
    assert plain.force[4, 0] > plain.force[3, 0] > 0
    assert plain.force[5, 0] == pytest.approx(plain.force[3, 0], rel=1e-4)
    assert abs(plain.force[6, 0]) < 1e-6 * plain.force[4, 0]


def test_sequence_friction_memory():
    h, height = paraboloid(n=64, width=8.0)
    depths, shifts, phases = trajectory()
    shifts[3:7, 0] *= 3.0                                            # enough to slip
    seq = solve_sequence(height, depths, shifts, phases, spacing=h, E=E, nu=NU, mu=0.3)
    fresh = solve_contact(height, 0.6, spacing=h, E=E, nu=NU, shift=tuple(shifts[5]), mu=0.3)
    # shear out matches a fresh solve; shear back (same shift) does not: slip was left behind
    single = solve_contact(height, 0.6, spacing=h, E=E, nu=NU, shift=tuple(shifts[3]), mu=0.3)
    assert seq.force[3, 0] == pytest.approx(single.force[0], rel=1e-4)
    assert seq.force[5, 0] < fresh.force[0]
    assert seq.force[6, 0] < 0                                      # back at 0: reversed shear
    assert (np.abs(seq.force[:, 0]) <= 0.3 * -seq.force[:, 2] + 1e-12).all()


def test_batch_equals_single():
    h, xx, yy = grid(64, 8.0)
    heights = np.stack([(xx ** 2 + yy ** 2) / 10, ((xx - 1) ** 2 + yy ** 2) / 6,
                        np.where(np.hypot(xx, yy) < 1.2, 0.0, np.nan)])
    depths = np.array([0.5, 0.3, 0.05])
    shifts = np.array([[0.05, 0.0], [0.0, -0.03], [0.02, 0.02]])
    batch = solve_contact_batch(heights, depths, spacing=h, E=E, nu=NU, shifts=shifts, mu=0.4)
    assert batch.pressure.shape == (3, 64, 64) and batch.displacement.shape == (3, 64, 64, 3)
    assert batch.traction.shape == (3, 64, 64, 2) and batch.force.shape == (3, 3)
    for k in range(3):
        one = solve_contact(heights[k], depths[k], spacing=h, E=E, nu=NU,
                            shift=tuple(shifts[k]), mu=0.4)
        np.testing.assert_allclose(batch.force[k], one.force, rtol=1e-3, atol=1e-7)
        np.testing.assert_allclose(batch.pressure[k], one.pressure,
                                   atol=1e-3 * one.pressure.max())


def test_thin_layer_bulge_contact_beyond_reach():
    # a nearly incompressible thin layer bulges up around the indenter and touches it outside
    # {height < depth}: the solver must leave its crop, and the gap must stay closed/open
    h, xx, yy = grid(64, 20.0)
    height = (xx ** 2 + yy ** 2) / 40.0
    res = solve_contact(height, 0.3, spacing=h, E=E, nu=0.49, thickness=2.0)
    loaded = res.pressure > 0
    assert (loaded & (height >= 0.3)).any()
    assert res.displacement[..., 2].max() > 0                       # the bulge
    gap = height - 0.3 - res.displacement[..., 2]
    assert gap.min() > -1e-4 and np.abs(gap[loaded]).max() < 1e-4
