"""Force/torque sensor clients: ATI NetF/T over UDP and a serial line protocol.

Wire formats:
  NetF/T (ATI RDT over UDP, port 49152): request ``>HHI`` = (0x1234, command, count), command
      2 = stream ``count`` records (0 = until stopped), 0 = stop; record 36 bytes ``>3I6i`` =
      rdt_seq, ft_seq, status, Fx Fy Fz Tx Ty Tz in counts (``counts_per_N``,
      ``counts_per_Nm``).  rdt_seq restarts at 1 with every request, so lost records are rdt_seq
      gaps in a stream and unanswered requests in poll mode.  A nonzero status word (sensor
      error, saturation) raises.
  serial F/T (this project's line protocol, ASCII, 8N1): host sends "R\\n" (one record),
      "S\\n" (stream at the device's rate) or "P\\n" (stop); the device answers lines
      "seq,Fx,Fy,Fz,Tx,Ty,Tz\\n", seq a decimal uint32 counting every record the device made
      (gaps = lost lines), forces in N and torques in N m as decimals.

Lost records are counted; once their fraction of all records passes ``max_lost_fraction``
(after ``min_records``) the client raises.  ``sign`` (per axis, applied to force and torque)
and ``tare_samples`` are read by the capture session: the mounting's axes -> the paper's pad
frame, and how many readings the tare at each lifted pose averages.
"""
from __future__ import annotations

import socket
import struct
import threading
import time
from collections import deque

import numpy as np

from stages.capture import DeviceError
from stages.capture.devices import Device, Sample
from stages.common import InputError

NETFT_PORT = 49152
NETFT_REQUEST = struct.Struct(">HHI")
NETFT_RECORD = struct.Struct(">3I6i")
NETFT_HEADER = 0x1234


class _LossCheck:
    """Counts lost records and raises once their fraction passes the limit."""

    def _check_loss(self) -> None:
        total = self.received + self.lost
        limit = float(self.p["max_lost_fraction"])
        if total >= int(self.p["min_records"]) and self.lost > limit * total:
            raise self.error(f"{self.lost} of {total} records lost ({100 * self.lost / total:.1f}%, "
                             f"limit {100 * limit:g}%)")


