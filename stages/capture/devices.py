"""Clients of the capture hardware: the common interface, the robot and the camera.

Every client is built from its params mapping (unknown keys refused; `faults` and `emulator`
are the emulators' and ignored here), has open()/close() and is a context manager.  A sensor
is read with ``read(since)``: the first sample taken at or after host time ``since``
(``time.time()``, s), waiting at most ``timeout_s``; a device that stays silent or disconnects
raises DeviceError naming it.  ``counts()`` says what went wrong along the way (lost packets,
dropped frames) for the artifact's attributes.  The force/torque clients are in ft.py, the
uSkin clients in tactile.py; ``client_class(name)`` finds any of them.

Freshness.  The capture reads every sensor after the robot has stopped at a trajectory sample,
so a sample must not predate that stop.  Request-driven reads are fresh by construction:
NetF/T and serial F/T in ``mode: poll`` (one request, one record), the camera (the frame read
after the stop; ``flush`` discards frames a camera buffered), SLCAN (a remote frame asks for
one scan).  Streams are judged by time: XELA messages carry the server's ``time`` (the XELA
server runs on the capture PC); NetF/T and serial F/T in ``mode: stream`` take the first
record received ``settle_s`` after the stop.
"""
from __future__ import annotations

import importlib
import socket
import struct
import time
from typing import Mapping

import numpy as np

from stages.capture import DeviceError
from stages.common import InputError

RTDE_PORT = 30004
DEVICES = {"robot": "devices:Robot", "netft": "ft:NetFT", "serial_ft": "ft:SerialFT",
           "camera": "devices:Camera", "xela": "tactile:Xela", "slcan": "tactile:Slcan"}


def client_class(name: str) -> type:
    """The client class of a device name (robot, netft, serial_ft, camera, xela, slcan)."""
    if name not in DEVICES:
        raise InputError(f"unknown device {name!r} (known: {', '.join(DEVICES)})")
    module, cls = DEVICES[name].split(":")
    return getattr(importlib.import_module(f"stages.capture.{module}"), cls)


class Sample:
    """One reading: host time `t` (s) and named arrays."""
    __slots__ = ("t", "values")

    def __init__(self, t: float, **values):
        self.t, self.values = float(t), values

    def __getitem__(self, key):
        return self.values[key]


class Device:
    """Common plumbing: params with defaults, a name for errors, context management."""
    kind = "device"
    defaults: dict = {}

    def __init__(self, params: Mapping | None = None):
        unknown = set(params or {}) - set(self.defaults) - {"faults", "emulator"}
        if unknown:
            raise InputError(f"{self.kind}: unknown parameter(s) {', '.join(sorted(unknown))} "
                             f"(known: {', '.join(sorted(self.defaults))})")
        self.p = {**self.defaults, **{k: v for k, v in (params or {}).items() if k in self.defaults}}
        self.samples = 0

    @property
    def name(self) -> str:
        return self.kind

    def error(self, what: str) -> DeviceError:
        return DeviceError(f"{self.name}: {what}")

    def counts(self) -> dict:
        return {"samples": self.samples}

    def open(self):
        return self

    def close(self) -> None:
        pass

    def __enter__(self):
        return self.open()

    def __exit__(self, *exc):
        self.close()


# ---------------------------------------------------------------------------------- robot
def _recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = b""
    while len(buf) < n:
        part = sock.recv(n - len(buf))
        if not part:
            raise ConnectionResetError("connection closed by the peer")
        buf += part
    return buf


