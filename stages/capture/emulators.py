"""Loopback emulators of the capture hardware, all driven by one twin World (twin.py).

Each emulator binds 127.0.0.1 (port 0: an ephemeral port) or a pseudo-terminal, runs in a
daemon thread, and starts/stops cleanly (context managers).  They speak the wire formats of
devices.py, so the capture code under test is the code that talks to the hardware:

  RobotTwin      the methods of ur_rtde's control and receive interfaces: moveL moves the
                 twin's tip at once and solves the contact; getActualTCPPose reads it back
  NetFTServer    ATI NetF/T RDT over UDP: answers stream requests (count 0 = until stopped,
                 count n = n records) at `rate_hz`, forces from the twin's wrench + `bias`
  SerialFTDevice the serial F/T line protocol on a pty (poll "R", stream "S", stop "P")
  SlcanDevice    the SLCAN taxel protocol on a pty (remote frame -> 16 taxel frames)
  XelaServer     XELA's WebSocket JSON at `rate_hz`, stamped with the twin state's time
  TwinCapture    a cv2.VideoCapture look-alike whose frames are the twin's marker images

Faults (each device's `faults` mapping; 0 = off): disconnect_after K (records / messages /
frames / scans served, then silence or a closed connection), drop_every n (every n-th record
or scan is never sent; for the camera every n-th read fails, `drop_burst` reads in a row), and
the robot's protective_stop_at K (the K-th moveL fails and the robot stays stopped).
"""
from __future__ import annotations

import abc
import json
import os
import select
import socket
import threading
import time
import tty
from typing import Callable, Mapping

import numpy as np

from stages.capture.devices import DEVICES, Camera, Robot
from stages.capture.ft import NETFT_HEADER, NETFT_RECORD, NETFT_REQUEST, NetFT, SerialFT
from stages.capture.tactile import TAXELS, Slcan, Xela
from stages.capture.twin import ContactTwin, World, marker_layout
from stages.common import InputError

FAULTS = {"robot": ("protective_stop_at",), "netft": ("disconnect_after", "drop_every"),
          "serial_ft": ("disconnect_after", "drop_every"), "slcan": ("disconnect_after", "drop_every"),
          "xela": ("disconnect_after",), "camera": ("disconnect_after", "drop_every", "drop_burst")}
SETTINGS = {"robot": (), "netft": ("rate_hz", "bias", "noise_N", "seed"),
            "serial_ft": ("rate_hz", "bias"), "slcan": ("gains", "noise"),
            "xela": ("rate_hz", "gains", "noise", "hex"), "camera": ("supersample",)}


