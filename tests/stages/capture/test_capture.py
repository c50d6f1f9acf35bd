"""Node `capture` end to end against the loopback emulators: physics, staging, faults, resume."""
import json
import os

import numpy as np
import pytest

from stages.capture import DeviceError
from stages.common import InputError
from tests.helpers import drain

LABELS = ("force", "torque", "position", "target", "depth", "normalised_depth", "shift", "phase",
          "contact_id", "indenter_id", "paired", "frame")


@pytest.fixture(scope="module")
def baseline(run_capture, tmp_path_factory):
    """An uninterrupted capture with robot + NetF/T + camera."""
    return run_capture(tmp_path_factory.mktemp("baseline"))


@pytest.fixture(scope="module")
def twin(ci, meshes, trajectory):
    """The deform node's answer for the same frames, sensor and meshes."""
    from stages.sim.deform import deform_sequence
    chunks, final = drain(deform_sequence(
        indenters=meshes, sim_trajectory={}, collection_trajectory=trajectory, sensor="gelsight-r10",
        spec=ci["sensors"]["gelsight-r10"], materials=ci["materials"]))
    out = {k: np.concatenate([c[k] for c in chunks]) for k in ("force", "position", "displacement", "frame")}
    return out, final


def _same(a, b, keys=LABELS + ("raw", "camera_valid")):
    for k in keys:
        if k in a or k in b:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_forces_positions_and_images_follow_the_twin(baseline, twin):
    data, final = baseline
    ref, deform = twin
    n = len(ref["force"])
    # 2 contacts of 25 frames: the untouched start, the 0.5 mm press, 2 x 2 shear legs, the release
    assert n == 50 and data["force"].shape == (n, 3) and data["force"].dtype == np.float32
    np.testing.assert_array_equal(data["frame"], ref["frame"])
    # NetF/T counts (1e6 per N) after the tare of a 0.12/-0.08/0.35 N bias: micro-newton agreement
    np.testing.assert_allclose(data["force"], ref["force"], atol=2e-6)
    assert data["force"][:, 2].min() < -0.5 and np.abs(data["force"][:, 0]).max() > 0.2
    np.testing.assert_allclose(data["position"], ref["position"], atol=1e-9)
    np.testing.assert_allclose(data["depth"], -data["position"][:, 2])
    # every sensor sample is taken after the robot stopped, and the labels follow the trajectory
    ts = data["timestamps"]
    assert np.all(ts["netft"] >= ts["robot"]) and np.all(ts["camera"] >= ts["robot"])
    assert data["raw"].shape == (n, 60, 80, 3) and data["camera_valid"].all()
    # frames are the pattern moved by the twin's displacement field, downsized like the camera's
    import cv2
    from stages.capture.twin import marker_image, marker_layout
    markers = marker_layout("gelsight-A-II", 7)
    for k in (5, 30):
        full = marker_image(markers, ref["displacement"][k], deform["grid_x"], deform["grid_y"])
        small = cv2.resize(full, (80, 60), interpolation=cv2.INTER_AREA)
        assert np.abs(small.astype(int) - data["raw"][k]).max() <= 1
    moved = np.abs(data["raw"].astype(int) - final["reference_raw"][None]).mean(axis=(1, 2, 3))
    assert moved[np.argmax(-data["force"][:, 2])] > 0.3 and moved[-1] == 0.0   # pressed vs lifted
    assert final["attrs"]["netft_lost"] == 0 and final["attrs"]["sessions"] == 1
    assert final["attrs"]["frames"] == n and final["attrs"]["contacts"] == 2


def test_staging_file_is_removed_after_sealing(run_capture, tmp_path):
    run_capture(tmp_path, devices=("robot", "netft"))
    assert os.listdir(tmp_path) == []


def _interrupted(run_capture, staging, match, **faults):
    with pytest.raises(DeviceError, match=match) as err:
        run_capture(staging, **faults)
    (path,) = staging.glob("capture-*.h5")
    import h5py
    with h5py.File(path, "r") as f:
        staged = {k: f[k][()] for k in ("force", "frame", "raw") if k in f}
        rows = int(f.attrs["committed_rows"])
    return str(err.value), staged, rows


