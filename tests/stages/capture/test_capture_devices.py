"""Device clients against the loopback emulators and real sockets; poses; the staging file."""
import socket
import threading
import time

import numpy as np
import pytest

from stages.capture import DeviceError
from stages.capture.devices import Camera, Robot
from stages.capture.emulators import (NetFTServer, RobotTwin, SerialFTDevice, TwinCapture, XelaServer,
                                      write_video)
from stages.capture.ft import NetFT, SerialFT
from stages.capture.poses import to_pose, to_sensor
from stages.capture.tactile import Xela
from stages.capture.twin import ContactTwin, World, marker_layout

BIAS = np.array([0.25, -0.5, 1.5, 0.01, -0.02, 0.03])


@pytest.fixture
def world(ci):
    """A twin with nothing mounted: every device reads the pad at rest."""
    spec = ci["sensors"]["gelsight-r10"]
    twin = ContactTwin(spec, ci["materials"]["r10"], mesh_of=None)
    return World(twin, origin=Robot.defaults["origin"], markers=marker_layout("gelsight-A-II"), image_size=(48, 64))


# ------------------------------------------------------------------------------ ur_rtde
def _free_loopback():
    """A 127.x.y.z address of this test run (nothing else listens on port 30004 there)."""
    rng = np.random.default_rng()
    return "127.%d.%d.%d" % tuple(rng.integers(2, 250, 3))


def test_robot_connection_refused_is_quick():
    t = time.monotonic()
    with pytest.raises(DeviceError, match=r"^robot 127\.\d+\.\d+\.\d+:30004: connection refused"):
        Robot({"ip": _free_loopback(), "timeout_s": 2.0}).open()
    assert time.monotonic() - t < 1.0


def test_ur_rtde_itself_raises_runtime_error_when_refused():
    """The behaviour Robot.open maps to DeviceError (ur_rtde 1.6.5)."""
    rtde_receive = pytest.importorskip("rtde_receive")
    with pytest.raises(RuntimeError, match="Could not connect"):
        rtde_receive.RTDEReceiveInterface(_free_loopback())


def test_robot_listener_that_never_answers_times_out():
    srv = socket.socket()
    for _ in range(5):
        host = _free_loopback()
        try:
            srv.bind((host, 30004))
            break
        except OSError:
            continue
    srv.listen(1)
    held = []
    threading.Thread(target=lambda: held.append(srv.accept()), daemon=True).start()
    t = time.monotonic()
    try:
        with pytest.raises(DeviceError, match=rf"^robot {host}:30004: no RTDE reply for 1 s$"):
            Robot({"ip": host, "timeout_s": 1.0}).open()
        assert 0.9 < time.monotonic() - t < 3.0
    finally:
        srv.close()
        for conn, _ in held:
            conn.close()


def test_robot_twin_moves_the_tip_and_stops(world):
    origin = Robot.defaults["origin"]
    with Robot({"ip": "twin", "yaw_deg": 30.0}, rtde=RobotTwin(world, protective_stop_at=3)) as robot:
        target = np.array([1.5, -2.0, 0.5])
        robot.move(to_pose(target, origin, 30.0))
        np.testing.assert_allclose(to_sensor(robot.pose()["pose"], origin, 30.0), target, atol=1e-12)
        robot.move(to_pose(target + [1, 0, 0], origin, 30.0))
        with pytest.raises(DeviceError, match="^robot twin: protective stop at move 3$"):
            robot.move(to_pose(target, origin, 30.0))


def test_poses_rotate_about_the_sensor_axis():
    origin = [0.4, -0.1, 0.2, 0.0, 3.14, 0.0]
    pose = to_pose([10.0, 0.0, -1.0], origin, yaw_deg=90.0)
    np.testing.assert_allclose(pose, [0.4, -0.09, 0.199, 0.0, 3.14, 0.0], atol=1e-12)
    np.testing.assert_allclose(to_sensor(pose, origin, 90.0), [10.0, 0.0, -1.0], atol=1e-9)
    with pytest.raises(ValueError, match="robot origin must be 6 finite numbers"):
        to_pose([0, 0, 0], [0.4, 0.0, 0.1])


# ------------------------------------------------------------------------------ F/T
def test_netft_stream_counts_rdt_gaps(world):
    with NetFTServer(world, bias=BIAS, rate_hz=500, drop_every=4) as srv, \
            NetFT({"host": srv.host, "port": srv.port, "mode": "stream", "max_lost_fraction": 0.5}) as ft:
        since = time.time()
        for _ in range(30):
            rec = ft.read(since)
            since = rec.t + 1e-6
        np.testing.assert_allclose(np.concatenate([rec["force"], rec["torque"]]), BIAS, atol=1e-6)
        c = ft.counts()
    # every 4th record of the stream is missing: lost / (received + lost) = 1/4 up to the ends
    assert c["received"] >= 30 and abs(c["lost"] - (c["received"] + c["lost"]) / 4) <= 1