class _Records:
    """Stream mode: a reader thread buffers records; reads hand them out by receive time."""

    def _init_records(self) -> None:
        self._records: deque = deque(maxlen=4096)
        self._cond, self._stop, self._thread = threading.Condition(), threading.Event(), None
        self._failure: str | None = None

    def _start_reader(self) -> None:
        self._thread = threading.Thread(target=self._receive_loop, name=self.name, daemon=True)
        self._thread.start()

    def _stop_reader(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(1.0)
            self._thread = None

    def _push(self, rec: Sample) -> None:
        with self._cond:
            self._records.append(rec)
            self._cond.notify_all()

    def _fail(self, why: str) -> None:
        with self._cond:
            self._failure = why
            self._cond.notify_all()

    def _read_stream(self, since: float) -> Sample:
        """The first record received `settle_s` after `since`."""
        start, since = since, since + float(self.p["settle_s"])
        timeout = float(self.p["timeout_s"])
        with self._cond:
            while True:
                fresh = next((r for r in self._records if r.t >= since), None)
                if fresh is not None:
                    return self._accept(fresh)
                if self._failure:
                    raise self.error(self._failure)
                last = self._records[-1].t if self._records else start
                quiet = time.time() - max(last, start)
                if quiet > timeout:
                    raise self.error(f"no reply for {quiet:.1f} s after {self.samples} samples")
                self._cond.wait(0.05)


class NetFT(_Records, _LossCheck, Device):
    """ATI NetF/T over UDP (see the module docstring for the wire format)."""
    kind = "netft"
    defaults = {"host": "192.168.1.1", "port": NETFT_PORT, "counts_per_N": 1e6, "counts_per_Nm": 1e6,
                "timeout_s": 2.0, "mode": "poll", "retry_s": 0.05, "settle_s": 0.0,
                "max_lost_fraction": 0.05, "min_records": 20, "sign": [1.0, 1.0, 1.0], "tare_samples": 8}

    def __init__(self, params=None):
        super().__init__(params)
        if self.p["mode"] not in ("poll", "stream"):
            raise InputError(f"netft: mode must be poll or stream, got {self.p['mode']!r}")
        self.sock, self.received, self.lost, self.bad, self._last_rdt = None, 0, 0, 0, None
        self._init_records()

    @property
    def name(self) -> str:
        return f"netft {self.p['host']}:{self.p['port']}"

    def open(self):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.connect((self.p["host"], int(self.p["port"])))
        except OSError as exc:
            self.sock.close()
            raise self.error(exc.strerror or str(exc)) from None
        if self.p["mode"] == "stream":
            self._send(2, 0)
            self._start_reader()
        return self

    def _send(self, command: int, count: int) -> None:
        try:
            self.sock.send(NETFT_REQUEST.pack(NETFT_HEADER, command, count))
        except OSError as exc:
            raise self.error(exc.strerror or str(exc)) from None

    def _decode(self, data: bytes, t: float) -> Sample | None:
        if len(data) != NETFT_RECORD.size:
            self.bad += 1
            return None
        rdt, ft_seq, status, *counts = NETFT_RECORD.unpack(data)
        if self._last_rdt is not None and rdt > self._last_rdt:
            self.lost += rdt - self._last_rdt - 1
        self._last_rdt = rdt
        self.received += 1
        c = np.asarray(counts, float)
        return Sample(t, force=c[:3] / float(self.p["counts_per_N"]), torque=c[3:] / float(self.p["counts_per_Nm"]),
                      status=status, ft_seq=ft_seq)

    def _receive_loop(self) -> None:
        self.sock.settimeout(0.1)
        while not self._stop.is_set():
            try:
                data = self.sock.recv(64)
            except TimeoutError:
                continue
            except OSError as exc:
                if not self._stop.is_set():
                    self._fail(exc.strerror or str(exc))
                return
            rec = self._decode(data, time.time())
            if rec is not None:
                self._push(rec)

    def _accept(self, rec: Sample) -> Sample:
        if rec["status"]:
            raise self.error(f"status word 0x{rec['status']:08x} (sensor error or saturation)")
        self.samples += 1
        self._check_loss()
        return rec

    def read(self, since: float) -> Sample:
        if self.p["mode"] == "stream":
            return self._read_stream(since)
        t0, timeout = time.time(), float(self.p["timeout_s"])
        self.sock.setblocking(False)
        try:                                      # replies to earlier, timed-out requests
            while True:
                self.sock.recv(64)
        except (BlockingIOError, OSError):
            pass
        self.sock.settimeout(float(self.p["retry_s"]))
        while True:
            self._last_rdt = None                 # every request starts a new RDT stream
            self._send(2, 1)
            try:
                data = self.sock.recv(64)
            except TimeoutError:
                self.lost += 1
                if time.time() - t0 > timeout:
                    raise self.error(f"no reply for {time.time() - t0:.1f} s after {self.samples} samples") from None
                continue
            except ConnectionRefusedError:
                raise self.error("connection refused (nothing listens at this address)") from None
            rec = self._decode(data, time.time())
            if rec is not None:
                return self._accept(rec)

    def counts(self) -> dict:
        return {"samples": self.samples, "received": self.received, "lost": self.lost, "bad": self.bad}

    def close(self) -> None:
        if self.sock is None:
            return
        try:
            self._send(0, 0)
        except DeviceError:
            pass
        self._stop_reader()
        self.sock.close()
        self.sock = None


def _serial_error(device: Device, exc: Exception) -> DeviceError:
    return device.error(f"disconnected after {device.samples} samples ({exc})")


class SerialFT(_Records, _LossCheck, Device):
    """A force/torque sensor streaming this project's ASCII line protocol over a serial port."""
    kind = "serial_ft"
    defaults = {"port": "/dev/ttyUSB0", "baudrate": 115200, "timeout_s": 2.0, "mode": "poll",
                "retry_s": 0.05, "settle_s": 0.0, "max_lost_fraction": 0.05, "min_records": 20,
                "sign": [1.0, 1.0, 1.0], "tare_samples": 8}

    def __init__(self, params=None):
        super().__init__(params)
        if self.p["mode"] not in ("poll", "stream"):
            raise InputError(f"serial_ft: mode must be poll or stream, got {self.p['mode']!r}")
        self.port, self.received, self.lost, self.bad, self._last_seq = None, 0, 0, 0, None
        self._init_records()

    @property
    def name(self) -> str:
        return f"serial_ft {self.p['port']}"

    def open(self):
        import serial
        try:
            self.port = serial.Serial(self.p["port"], int(self.p["baudrate"]), timeout=float(self.p["retry_s"]))
            self.port.reset_input_buffer()
            if self.p["mode"] == "stream":
                self.port.write(b"S\n")
        except (serial.SerialException, OSError) as exc:
            raise self.error(f"cannot open ({exc})") from None
        if self.p["mode"] == "stream":
            self._start_reader()
        return self

    def _receive_loop(self) -> None:
        import serial
        while not self._stop.is_set():
            try:
                line = self.port.readline()
            except (serial.SerialException, OSError) as exc:
                if not self._stop.is_set():
                    self._fail(f"disconnected after {self.received} records ({exc})")
                return
            rec = self._parse(line) if line.endswith(b"\n") else None
            if rec is not None:
                self._push(rec)

    def _accept(self, rec: Sample) -> Sample:
        self.samples += 1
        self._check_loss()
        return rec

    def _parse(self, line: bytes) -> Sample | None:
        try:
            fields = line.decode("ascii").strip().split(",")
            seq, values = int(fields[0]), np.asarray([float(v) for v in fields[1:]], float)
        except (UnicodeDecodeError, ValueError, IndexError):
            seq, values = None, None
        if values is None or values.shape != (6,):
            self.bad += 1
            return None
        if self._last_seq is not None:
            self.lost += (seq - self._last_seq - 1) % 2 ** 32
        self._last_seq = seq
        self.received += 1
        return Sample(time.time(), force=values[:3], torque=values[3:], seq=seq)

    def read(self, since: float) -> Sample:
        if self.p["mode"] == "stream":
            return self._read_stream(since)
        import serial
        t0, timeout = time.time(), float(self.p["timeout_s"])
        try:
            self.port.reset_input_buffer()
            self.port.write(b"R\n")
            while True:
                line = self.port.readline()
                rec = self._parse(line) if line.endswith(b"\n") else None
                if rec is not None:
                    return self._accept(rec)
                if time.time() - t0 > timeout:
                    raise self.error(f"no reply for {time.time() - t0:.1f} s after {self.samples} samples")
                if not line:
                    self.port.write(b"R\n")
        except (serial.SerialException, OSError) as exc:
            raise _serial_error(self, exc) from None

    def counts(self) -> dict:
        return {"samples": self.samples, "received": self.received, "lost": self.lost, "bad": self.bad}

    def close(self) -> None:
        if self.port is not None:
            self._stop_reader()
            try:
                if self.p["mode"] == "stream":
                    self.port.write(b"P\n")
                self.port.close()
            except Exception:                     # noqa: BLE001 - a vanished port closes anyway
                pass
            self.port = None
