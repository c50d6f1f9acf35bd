"""The sensor and elastomer catalogue reproduces the paper's qualitative facts."""
import numpy as np
import pytest

from stages.sim.contact import solve_contact
from stages.sim.deform import calibrate, deform_sequence
from stages.sim.indenters import SEEN, height_map, make_indenter
from stages.sim.sensors import contact_height, material_of, surface_gap
from stages.sim.trajectory import calibration_trajectory, collection_trajectory

RATIOS = ("r6", "r8", "r10", "r12", "r14", "r16", "r18")
GELS = tuple(f"gelsight-{r}" for r in RATIOS)


def test_materials(params):
    mats = params["materials"]
    assert set(RATIOS) | {"sim"} <= set(mats)
    assert mats["sim"]["E"] == 1.45e5 and mats["sim"]["nu"] == 0.45       # the paper's sim pad
    moduli = [mats[r]["E"] for r in RATIOS]
    assert all(a > b for a, b in zip(moduli, moduli[1:]))                 # higher ratio = softer
    for m in mats.values():
        assert 0 < m["nu"] < 0.5 and m["mu"] > 0 and 0 <= m["hysteresis"] < 1


@pytest.mark.parametrize("profile", [None, "ci", "paper"])
def test_sensor_geometry(profile, load_params):
    p = load_params(profile)
    sensors, mats = p["sensors"], p["materials"]
    for name, s in sensors.items():
        (h, w), dx = s["grid"], s["spacing_mm"]
        assert s["material"] in mats, name
        assert h % 2 == 1 and w % 2 == 1, name            # the pad centre is a cell centre
        assert abs(w * dx - s["pad_mm"][0]) <= dx and abs(h * dx - s["pad_mm"][1]) <= dx, name
        assert s["trajectory"] in ("sim_trajectory", "collection_trajectory")
    assert sensors["sim"]["pad_mm"] == [20.0, 20.0] and sensors["sim"]["thickness_mm"] == 4.0
    assert sensors["sim"]["material"] == "sim" and sensors["sim"]["trajectory"] == "sim_trajectory"
    for gel, ratio in zip(GELS, RATIOS):                   # one geometry: only the elastomer differs
        same = lambda s: {k: v for k, v in s.items() if k not in ("material", "body", "hardness")}
        assert same(sensors[gel]) == same(sensors[GELS[0]])
        assert sensors[gel]["material"] == ratio
    assert sensors[GELS[0]]["pad_mm"] == [25.0, 25.0] and sensors[GELS[0]]["thickness_mm"] == 4.0
    tactip, uskin = sensors["tactip"], sensors["uskin"]
    assert tactip["curvature_radius_mm"] == 41.5 and tactip["pad_mm"] == [40.0, 40.0]
    assert tactip["max_depth_mm"] <= 5.0 and tactip["depth_scale"] * 1.0 == tactip["max_depth_mm"]
    assert uskin["pad_mm"] == [24.6, 22.6] and uskin["thickness_mm"] == 5.0
    e = {n: mats[sensors[n]["material"]]["E"] for n in ("tactip", "gelsight-r10", "uskin")}
    assert e["tactip"] < e["gelsight-r10"] < e["uskin"]   # very soft .. stiffest


def test_softer_elastomer_less_force(params):
    """Same GelSight pad, same sphere, same depth: force falls from r6 to r18, normal and shear."""
    spec = {**params["sensors"]["gelsight-r10"], "grid": [33, 33], "spacing_mm": 0.78125}
    height = height_map("sphere", shape=(33, 33), spacing=0.78125)
    forces = []
    for r in RATIOS:
        m = material_of({**spec, "material": r}, params["materials"])
        forces.append(solve_contact(height, 1.0, spacing=0.78125, E=m["E"], nu=m["nu"],
                                    thickness=4.0, shift=(0.1, 0.0)).force)
    forces = np.array(forces)
    assert np.all(np.diff(forces[:, 2]) > 0)                # |Fz| shrinks as Fz < 0 rises to 0
    assert np.all(np.diff(forces[:, 0]) < 0)                # stuck shear: Fx > 0 shrinks too
    assert forces[-1, 2] / forces[0, 2] == pytest.approx(2.1e5 / 8.1e5, rel=1e-6)