def test_disconnect_keeps_complete_contacts_and_resumes(run_capture, baseline, tmp_path):
    data, _ = baseline
    # 8 tare + 25 frames for the first contact, 8 tare + 4 frames of the second, then silence
    msg, staged, rows = _interrupted(run_capture, tmp_path, r"^netft 127\.0\.0\.1:\d+: no reply for 0\.\d s after "
                                     r"45 samples \(trajectory frame 29, contact 1\)$",
                                     netft={"faults": {"disconnect_after": 45}})
    assert rows == 25 and len(staged["force"]) == 25
    np.testing.assert_array_equal(staged["force"], data["force"][:25])
    resumed, final = run_capture(tmp_path, netft={"timeout_s": 1.0})   # patience may change
    _same(resumed, data)
    assert final["attrs"]["sessions"] == 2 and os.listdir(tmp_path) == []


def test_resume_refuses_other_parameters(run_capture, tmp_path):
    _interrupted(run_capture, tmp_path, "netft", netft={"faults": {"disconnect_after": 45}})
    with pytest.raises(ValueError, match=r"capture-gelsight-r10\.h5 holds a capture with other parameters "
                                         r"\(differs in camera\.out_size\)"):
        run_capture(tmp_path, camera={"out_size": [30, 40]})


def test_lost_udp_packets_are_counted_or_fatal(run_capture, baseline, tmp_path):
    data, _ = baseline
    got, final = run_capture(tmp_path / "a", netft={"faults": {"drop_every": 12}, "max_lost_fraction": 0.1})
    lost, received = final["attrs"]["netft_lost"], final["attrs"]["netft_received"]
    # every 12th record sent is dropped; a reply later than retry_s (a busy machine) is asked
    # for again and counted as lost too, so a few more may be lost than were dropped
    dropped = (received + lost) // 12
    assert dropped <= lost <= dropped + 3 and lost >= 5
    _same(got, data)                              # a lost reply is asked for again: same data
    with pytest.raises(DeviceError, match=r"^netft 127\.0\.0\.1:\d+: 10 of 21 records lost \(47\.6%, limit 5%\) "
                                          r"\(trajectory frame 2, contact 0\)$"):
        run_capture(tmp_path / "b", netft={"faults": {"drop_every": 2}})


def test_dropped_camera_frames_repeat_the_last_frame(run_capture, baseline, tmp_path):
    data, _ = baseline
    # every 5 reads the last 3 fail: with 2 retries every third sample gets no frame at all
    cam = {"retries": 2, "max_invalid_fraction": 0.5, "faults": {"drop_every": 5, "drop_burst": 3}}
    got, final = run_capture(tmp_path / "a", camera=cam)
    valid = got["camera_valid"]
    bad = np.flatnonzero(~valid)
    assert 10 <= bad.size <= 20 and final["attrs"]["camera_invalid"] == bad.size
    assert final["attrs"]["camera_dropped"] >= 3 * bad.size
    for k in bad:                                 # repeats the frame before; valid rows are fresh
        np.testing.assert_array_equal(got["raw"][k], got["raw"][k - 1])
    np.testing.assert_array_equal(got["raw"][valid], data["raw"][valid])
    np.testing.assert_array_equal(got["force"], data["force"])
    cam["max_invalid_fraction"] = 0.05
    with pytest.raises(DeviceError, match=r"^camera 0: 7 of 21 samples without a frame \(33%, limit 5%\) "
                                         r"\(trajectory frame 19, contact 0\)$"):
        run_capture(tmp_path / "b", camera=cam)


def test_camera_that_stops_delivering_is_an_error(run_capture, tmp_path):
    with pytest.raises(DeviceError, match=r"^camera 0: no frame for 10 reads after 33 samples "
                                         r"\(trajectory frame 32, contact 1\)$"):
        run_capture(tmp_path, camera={"faults": {"disconnect_after": 30}})


def test_a_camera_lost_at_the_end_of_a_contact_does_not_commit_it(run_capture, baseline, tmp_path):
    """The camera serves 24 frames (the reference and the first contact's first 23 rows) and no
    more: the first contact would end in two repeated frames marked invalid.  It is not
    committed; the resume captures it again, so the dataset equals an uninterrupted one."""
    data, _ = baseline
    msg, staged, rows = _interrupted(run_capture, tmp_path, r"^camera 0: no frame for 10 reads after 26 samples "
                                                            r"\(end of contact 0, which is captured again\)$",
                                     camera={"faults": {"disconnect_after": 24}},
                                     netft={"timeout_s": 5.0})    # the camera's error, not a slow F/T's
    assert rows == 0 and len(staged["raw"]) == 0
    resumed, final = run_capture(tmp_path, netft={"timeout_s": 5.0})
    _same(resumed, data)
    assert resumed["camera_valid"].all() and final["attrs"]["sessions"] == 2