class _Thread(abc.ABC):
    """start()/stop() of a daemon loop thread, as a context manager."""

    def __init__(self):
        self._stop, self._thread = threading.Event(), None

    def start(self):
        self._thread = threading.Thread(target=self._loop, name=type(self).__name__, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    @abc.abstractmethod
    def _loop(self) -> None:
        """The server's body, run in its thread until stop()."""


class _Faults:
    """Which records a device serves: counts them, drops every n-th, goes silent after K."""

    def __init__(self, disconnect_after: int = 0, drop_every: int = 0):
        self.disconnect_after, self.drop_every = int(disconnect_after), int(drop_every)
        self.produced, self.dead = 0, False

    def next(self) -> bool:
        """Produce one record; True when it is to be sent."""
        self.produced += 1
        if self.disconnect_after and self.produced > self.disconnect_after:
            self.dead = True
        if self.dead:
            return False
        return not (self.drop_every and self.produced % self.drop_every == 0)


# ---------------------------------------------------------------------------------- robot
class RobotTwin:
    """The ur_rtde control + receive interfaces of a UR5e whose tool is the twin's indenter."""

    def __init__(self, world: World, *, protective_stop_at: int = 0):
        self.world, self.stop_at = world, int(protective_stop_at)
        self.moves, self.stopped = 0, False

    def moveL(self, pose, speed: float = 0.25, acceleration: float = 1.2, asynchronous: bool = False) -> bool:
        if self.stopped:
            return False
        self.moves += 1
        if self.stop_at and self.moves >= self.stop_at:
            self.stopped = True
            return False
        self.world.move_to(pose)
        return True

    def getActualTCPPose(self) -> list:
        return self.world.snapshot()[1].tolist()

    def isProtectiveStopped(self) -> bool:
        return self.stopped

    def isConnected(self) -> bool:
        return True

    def stopScript(self) -> None:
        pass

    def disconnect(self) -> None:
        pass


# --------------------------------------------------------------------------------- NetF/T
class NetFTServer(_Thread):
    """ATI NetF/T RDT server on 127.0.0.1 (UDP)."""

    def __init__(self, world: World, *, counts_per_N=1e6, counts_per_Nm=1e6, bias=(0.0,) * 6,
                 rate_hz: float = 1000.0, noise_N: float = 0.0, seed: int = 0, disconnect_after=0,
                 drop_every=0):
        super().__init__()
        self.world, self.period = world, 1.0 / float(rate_hz)
        self.scale = np.array([counts_per_N] * 3 + [counts_per_Nm] * 3, float)
        self.bias, self.noise = np.asarray(bias, float), float(noise_N)
        self.rng = np.random.default_rng(seed)
        self.faults = _Faults(disconnect_after, drop_every)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.host, self.port = self.sock.getsockname()
        self.ft_seq = 0

    def _record(self, rdt: int) -> bytes:
        _, _, state = self.world.snapshot()
        wrench = self.world.wrench(state) + self.bias
        if self.noise:
            wrench[:3] += self.rng.normal(0.0, self.noise, 3)
        self.ft_seq += 1
        counts = np.rint(wrench * self.scale).astype(np.int64)
        return NETFT_RECORD.pack(rdt, self.ft_seq % 2 ** 32, 0, *(int(c) for c in counts))

    def _loop(self) -> None:
        client, remaining, rdt, due = None, 0, 0, 0.0
        while not self._stop.is_set():
            wait = 0.1 if remaining == 0 else due - time.monotonic()
            try:
                if wait > 0:
                    self.sock.settimeout(wait)
                    data, addr = self.sock.recvfrom(64)
                else:
                    self.sock.setblocking(False)
                    data, addr = self.sock.recvfrom(64)
            except (TimeoutError, BlockingIOError):
                data = None
            except OSError:
                return                                      # socket closed by stop()
            if data is not None and len(data) == NETFT_REQUEST.size:
                header, command, count = NETFT_REQUEST.unpack(data)
                if header == NETFT_HEADER and command == 2:
                    client, remaining, rdt, due = addr, (count or -1), 0, time.monotonic()
                elif header == NETFT_HEADER and command == 0:
                    remaining = 0
                continue
            if remaining and time.monotonic() >= due:
                rdt += 1
                record = self._record(rdt)
                if self.faults.next():
                    try:
                        self.sock.sendto(record, client)
                    except OSError:
                        pass
                remaining -= remaining > 0
                due += self.period

    def stop(self) -> None:
        self._stop.set()
        self.sock.close()
        super().stop()


# ----------------------------------------------------------------------- serial devices
class _PtyDevice(_Thread):
    """A device on the master side of a pseudo-terminal; clients open `port` (the slave)."""
    terminator = b"\n"

    def __init__(self, world: World, *, disconnect_after=0, drop_every=0):
        super().__init__()
        self.world, self.faults = world, _Faults(disconnect_after, drop_every)
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)                  # no echo, no line editing
        os.set_blocking(self.master, False)
        self.port = os.ttyname(self._slave)

    def _write(self, data: bytes) -> None:
        try:
            os.write(self.master, data)
        except (BlockingIOError, OSError):      # nobody reads: the line is lost, as on a wire
            pass

    def _loop(self) -> None:
        buf = b""
        while not self._stop.is_set() and not self.faults.dead:
            ready, _, _ = select.select([self.master], [], [], self._timeout())
            if ready:
                try:
                    buf += os.read(self.master, 4096)
                except (BlockingIOError, OSError):
                    time.sleep(0.01)
                while self.terminator in buf:
                    cmd, buf = buf.split(self.terminator, 1)
                    self._command(cmd.strip())
            self._tick()
        if self.faults.dead:                     # unplugged: the client's reads fail
            os.close(self.master)
            self.master = -1

    def _timeout(self) -> float:
        return 0.05

    @abc.abstractmethod
    def _command(self, cmd: bytes) -> None:
        """Answer one command line from the client."""

    def _tick(self) -> None:
        pass

    def stop(self) -> None:
        super().stop()
        for fd in (self.master, self._slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master = self._slave = -1


class SerialFTDevice(_PtyDevice):
    """The serial F/T line protocol (devices.py) on a pty, forces from the twin."""

    def __init__(self, world: World, *, rate_hz: float = 500.0, bias=(0.0,) * 6, **faults):
        super().__init__(world, **faults)
        self.period, self.bias = 1.0 / float(rate_hz), np.asarray(bias, float)
        self.streaming, self.due = False, 0.0

    def _emit(self) -> None:
        seq = self.faults.produced + 1
        if not self.faults.next():
            return
        _, _, state = self.world.snapshot()
        w = self.world.wrench(state) + self.bias
        self._write((f"{seq % 2 ** 32}," + ",".join(f"{v:.6f}" for v in w) + "\n").encode())

    def _command(self, cmd: bytes) -> None:
        if cmd == b"R":
            self._emit()
        elif cmd in (b"S", b"P"):
            self.streaming, self.due = cmd == b"S", time.monotonic()

    def _timeout(self) -> float:
        return max(self.due - time.monotonic(), 0.0) if self.streaming else 0.05

    def _tick(self) -> None:
        if self.streaming and time.monotonic() >= self.due:
            self._emit()
            self.due += self.period


class SlcanDevice(_PtyDevice):
    """A USB-CAN adapter (SLCAN) with the uSkin on its bus, scans from the twin."""
    terminator = b"\r"

    def __init__(self, world: World, *, request_id: int = 0x100, **faults):
        super().__init__(world, **faults)
        self.request_id, self.is_open = int(request_id), False

    def _command(self, cmd: bytes) -> None:
        if cmd in (b"C", b"O") or (cmd[:1] == b"S" and cmd[1:].isdigit()):
            self.is_open = cmd == b"O" or (self.is_open and cmd[:1] == b"S")
            self._write(b"\r")
        elif cmd == f"r{self.request_id:03X}0".encode() and self.is_open:
            self._write(b"z\r")
            scan = self.faults.produced + 1
            if not self.faults.next():
                return
            _, _, state = self.world.snapshot()
            sig = self.world.signals(state)
            self._write(b"".join(f"t{self.request_id + 1 + k:03X}8{x:04X}{y:04X}{z:04X}{scan % 2 ** 16:04X}\r".encode()
                                 for k, (x, y, z) in enumerate(sig)))
        else:
            self._write(b"\a")


# ------------------------------------------------------------------------------ XELA
class XelaServer(_Thread):
    """XELA's WebSocket server on 127.0.0.1: one JSON message per period to every client."""

    def __init__(self, world: World, *, rate_hz: float = 100.0, sensor_id: str = "1", hex: bool = False,
                 disconnect_after: int = 0):
        super().__init__()
        from websockets.sync.server import serve
        self.world, self.period, self.sensor_id, self.hex = world, 1.0 / float(rate_hz), str(sensor_id), hex
        self.faults = _Faults(disconnect_after)
        self.server = serve(self._handler, "127.0.0.1", 0)
        self.port = self.server.socket.getsockname()[1]
        self.url = f"ws://127.0.0.1:{self.port}"

    def _loop(self) -> None:
        self.server.serve_forever()

    def _handler(self, ws) -> None:
        from websockets.exceptions import ConnectionClosed
        due = time.monotonic()
        while not self._stop.is_set():
            t, _, state = self.world.snapshot()
            number = self.faults.produced + 1
            if not self.faults.next():
                ws.close()
                return
            values = self.world.signals(state).ravel().tolist()
            data = [f"{v:04X}" for v in values] if self.hex else values
            msg = {"message": number, "time": t, "sensors": 1,
                   self.sensor_id: {"data": data, "sensor": self.sensor_id, "taxels": TAXELS,
                                    "model": "uSPa44", "calibrated": None}}
            try:
                ws.send(json.dumps(msg))
            except ConnectionClosed:
                return
            due += self.period
            time.sleep(max(due - time.monotonic(), 0.0))

    def stop(self) -> None:
        self._stop.set()
        self.server.shutdown()
        super().stop()


# ------------------------------------------------------------------------------ camera
class TwinCapture:
    """A cv2.VideoCapture look-alike: every read renders the twin's current marker image."""

    def __init__(self, world: World, *, disconnect_after: int = 0, drop_every: int = 0, drop_burst: int = 1):
        self.world, self.disconnect_after = world, int(disconnect_after)
        self.drop_every, self.drop_burst = int(drop_every), int(drop_burst)
        self.reads = self.frames = 0
        self.opened = True

    def isOpened(self) -> bool:
        return self.opened

    def read(self):
        self.reads += 1
        gone = self.disconnect_after and self.frames >= self.disconnect_after
        dropped = self.drop_every and (self.reads - 1) % self.drop_every >= self.drop_every - self.drop_burst
        if not self.opened or gone or dropped:
            return False, None
        self.frames += 1
        _, _, state = self.world.snapshot()
        import cv2
        return True, cv2.cvtColor(self.world.image(state), cv2.COLOR_RGB2BGR)

    def grab(self) -> bool:
        return self.read()[0]

    def get(self, prop: int) -> float:
        import cv2
        return float(self.frames) if prop == cv2.CAP_PROP_POS_FRAMES else 0.0

    def set(self, prop: int, value) -> bool:
        return True

    def release(self) -> None:
        self.opened = False


def write_video(path, frames, fps: float = 40.0, fourcc: str = "FFV1") -> str:
    """Write RGB frames (N, H, W, 3) uint8 to a video file (FFV1 is lossless); returns the path."""
    import cv2
    frames = np.asarray(frames, np.uint8)
    h, w = frames.shape[1:3]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), float(fps), (w, h))
    if not writer.isOpened():
        raise ValueError(f"cannot write video {path} with codec {fourcc}")
    for f in frames:
        writer.write(np.ascontiguousarray(f[..., ::-1]))
    writer.release()
    return str(path)