def probe_rtde(host: str, timeout_s: float, port: int = RTDE_PORT) -> None:
    """Negotiate RTDE protocol version 2 (package 'V' = 86) with a socket timeout.

    ur_rtde's constructors block forever, holding the GIL, when something accepts the
    connection but never answers (measured with ur_rtde 1.6.5), so no worker thread can time
    them out; this handshake in Python can, and runs before them.
    """
    where = f"robot {host}:{port}"
    try:
        with socket.create_connection((host, port), timeout=timeout_s) as sock:
            sock.settimeout(timeout_s)
            sock.sendall(struct.pack(">HBH", 5, 86, 2))
            size, kind = struct.unpack(">HB", _recv_exact(sock, 3))
            body = _recv_exact(sock, max(size - 3, 0))
    except ConnectionRefusedError:
        raise DeviceError(f"{where}: connection refused (robot off, wrong address, or RTDE disabled)") from None
    except TimeoutError:
        raise DeviceError(f"{where}: no RTDE reply for {timeout_s:g} s") from None
    except OSError as exc:
        raise DeviceError(f"{where}: {exc.strerror or exc}") from None
    if kind != 86 or not body or body[0] != 1:
        raise DeviceError(f"{where}: the RTDE server refused protocol version 2")


class Robot(Device):
    """UR5e over ur_rtde: blocking moveL to TCP poses, measured TCP pose, protective stops.

    `rtde`: an object with the methods of both ur_rtde interfaces this class uses (moveL,
    getActualTCPPose, isProtectiveStopped, isConnected, stopScript, disconnect) -- the
    emulator's twin; None opens the real robot at `ip` (ur_rtde is imported only then).
    """
    kind = "robot"
    defaults = {"ip": "192.168.1.102", "speed": 0.02, "acceleration": 0.2, "timeout_s": 2.0,
                "origin": [0.4, 0.0, 0.1, 0.0, 3.14159265, 0.0], "yaw_deg": 0.0, "approach_mm": 2.0,
                "clearance_mm": 20.0}

    def __init__(self, params=None, rtde=None):
        super().__init__(params)
        self._twin, self.control, self.receive, self.moves = rtde, None, None, 0

    @property
    def name(self) -> str:
        return f"robot {self.p['ip']}"

    def open(self):
        if self._twin is not None:
            self.control = self.receive = self._twin
            return self
        probe_rtde(self.p["ip"], float(self.p["timeout_s"]))
        try:
            import rtde_control
            import rtde_receive
        except ImportError:
            raise self.error("the ur_rtde package is not installed (pip install ur_rtde), "
                             "or capture with emulate: true") from None
        try:
            self.receive = rtde_receive.RTDEReceiveInterface(self.p["ip"])
            self.control = rtde_control.RTDEControlInterface(self.p["ip"])
        except RuntimeError as exc:
            self.close()
            raise self.error(str(exc)) from None
        return self

    def move(self, pose) -> None:
        """Blocking linear move to a TCP pose; a failed move or a protective stop raises."""
        self.moves += 1
        ok = self.control.moveL([float(v) for v in pose], float(self.p["speed"]),
                                float(self.p["acceleration"]))
        if self.receive.isProtectiveStopped():
            raise self.error(f"protective stop at move {self.moves}")
        if not ok:
            raise self.error(f"moveL failed at move {self.moves}")

    def pose(self) -> Sample:
        if not self.receive.isConnected():
            raise self.error(f"connection lost after {self.moves} moves")
        pose = np.asarray(self.receive.getActualTCPPose(), float)
        self.samples += 1
        return Sample(time.time(), pose=pose)

    def counts(self) -> dict:
        return {"samples": self.samples, "moves": self.moves}

    def close(self) -> None:
        for iface, calls in ((self.control, ("stopScript", "disconnect")), (self.receive, ("disconnect",))):
            for call in calls if iface is not None and iface is not self._twin else ():
                try:
                    getattr(iface, call)()
                except RuntimeError:
                    pass
        self.control = self.receive = None