def test_protective_stop_then_resume(run_capture, baseline, tmp_path):
    data, _ = baseline
    # moves: clearance, approach, 25 frames, lift (28); second contact (another indenter):
    # clearance, approach, then its 8th frame is move 38
    msg, staged, rows = _interrupted(run_capture, tmp_path, r"^robot twin: protective stop at move 38 "
                                                            r"\(trajectory frame 32, contact 1\)$",
                                     robot={"faults": {"protective_stop_at": 38}})
    assert rows == 25
    resumed, final = run_capture(tmp_path)
    _same(resumed, data)
    assert final["attrs"]["sessions"] == 2


def test_operator_tool_changes_stop_and_resume(run_capture, baseline, tmp_path):
    data, _ = baseline
    session = {"tool_change": "operator"}
    with pytest.raises(DeviceError, match=r"^robot twin: mount indenter 'prism' \(replacing 'sphere'\), then run "
                                          r"the capture again to continue$"):
        run_capture(tmp_path, session=session)
    resumed, final = run_capture(tmp_path, session=session)
    _same(resumed, data)
    assert final["attrs"]["sessions"] == 2


def test_serial_ft_xela_and_slcan_agree_with_the_twin(run_capture, tmp_path, ci, meshes, trajectory):
    from stages.markers.uskin import taxel_signals
    from stages.sim.deform import deform_sequence
    a, fa = run_capture(tmp_path / "a", devices=("robot", "serial_ft", "xela"), sensor="uskin",
                        xela={"emulator": {"hex": True}})
    b, fb = run_capture(tmp_path / "b", devices=("robot", "netft", "slcan"), sensor="uskin")
    chunks, final = drain(deform_sequence(indenters=meshes, sim_trajectory={}, collection_trajectory=trajectory,
                                          sensor="uskin", spec=ci["sensors"]["uskin"], materials=ci["materials"]))
    force = np.concatenate([c["force"] for c in chunks])
    disp = np.concatenate([c["displacement"] for c in chunks])
    # 6 decimals on the serial line, and the solver's tolerance (1e-5 of a depth): the emulators'
    # world warm-starts each contact's iteration from its own last frame, deform from the sequence's
    tol = 2e-6 + 1e-5 * float(np.abs(force).max())
    np.testing.assert_allclose(a["force"], force, atol=tol)
    np.testing.assert_allclose(b["force"], force, atol=tol)
    signals = taxel_signals(disp, final["grid_x"], final["grid_y"], pad_mm=ci["sensors"]["uskin"]["pad_mm"],
                            noise=0.0)
    np.testing.assert_array_equal(a["signals"], signals)
    np.testing.assert_array_equal(b["signals"], signals)
    assert a["signals"][:, :, 2].max() > 32768 + 200                 # pressing raises z
    np.testing.assert_array_equal(fa["reference_signals"], np.full((16, 3), 32768))
    assert fa["attrs"]["xela_lost"] == 0 and fb["attrs"]["slcan_lost"] == 0


def test_slcan_disconnect_names_the_port(run_capture, tmp_path):
    with pytest.raises(DeviceError, match=r"^slcan /dev/pts/\d+: disconnected after 3 samples"):
        run_capture(tmp_path, devices=("robot", "slcan"), sensor="uskin", slcan={"faults": {"disconnect_after": 3}})


