"""capture_calibration: the material-compensation calibration captured from a (here emulated)
sensor, and the transfers that compensate with it instead of the twin's calibrate."""
import os

import numpy as np
import pytest

from stages.common import InputError, attrs_of
from tests.helpers import concat, drain

SENSOR = "gelsight-r10"


@pytest.fixture(scope="module")
def calibration_inputs(ci):
    from stages.sim.indenters import indenter_set
    from stages.sim.trajectory import calibration_trajectory
    tp = ci["calibration_trajectory"]
    trajectory = calibration_trajectory(**{k: tp[k] for k in ("max_depth_mm", "n_steps", "repetitions", "indenter",
                                                                "rate_hz")})
    art = indenter_set([tp["indenter"]])
    meshes = {f"meshes/{n}/{k}": v for n, m in art["meshes"].items() for k, v in m.items()}
    return trajectory, meshes


def _run(ci, calibration_inputs, staging, sensor=SENSOR, devices=("robot", "netft"), session=None):
    from stages.capture.session import capture_calibration
    trajectory, meshes = calibration_inputs
    params = {"robot": {}, "netft": {"retry_s": 0.02, "timeout_s": 0.5,
                                     "emulator": {"bias": [0.12, -0.08, 0.35, 0.004, -0.002, 0.001]}},
              "serial_ft": {"retry_s": 0.02, "timeout_s": 0.5}, "camera": {}, "xela": {}, "slcan": {}}
    return capture_calibration(trajectory=trajectory, sensor=sensor, spec=ci["sensors"][sensor],
                               devices=list(devices), session=session, rate_hz=0.0, staging_dir=str(staging),
                               emulate=True, indenters=meshes, materials=ci["materials"], **params)


def _capture(*args, **kwargs):
    chunks, final = drain(_run(*args, **kwargs))
    return concat(chunks), final


@pytest.fixture(scope="module")
def captured(ci, calibration_inputs, tmp_path_factory):
    return _capture(ci, calibration_inputs, tmp_path_factory.mktemp("staging"))


@pytest.fixture(scope="module")
def twin(ci, calibration_inputs):
    from stages.sim.deform import calibrate
    trajectory, meshes = calibration_inputs
    return calibrate(indenters=meshes, trajectory=trajectory, sensor=SENSOR, spec=ci["sensors"][SENSOR],
                     materials=ci["materials"])


def test_captured_calibration_presses_the_sensors_depth_and_reads_the_twins_force(captured, twin, ci):
    arrays, final = captured
    # every calibration frame, pressed to the sensor's max_depth_mm (1.4 mm), not the trajectory's
    assert arrays["force"].shape == twin["force"].shape
    np.testing.assert_allclose(arrays["depth"], twin["depth"], atol=1e-9)
    np.testing.assert_allclose(arrays["normalised_depth"], twin["normalised_depth"], atol=1e-6)
    np.testing.assert_array_equal(arrays["phase"], twin["phase"])
    # the F/T reading, its bias tared away, is the twin's force
    np.testing.assert_allclose(arrays["force"], twin["force"], atol=1e-3)
    attrs = final["attrs"]
    spec = ci["sensors"][SENSOR]
    assert attrs["calibration"] is True and attrs["indenter"] == ci["calibration_trajectory"]["indenter"]
    assert attrs["max_depth_mm"] == spec["max_depth_mm"] and attrs["pad_mm"] == spec["pad_mm"]
    # nothing the twin's catalogue knows and a lab would not (its friction, modulus, hysteresis)
    assert not {"mu", "E_pa", "hysteresis", "material"} & set(attrs) and "mu" not in attrs_of(twin)


def test_captured_calibration_gives_the_twins_compensation_curves(captured, twin):
    from stages.force.compensation import curves_from_calibration
    arrays, _ = captured
    assert "loading" not in arrays            # the captured phase tells loading from unloading
    got, want = curves_from_calibration(arrays), curves_from_calibration(twin)
    for curve in ("loading", "unloading"):
        np.testing.assert_allclose(getattr(got, curve), getattr(want, curve), rtol=1e-3, atol=1e-3)


def test_calibration_without_phase_or_loading_is_named():
    from stages.force.compensation import curves_from_calibration
    with pytest.raises(ValueError, match=r"calibration: no loading or phase"):
        curves_from_calibration({"normalised_depth": np.zeros(3), "force": np.zeros((3, 3))})


def test_calibration_capture_needs_a_force_sensor(ci, calibration_inputs, tmp_path):
    with pytest.raises(InputError, match=r"capture_calibration\[gelsight-r10\]: devices \['robot', 'camera'\] "
                                         r"read no force: add one of netft / serial_ft"):
        _capture(ci, calibration_inputs, tmp_path, devices=["robot", "camera"])
    with pytest.raises(InputError, match=r"capture_calibration\[gelsight-r10\]: unknown session setting\(s\) "
                                         r"depth_scale \(known: name, chunk_frames, tool_change\)"):
        _capture(ci, calibration_inputs, tmp_path, session={"depth_scale": 2.0})
    with pytest.raises(InputError, match=r"capture_calibration\[gelsight-A-I\]: a calibration belongs to a "
                                         r"body; list gelsight-A-II \(the body gelsight-A-I rides on\)"):
        _capture(ci, calibration_inputs, tmp_path, sensor="gelsight-A-I")
    assert os.listdir(tmp_path) == []