def test_dome_gap_and_touchdown(params):
    spec = params["sensors"]["tactip"]
    gap = surface_gap(spec)
    c = spec["grid"][0] // 2
    assert gap[c, c] == 0.0
    x = (np.arange(spec["grid"][1]) - c) * spec["spacing_mm"]
    edge = np.flatnonzero(np.abs(x) <= 20.0)[-1]
    assert gap[c, edge] == pytest.approx(41.5 - np.sqrt(41.5 ** 2 - x[edge] ** 2))
    assert np.isinf(gap[0, 0])                               # no pad beyond the dome's base
    flat_punch = make_indenter("cylinder")                  # radius 3 mm, 6 mm off the apex
    h = contact_height(flat_punch, spec, (6.0, 0.0), gap)
    touch = np.unravel_index(np.argmin(np.where(np.isfinite(h), h, np.inf)), h.shape)
    assert h[touch] == pytest.approx(0.0, abs=1e-12)         # depth counts from first touch
    assert x[touch[1]] == pytest.approx(6.0 - 3.0, abs=spec["spacing_mm"])   # rim nearest the apex
    assert touch[0] == c


def _force_at_max_normalised_depth(params, indenter_artifact, sensor):
    tr = calibration_trajectory(n_steps=4, repetitions=1)
    out = calibrate(indenters=indenter_artifact, trajectory=tr, sensor=sensor,
                    spec=params["sensors"][sensor], materials=params["materials"])
    assert out["normalised_depth"].max() == 1.0
    return -out["force"][np.argmax(out["normalised_depth"]), 2]


def test_tactip_softest_at_max_normalised_depth(params, indenter_artifact):
    """Paper (Supp. Fig. 13A, the hetero calibration: GelSight and uSkin to 1 mm, TacTip to
    4.5 mm): at maximum normalised depth TacTip's force is 2x below GelSight's and 4x below
    uSkin's.  Tolerance: a factor 1.5 either way (measured here: 2.00 and 4.00)."""
    hetero = params["sensors"]["gelsight-A-II"]
    assert hetero["max_depth_mm"] == 1.0 and hetero["body"] == "gelsight-A-II"
    assert params["sensors"]["gelsight-r10"]["max_depth_mm"] == 1.4       # the material study's d_max
    f = {s: _force_at_max_normalised_depth(params, indenter_artifact, s)
         for s in ("gelsight-A-II", "tactip", "uskin")}
    assert 2 / 1.5 < f["gelsight-A-II"] / f["tactip"] < 2 * 1.5
    assert 4 / 1.5 < f["uskin"] / f["tactip"] < 4 * 1.5
    assert f["uskin"] > f["gelsight-A-II"] > f["tactip"]


def test_gelsight_force_range(params, indenter_artifact, run_node):
    """Paper: normal -16..0 N and shear -6..6 N over the GelSight collection protocol.

    Representative subset: the 12 seen indenters at the centre point pressed to the protocol's
    1 mm, sheared 1 mm in 4 directions.  Tolerance: the extreme normal force within 25% of
    16 N, the extreme shear within a factor 1.5 of 6 N (measured: -15.8 N, 5.6 N)."""
    tr = collection_trajectory(n_points=1, n_directions=4, depth_step_mm=1.0, max_depth_mm=1.0,
                               indenters=SEEN)
    spec = params["sensors"]["gelsight-r10"]
    chunks, _ = run_node(deform_sequence(
        indenters=indenter_artifact, sim_trajectory={}, collection_trajectory=tr,
        sensor="gelsight-r10", spec=spec, materials=params["materials"],
        contacts_per_indenter=0, frame_stride=1000))          # each movement's target only
    force = np.concatenate([c["force"] for c in chunks])
    assert len(chunks) == 12
    assert 16 / 1.25 < -force[:, 2].min() < 16 * 1.25
    assert force[:, 2].max() <= 0.0                          # the pad never pulls
    shear = np.abs(force[:, :2]).max()
    assert 6 / 1.5 < shear < 6 * 1.5
    assert force[:, 0].min() == pytest.approx(-force[:, 0].max(), rel=0.1)   # symmetric range