def test_bad_requests_fail_before_any_device_starts(run_capture, tmp_path):
    with pytest.raises(InputError, match="devices must include robot"):
        run_capture(tmp_path, devices=("netft",))
    with pytest.raises(InputError, match="choose one of netft / serial_ft"):
        run_capture(tmp_path, devices=("robot", "netft", "serial_ft"))
    with pytest.raises(InputError, match=r"netft: unknown parameter\(s\) hostname"):
        run_capture(tmp_path, netft={"hostname": "x"})
    with pytest.raises(InputError, match=r"netft: unknown fault\(s\) explode"):
        run_capture(tmp_path, netft={"faults": {"explode": 1}})
    bad = [({"robot": {"origin": [0.4, 0.0]}}, r"robot origin must be 6 finite numbers"),
           ({"netft": {"sign": [1.0, 1.0]}}, r"netft.sign must be 3 finite numbers \(Fx, Fy, Fz\), got \[1.0, 1.0\]"),
           ({"camera": {"size": [480]}}, r"camera.size must be 2 whole numbers >= 1, got \[480\]"),
           ({"camera": {"out_size": [0, 64]}}, r"camera.out_size must be 2 whole numbers >= 1, got \[0, 64\]"),
           ({"camera": {"pattern": "nosuch"}}, r"unknown marker pattern 'nosuch'"),
           ({"session": {"frame_stride": 0}}, r"frame_stride must be a whole number >= 1, got 0"),
           ({"session": {"indenters": ["nosuch"]}}, r"unknown indenter\(s\) nosuch"),
           ({"session": {"tool_change": "bogus"}}, r"tool_change must be auto or operator, got 'bogus'"),
           ({"netft": {"mode": "bogus"}}, r"netft: mode must be poll or stream, got 'bogus'")]
    for params, message in bad:
        with pytest.raises(InputError, match=message) as err:
            run_capture(tmp_path, **params)
        assert err.value.user_error is True
    assert os.listdir(tmp_path) == []       # caught before the staging file is made


def test_a_staging_file_with_no_contact_yields_to_corrected_parameters(run_capture, baseline, tmp_path):
    """A run that failed before its first contact leaves nothing worth keeping: the corrected
    run starts over instead of refusing the file's other parameters."""
    with pytest.raises(DeviceError):
        run_capture(tmp_path, netft={"faults": {"disconnect_after": 1}}, camera={"out_size": [30, 40]})
    assert len(os.listdir(tmp_path)) == 1
    got, _ = run_capture(tmp_path)
    np.testing.assert_array_equal(got["force"], baseline[0]["force"])


# -- sealing through the engine: a kill at any instant keeps the staging file or the artifact --

SEAL_GRAPH = '''\
from pipeline import Graph

GRAPH = Graph()
GRAPH.node("indenters", "stages.sim.indenters:indenter_set", params={"names": "names"}, version="1")
GRAPH.node("trajectory", "stages.sim.trajectory:collection_trajectory",
           params={k: f"trajectory.{k}" for k in ("indenters", "n_points", "n_directions", "depth_step_mm",
                                                   "max_depth_mm", "speed_mm_s")}, version="1")
GRAPH.node("capture", "stages.capture.session:capture",
           inputs={"trajectory": "trajectory", "indenters": "indenters"},
           params={k: f"capture.{k}" for k in ("devices", "emulate", "sensor", "rate_hz", "session", "robot",
                                               "netft", "serial_ft", "camera", "xela", "slcan", "spec",
                                               "materials")},
           source=True)
'''

# SIGKILL this process at one point of publishing the capture (the engine's code runs as is)
KILL_AT = '''\
import os, signal, sys
from pathlib import Path
point, real = sys.argv[1], (os.replace, os.fsync, os.remove)
die = lambda: os.kill(os.getpid(), signal.SIGKILL)
def replace(src, dst, *a, **k):
    artifact = Path(dst).parent.name == "objects" and str(dst).endswith(".h5")
    if artifact and point == "before_replace":
        die()
    real[0](src, dst, *a, **k)
def fsync(fd):
    real[1](fd)
    if point == "after_folder_fsync" and os.path.isdir(f"/proc/self/fd/{fd}"):
        die()
def remove(path, *a, **k):
    if point == "before_staging_removed" and "capture-" in str(path):
        die()
    real[2](path, *a, **k)
os.replace, os.fsync, os.remove = replace, fsync, remove
from pipeline.cli import main
sys.exit(main(["run", "capture"]))
'''