def test_calibration_staging_is_its_own_file_and_is_removed(ci, calibration_inputs, tmp_path):
    """The calibration stages into capture-<sensor>-calibration.h5, so an interrupted collection
    capture of the same sensor (capture-<sensor>.h5) is left alone."""
    other = tmp_path / f"capture-{SENSOR}.h5"
    other.write_bytes(b"an interrupted collection capture")
    gen = _run(ci, calibration_inputs, tmp_path)
    next(gen)
    assert (tmp_path / f"capture-{SENSOR}-calibration.h5").exists()
    drain(gen)
    assert sorted(os.listdir(tmp_path)) == [f"capture-{SENSOR}.h5"]
    assert other.read_bytes() == b"an interrupted collection capture"


def test_transfers_compensate_with_a_captured_calibration_of_their_sensor(captured, twin):
    from stages.force.fit import calibrations as _calibrations
    arrays, _ = captured
    tactip = {"force": np.zeros((2, 3)), "attrs": {"sensor": "tactip"}}
    assert attrs_of(twin)["sensor"] == SENSOR            # calibrate names its body: the lookup's key
    chosen, which = _calibrations((tactip, twin), {SENSOR: arrays})
    assert chosen[0] is tactip and chosen[1] is arrays
    assert which == {"target": f"capture_calibration[sensor={SENSOR}]"}
    chosen, which = _calibrations((tactip, twin), {})
    assert chosen == (tactip, twin) and which == {}
    chosen, which = _calibrations((None, None), {SENSOR: arrays})    # the authors' homo set: none
    assert chosen == (None, None) and which == {}


def test_the_graph_gathers_captured_calibrations_into_every_transfer():
    """By default no sensor is captured and every transfer gathers none; a listed sensor's
    capture_calibration joins every transfer, and the scheduler asks for it to be captured."""
    from stages.graph import GRAPH
    from tests.helpers import load_params
    params = load_params("ci")
    inst = GRAPH.expand(params)
    assert not any(n.startswith("capture_calibration[") for n in inst)
    transfers = [i for n, i in inst.items() if n.startswith("transfer[")]
    assert transfers and all(i.inputs["captured_calibrations"] == {} for i in transfers)
    params["capture"]["calibration"]["sensors"] = [SENSOR]
    inst = GRAPH.expand(params)
    name = f"capture_calibration[sensor={SENSOR}]"
    assert inst[name].node.source
    transfers = [i for n, i in inst.items() if n.startswith("transfer[")]
    assert all(i.inputs["captured_calibrations"] == {SENSOR: name} for i in transfers)


def test_captured_shear_leg_moves_the_robot_at_the_sensors_stroke(ci, calibration_inputs, tmp_path):
    """The calibration's shear leg (its trajectory holds the touchdown point and the shift apart)
    is driven by the robot at the sensor's own stroke (shear_scale), as calibrate presses its
    twin: the F/T reads the twin's shear, and the captured calibration gives genforce_plus's
    shear_calibration the twin's shear-to-normal ratio."""
    from stages.capture.session import capture_calibration
    from stages.force.compensation import shear_ratio
    from stages.sim.deform import calibrate
    from stages.sim.trajectory import calibration_trajectory
    tp = ci["calibration_trajectory"]
    trajectory = calibration_trajectory(max_depth_mm=tp["max_depth_mm"], n_steps=4, repetitions=1,
                                        indenter=tp["indenter"], shear_mm=1.0, shear_steps=3)
    _, meshes = calibration_inputs
    spec = {**ci["sensors"][SENSOR], "shear_scale": 1.5}
    chunks, final = drain(capture_calibration(
        trajectory=trajectory, sensor=SENSOR, spec=spec, devices=["robot", "netft"], session=None, rate_hz=0.0,
        staging_dir=str(tmp_path), emulate=True, indenters=meshes, materials=ci["materials"], robot={},
        netft={"retry_s": 0.02, "timeout_s": 0.5}, serial_ft={"retry_s": 0.02, "timeout_s": 0.5}, camera={},
        xela={}, slcan={}))
    got = concat(chunks)
    want = calibrate(indenters=meshes, trajectory=trajectory, sensor=SENSOR, spec=spec, materials=ci["materials"])
    assert np.abs(want["shift"]).max() == pytest.approx(1.5)
    np.testing.assert_allclose(got["shift"], want["shift"], atol=1e-6)
    np.testing.assert_allclose(got["force"], want["force"], atol=1e-3)
    assert np.abs(got["force"][:, 0]).max() > 0.1                   # the leg reads shear
    assert shear_ratio(got) == pytest.approx(shear_ratio(want), rel=1e-3)