# ------------------------------------------------------------------------------ bundle
def split_params(device: str, params: Mapping) -> tuple[dict, dict, dict]:
    """A device's params -> (client params, emulator settings, faults), unknown keys refused."""
    params = dict(params or {})
    settings, faults = dict(params.pop("emulator", None) or {}), dict(params.pop("faults", None) or {})
    for what, given, known in (("emulator setting", settings, SETTINGS[device]), ("fault", faults, FAULTS[device])):
        unknown = set(given) - set(known)
        if unknown:
            raise InputError(f"{device}: unknown {what}(s) {', '.join(sorted(unknown))} "
                             f"(known: {', '.join(known) or 'none'})")
    return params, settings, {k: int(v) for k, v in faults.items()}


class Emulators:
    """The twin world plus one emulator per requested device, and clients wired to them.

    devices: names from devices.DEVICES; params: device name -> its params mapping;
    spec/material: the sensor's catalogue entry and elastomer; mesh_of: indenter name -> mesh.
    """

    def __init__(self, devices, params: Mapping, *, spec: Mapping, material: Mapping,
                 mesh_of: Callable[[str], object]):
        self.devices = list(devices)
        unknown = [d for d in self.devices if d not in DEVICES]
        if unknown:
            raise InputError(f"unknown device(s) {', '.join(unknown)} (known: {', '.join(DEVICES)})")
        self.parts = {d: split_params(d, params.get(d, {})) for d in self.devices}
        robot = {**Robot.defaults, **self.parts.get("robot", ({}, {}, {}))[0]}
        cam = {**Camera.defaults, **self.parts.get("camera", ({}, {}, {}))[0]}
        taxels = (self.parts.get("xela") or self.parts.get("slcan") or ({}, {}, {}))[1]
        self.world = World(ContactTwin(spec, material, mesh_of), origin=robot["origin"], yaw_deg=robot["yaw_deg"],
                           markers=(marker_layout(cam["pattern"], int(cam["pattern_seed"]))
                                    if "camera" in self.devices else None),
                           image_size=cam["size"],
                           supersample=self.parts.get("camera", ({}, {}, {}))[1].get("supersample", 1),
                           gains=taxels.get("gains"), noise=taxels.get("noise", 0.0))
        self.servers: list = []
        self.clients: dict = {}

    def start(self):
        w = self.world
        for d in self.devices:
            p, s, f = self.parts[d]
            if d == "robot":
                self.clients[d] = Robot({**p, "ip": "twin"}, rtde=RobotTwin(w, **f))
            elif d == "netft":
                c = {**NetFT.defaults, **p}
                srv = NetFTServer(w, counts_per_N=c["counts_per_N"], counts_per_Nm=c["counts_per_Nm"], **s, **f)
                self.clients[d] = NetFT({**p, "host": srv.host, "port": srv.port})
            elif d == "serial_ft":
                srv = SerialFTDevice(w, **s, **f)
                self.clients[d] = SerialFT({**p, "port": srv.port})
            elif d == "slcan":
                srv = SlcanDevice(w, request_id=int({**Slcan.defaults, **p}["request_id"]), **f)
                self.clients[d] = Slcan({**p, "port": srv.port})
            elif d == "xela":
                srv = XelaServer(w, sensor_id=str({**Xela.defaults, **p}["sensor_id"]),
                                 **{k: v for k, v in s.items() if k in ("rate_hz", "hex")}, **f)
                self.clients[d] = Xela({**p, "url": srv.url})
            else:                                                   # camera
                self.clients[d] = Camera(p, capture=TwinCapture(w, **f))
            if d not in ("robot", "camera"):
                self.servers.append(srv.start())
        return self

    def stop(self) -> None:
        for srv in self.servers:
            srv.stop()
        self.servers = []

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()