@pytest.fixture(scope="module")
def seal_project(tmp_path_factory, ci):
    import yaml
    from tests.helpers import ROOT
    root = tmp_path_factory.mktemp("seal")
    (root / "pyproject.toml").write_text('[tool.pipeline]\ngraph = "sealgraph:GRAPH"\n')
    (root / "sealgraph.py").write_text(SEAL_GRAPH)
    params = {"names": ["sphere", "prism"],
              "trajectory": {"indenters": ["sphere", "prism"], "n_points": 1, "n_directions": 2,
                             "depth_step_mm": 0.5, "max_depth_mm": 0.5, "speed_mm_s": 20.0},
              "capture": {**{k: ci["capture"][k] for k in ("robot", "netft", "serial_ft", "camera", "xela", "slcan")},
                          "devices": ["robot", "netft"], "emulate": True, "sensor": "gelsight-r10", "rate_hz": 0.0,
                          "session": {"contacts_per_indenter": 0, "frame_stride": 1},
                          "spec": ci["sensors"]["gelsight-r10"], "materials": ci["materials"]}}
    (root / "params.yaml").write_text(yaml.safe_dump(params))
    env = {**os.environ, "PYTHONPATH": f"{root}{os.pathsep}{ROOT}"}
    env.pop("PIPELINE_STORE", None)
    assert _pipeline(root, env, "run", "indenters", "trajectory", "--store", "inputs").returncode == 0
    (key,) = [n["key"] for n in json.loads(_pipeline(root, env, "status", "--json", "capture", "--store",
                                                     "inputs").stdout)["nodes"] if n["name"] == "capture"]
    return root, env, key


def _pipeline(root, env, *args, code=None):
    import subprocess
    import sys
    cmd = [sys.executable, "-c", code, *args] if code else [sys.executable, "-m", "pipeline", *args]
    return subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("point", ["before_replace", "after_folder_fsync", "before_staging_removed"])
def test_a_kill_while_sealing_keeps_the_staging_file_or_the_artifact(seal_project, point):
    """Before: the staging file was deleted as the node returned, before the engine published
    the artifact, and a kill in that window left the rows only in a temp file gc deletes."""
    import shutil
    import h5py
    root, env, key = seal_project
    store = root / "artifacts"
    shutil.rmtree(store, ignore_errors=True)
    shutil.copytree(root / "inputs", store)            # indenters and trajectory, built once
    killed = _pipeline(root, env, point, code=KILL_AT)
    assert killed.returncode == -9, killed.stderr[-2000:]
    staging = store / "staging" / "capture-gelsight-r10.h5"
    artifact = store / "objects" / f"{key}.h5"
    assert artifact.exists() == (point != "before_replace")
    assert staging.exists()                      # removed only after the durable publish
    with h5py.File(staging, "r") as f:
        assert f.attrs["complete"] and int(f.attrs["committed_contacts"]) == 2
        staged = {k: f[k][()] for k in ("force", "frame", "timestamps/netft")}
    again = _pipeline(root, env, "run", "capture", "--json")
    assert again.returncode == 0, again.stderr[-2000:]
    status = {n["name"]: n["status"] for n in json.loads(again.stdout)["nodes"]}["capture"]
    assert status == ("ran" if point == "before_replace" else "cached")
    with h5py.File(artifact, "r") as f:
        for name, value in staged.items():       # the rows captured before the kill, not new ones
            np.testing.assert_array_equal(f[name][()], value, err_msg=name)
    assert staging.exists() == (point != "before_replace")   # a kill after publishing leaves it over


def test_a_forced_capture_never_republishes_an_earlier_sessions_staging_file(seal_project):
    """Before: a kill between the publish and the staging file's removal left the finished
    session's file, and `run capture --force` republished its old rows as new in a second."""
    import shutil
    root, env, key = seal_project
    store = root / "artifacts"
    shutil.rmtree(store, ignore_errors=True)
    shutil.copytree(root / "inputs", store)
    assert _pipeline(root, env, "before_staging_removed", code=KILL_AT).returncode == -9
    staging = store / "staging" / "capture-gelsight-r10.h5"
    artifact = store / "objects" / f"{key}.h5"
    before = artifact.read_bytes()
    forced = _pipeline(root, env, "run", "capture", "--force")
    assert forced.returncode == 2 and "Traceback" not in forced.stderr
    assert forced.stderr.startswith(f"pipeline: error: node capture: staging file {staging} holds an earlier session's "
                                    "finished capture (2 contacts") and forced.stderr.count("\n") == 1
    assert artifact.read_bytes() == before and staging.exists()
    staging.unlink()                                   # as the line says: a fresh capture
    fresh = _pipeline(root, env, "run", "capture", "--force", "--json")
    assert fresh.returncode == 0, fresh.stderr[-2000:]
    assert {n["name"]: n["status"] for n in json.loads(fresh.stdout)["nodes"]}["capture"] == "ran"
    assert not staging.exists()