# ---------------------------------------------------------------------------------- camera
class Camera(Device):
    """An OpenCV camera (device index) or video file, frames as RGB (H, W, 3) uint8.

    A failed read is a dropped frame: the read is retried `retries` times; when all fail the
    sample repeats the last good frame and is marked invalid (`valid` False).  Frame counters
    that jump (CAP_PROP_POS_FRAMES, files and some cameras) count frames the source skipped.
    `max_consecutive` failed reads in a row mean the camera is gone (DeviceError), as does an
    invalid fraction above `max_invalid_fraction` once `min_samples` samples were taken.
    `capture`: a VideoCapture-like object to use instead of opening `source` (the emulator's).
    """
    kind = "camera"
    defaults = {"source": 0, "size": [480, 640], "fps": 40.0, "retries": 2, "max_consecutive": 10,
                "max_invalid_fraction": 0.1, "min_samples": 20, "flush": 0,
                "out_size": None, "pattern": "gelsight-A-II", "pattern_seed": 7}

    def __init__(self, params=None, capture=None):
        super().__init__(params)
        self.cap, self._given = capture, capture
        self.dropped = self.skipped = self.invalid = self._consecutive = 0
        self._last, self._last_pos = None, None

    @property
    def name(self) -> str:
        return f"camera {self.p['source']}"

    def open(self):
        import cv2
        if self.cap is None:
            src = self.p["source"]
            self.cap = cv2.VideoCapture(int(src) if str(src).isdigit() else str(src))
            if isinstance(src, int) or str(src).isdigit():
                h, w = self.p["size"]
                self.cap.set(cv2.CAP_PROP_FRAME_WIDTH, w)
                self.cap.set(cv2.CAP_PROP_FRAME_HEIGHT, h)
                self.cap.set(cv2.CAP_PROP_FPS, float(self.p["fps"]))
                self.cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        if not self.cap.isOpened():
            raise self.error("cannot open the camera or video file")
        return self

    def _frame(self, bgr: np.ndarray) -> np.ndarray:
        import cv2
        h, w = (int(v) for v in self.p["size"])
        if bgr.shape[:2] != (h, w):
            bgr = cv2.resize(bgr, (w, h), interpolation=cv2.INTER_AREA)
        return cv2.cvtColor(bgr, cv2.COLOR_GRAY2RGB if bgr.ndim == 2 else cv2.COLOR_BGR2RGB)

    def read(self, since: float) -> Sample:
        import cv2
        for _ in range(int(self.p["flush"])):
            self.cap.grab()
        for _ in range(int(self.p["retries"]) + 1):
            ok, bgr = self.cap.read()
            if ok and bgr is not None:
                break
            self.dropped += 1
            self._consecutive += 1
            if self._consecutive >= int(self.p["max_consecutive"]):
                raise self.error(f"no frame for {self._consecutive} reads after {self.samples} samples")
        else:
            bgr = None
        t = time.time()
        self.samples += 1
        if bgr is None:
            self.invalid += 1
            if self._last is None:
                raise self.error("no frame at the first read")
            n, limit = self.samples, float(self.p["max_invalid_fraction"])
            if n >= int(self.p["min_samples"]) and self.invalid > limit * n:
                raise self.error(f"{self.invalid} of {n} samples without a frame "
                                 f"({100 * self.invalid / n:.0f}%, limit {100 * limit:g}%)")
            return Sample(t, image=self._last, valid=False)
        self._consecutive = 0
        pos = self.cap.get(cv2.CAP_PROP_POS_FRAMES)
        if pos > 0 and self._last_pos is not None and pos - self._last_pos > 1:
            self.skipped += int(pos - self._last_pos - 1)
        self._last_pos = pos if pos > 0 else None
        self._last = self._frame(bgr)
        return Sample(t, image=self._last, valid=True)

    def confirm(self) -> None:
        """After samples that got no fresh frame: read until one comes (not a sample), or raise
        as read does once `max_consecutive` reads in a row failed.  The rows that repeated the
        last frame may have been a camera going away: data ending in them is committed only
        once the camera is known to deliver."""
        while self._consecutive:
            ok, bgr = self.cap.read()
            if ok and bgr is not None:
                self._consecutive = 0
                return
            self.dropped += 1
            self._consecutive += 1
            if self._consecutive >= int(self.p["max_consecutive"]):
                raise self.error(f"no frame for {self._consecutive} reads after {self.samples} samples")

    def counts(self) -> dict:
        return {"samples": self.samples, "dropped": self.dropped, "invalid": self.invalid,
                "skipped": self.skipped}

    def close(self) -> None:
        if self.cap is not None:
            self.cap.release()
        self.cap = self._given