def test_netft_stream_silence_is_an_error(world):
    with NetFTServer(world, rate_hz=500, disconnect_after=20) as srv, \
            NetFT({"host": srv.host, "port": srv.port, "mode": "stream", "timeout_s": 0.3}) as ft:
        with pytest.raises(DeviceError, match=rf"^netft 127\.0\.0\.1:{srv.port}: no reply for 0\.\d s "
                                              r"after \d+ samples$"):
            for _ in range(100):
                ft.read(time.time())


def test_netft_refused_when_nothing_listens():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    sock.close()
    with NetFT({"host": "127.0.0.1", "port": port, "timeout_s": 0.5}) as ft:
        with pytest.raises(DeviceError, match=rf"^netft 127\.0\.0\.1:{port}: connection refused"):
            ft.read(time.time())


def test_serial_ft_stream_and_unplug(world):
    with SerialFTDevice(world, rate_hz=400, bias=BIAS, drop_every=5, disconnect_after=60) as dev, \
            SerialFT({"port": dev.port, "mode": "stream", "max_lost_fraction": 0.5, "timeout_s": 0.5}) as ft:
        rec = ft.read(time.time())
        np.testing.assert_allclose(np.concatenate([rec["force"], rec["torque"]]), BIAS, atol=1e-6)
        with pytest.raises(DeviceError, match=rf"^serial_ft {dev.port}: (disconnected|no reply)"):
            for _ in range(200):
                rec = ft.read(rec.t + 1e-6)
        assert ft.lost >= 5 and ft.received >= 20


# ------------------------------------------------------------------------------ XELA
def test_xela_hex_messages_and_closed_connection(world):
    with XelaServer(world, rate_hz=200, hex=True, disconnect_after=15) as srv, \
            Xela({"url": srv.url, "timeout_s": 1.0}) as xela:
        first = xela.read(time.time())
        np.testing.assert_array_equal(first["signals"], np.full((16, 3), 32768))
        with pytest.raises(DeviceError, match=rf"^xela {srv.url}: connection closed after 15 messages$"):
            for _ in range(100):
                xela.read(time.time())


def test_xela_refused():
    with pytest.raises(DeviceError, match=r"^xela ws://127\.0\.0\.1:9: cannot connect"):
        Xela({"url": "ws://127.0.0.1:9", "timeout_s": 0.5}).open()


# ------------------------------------------------------------------------------ camera
def test_camera_reads_a_video_file_and_reports_its_end(world, tmp_path):
    from stages.capture.twin import marker_image
    rng = np.random.default_rng(0)
    twin = world.twin
    frames = []
    for k in range(5):               # the pattern under five random smooth displacement fields
        disp = np.zeros(twin.shape + (3,))
        disp[..., 0], disp[..., 1] = rng.normal(0, 0.3, 2)
        frames.append(marker_image(world.markers, disp, twin.grid_x, twin.grid_y, size=(48, 64)))
    path = write_video(tmp_path / "cam.avi", np.stack(frames))
    with Camera({"source": path, "size": [48, 64], "max_consecutive": 4}) as cam:
        got = [cam.read(0.0)["image"] for _ in range(5)]
        np.testing.assert_array_equal(np.stack(got), np.stack(frames))     # FFV1 is lossless
        assert cam.skipped == 0
        with pytest.raises(DeviceError, match=r"cam\.avi: no frame for 4 reads after 6 samples$"):
            for _ in range(3):
                cam.read(0.0)


def test_twin_camera_renders_the_current_state(world):
    cap = TwinCapture(world, drop_every=3)
    ok1, f1 = cap.read()
    ok2, _ = cap.read()
    ok3, f3 = cap.read()
    assert (ok1, ok2, ok3) == (True, True, False) and f3 is None
    np.testing.assert_array_equal(f1[..., 0], world.image(world.twin.rest)[..., 0])
    assert f1.shape == (48, 64, 3) and 0 < (f1 > 0).mean() < 0.5


# ------------------------------------------------------------------------------ staging
def test_staging_drops_a_partial_contact_and_guards_its_parameters(tmp_path):
    import h5py

    from stages.capture.staging import BLOCK, Staging
    path = tmp_path / "capture-x.h5"
    layout = {"force": ((3,), np.float32), "frame": ((), np.int64)}
    st = Staging(path, {"a": 1, "b": {"c": [1, 2]}}, layout)
    for k in range(3):
        st.append({"force": np.full(3, k), "frame": k})
    st.commit({"netft_lost": 2}, 1.5)
    for k in range(BLOCK + 2):                              # a contact cut short: never committed
        st.append({"force": np.full(3, 9), "frame": 9})
    st.f.flush()
    st.f.close()                                            # as if the process died here
    with h5py.File(path, "r") as f:
        assert f["frame"].shape == (3 + BLOCK,)             # full blocks reach the file early
    with pytest.raises(ValueError, match=r"capture-x\.h5 holds a capture with other parameters \(differs in b\.c\)"):
        Staging(path, {"a": 1, "b": {"c": [1, 3]}}, layout)
    st = Staging(path, {"a": 1, "b": {"c": [1, 2]}}, layout)
    assert st.rows == 3 and st.contacts_done == 1 and st.counts() == {"netft_lost": 2}
    np.testing.assert_array_equal(st.read("frame"), [0, 1, 2])
    assert int(st.get("sessions")) == 2
    st.close()
