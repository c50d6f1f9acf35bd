"""uSkin clients: the XELA server's WebSocket JSON, and SLCAN over a serial port.

Wire formats:
  XELA WebSocket: JSON messages {"message": n, "time": t, "<sensor id>": {"data": [...]}} with
      ``data`` 48 values (x, y, z per taxel, taxels row-major) as ints, hex strings or one
      comma-separated hex string; raw counts around 32768; parsed by
      stages.capture.xela.parse_xela.  Gaps in ``message`` count as lost messages.
  SLCAN (Lawicel ASCII over a serial port, this project's frame mapping; XELA's own CAN
      layout is not public): the adapter is set up with "C\\r", "S6\\r" (500 kbit/s),
      "O\\r"; a scan is requested with the remote frame "r1000\\r" (id 0x100, DLC 0); the
      sensor answers 16 data frames "tIII8" + 16 hex digits + "\\r" with id 0x101 + taxel
      (taxel = row * 4 + col) and data x, y, z (big-endian uint16 raw counts) and the scan
      counter (big-endian uint16, gaps = lost scans); the adapter's "z\\r" acks are skipped.
"""
from __future__ import annotations

import json
import struct
import threading
import time

import numpy as np

from stages.capture.devices import Device, Sample
from stages.capture.ft import _serial_error

TAXELS = 16


class Xela(Device):
    """XELA uSkin server over a WebSocket (about 100 Hz JSON messages), parsed by
    stages.capture.xela.parse_xela; `sensor_id` picks the sensor."""
    kind = "xela"
    defaults = {"url": "ws://127.0.0.1:5000", "sensor_id": "1", "timeout_s": 2.0}

    def __init__(self, params=None):
        super().__init__(params)
        self.ws, self.lost, self.bad, self.messages = None, 0, 0, 0
        self._latest: Sample | None = None
        self._closed: str | None = None
        self._cond, self._thread, self._last_no = threading.Condition(), None, None

    @property
    def name(self) -> str:
        return f"xela {self.p['url']}"

    def open(self):
        from websockets.sync.client import connect
        try:
            # entered like `with connect(...) as ws`, closed in close()
            self.ws = connect(self.p["url"], open_timeout=float(self.p["timeout_s"]), max_size=2 ** 22).__enter__()
        except (OSError, TimeoutError) as exc:
            raise self.error(f"cannot connect ({exc})") from None
        except Exception as exc:                  # noqa: BLE001 - websockets' handshake errors
            raise self.error(f"WebSocket handshake failed ({exc})") from None
        self._thread = threading.Thread(target=self._receive_loop, name=self.name, daemon=True)
        self._thread.start()
        return self

    def _receive_loop(self) -> None:
        from websockets.exceptions import ConnectionClosed

        from stages.capture.xela import parse_xela
        sensor = str(self.p["sensor_id"])
        try:
            for raw in self.ws:
                t = time.time()
                try:
                    msg = json.loads(raw)
                    signals = parse_xela(msg).get(sensor)
                except ValueError:
                    self.bad += 1
                    continue
                if signals is None:               # welcome / status messages, other sensors
                    continue
                number = msg.get("message")
                with self._cond:
                    if isinstance(number, int) and self._last_no is not None and number > self._last_no:
                        self.lost += number - self._last_no - 1
                    self._last_no = number if isinstance(number, int) else None
                    self.messages += 1
                    self._latest = Sample(float(msg.get("time", t)), signals=signals, received=t)
                    self._cond.notify_all()
        except ConnectionClosed:
            pass
        except OSError:
            pass
        with self._cond:
            self._closed = f"connection closed after {self.messages} messages"
            self._cond.notify_all()

    def read(self, since: float) -> Sample:
        timeout = float(self.p["timeout_s"])
        with self._cond:
            while True:
                if self._latest is not None and self._latest.t >= since:
                    self.samples += 1
                    return self._latest
                if self._closed:
                    raise self.error(self._closed)
                waited = time.time() - max(since, self._latest.values["received"] if self._latest else since)
                if waited > timeout:
                    raise self.error(f"no message for {waited:.1f} s after {self.messages} messages")
                self._cond.wait(0.05)

    def counts(self) -> dict:
        return {"samples": self.samples, "messages": self.messages, "lost": self.lost, "bad": self.bad}

    def close(self) -> None:
        if self.ws is not None:
            self.ws.close()
            if self._thread is not None:
                self._thread.join(1.0)
            self.ws = None


class Slcan(Device):
    """uSkin scans over a USB-CAN adapter speaking SLCAN (see the module docstring)."""
    kind = "slcan"
    defaults = {"port": "/dev/ttyACM0", "baudrate": 115200, "bitrate": "S6", "request_id": 0x100,
                "timeout_s": 2.0, "retry_s": 0.05}

    def __init__(self, params=None):
        super().__init__(params)
        self.port, self.lost, self.bad, self._last_scan = None, 0, 0, None

    @property
    def name(self) -> str:
        return f"slcan {self.p['port']}"

    def open(self):
        import serial
        try:
            self.port = serial.Serial(self.p["port"], int(self.p["baudrate"]), timeout=float(self.p["retry_s"]))
            for cmd in ("C", str(self.p["bitrate"]), "O"):
                self.port.write(cmd.encode() + b"\r")
                reply = self.port.read_until(b"\r")
                if cmd != "C" and not reply.endswith(b"\r"):
                    raise self.error(f"adapter did not acknowledge {cmd!r} (reply {reply!r})")
        except (serial.SerialException, OSError) as exc:
            raise self.error(f"cannot open ({exc})") from None
        return self

    def _frame(self, text: bytes):
        """(taxel, (x, y, z), scan) of one data frame, or None for acks and other ids."""
        if len(text) != 21 or text[:1] != b"t" or text[4:5] != b"8":
            return None
        try:
            ident, data = int(text[1:4], 16), bytes.fromhex(text[5:21].decode("ascii"))
        except ValueError:
            self.bad += 1
            return None
        taxel = ident - int(self.p["request_id"]) - 1
        if not 0 <= taxel < TAXELS:
            return None
        x, y, z, scan = struct.unpack(">4H", data)
        return taxel, (x, y, z), scan

    def read(self, since: float) -> Sample:
        import serial
        t0, timeout = time.time(), float(self.p["timeout_s"])
        request = f"r{int(self.p['request_id']):03X}0\r".encode()
        try:
            self.port.reset_input_buffer()
            self.port.write(request)
            got: dict[int, tuple] = {}
            scan = None
            while True:
                line = self.port.read_until(b"\r")
                if line.endswith(b"\r"):
                    frame = self._frame(line[:-1])
                    if frame is not None:
                        taxel, xyz, s = frame
                        if s != scan:             # a new scan starts; a partial one is discarded
                            got, scan = {}, s
                        got[taxel] = xyz
                        if len(got) == TAXELS:
                            break
                elif not line:
                    if time.time() - t0 > timeout:
                        raise self.error(f"no scan for {time.time() - t0:.1f} s after {self.samples} samples")
                    self.port.write(request)
        except (serial.SerialException, OSError) as exc:
            raise _serial_error(self, exc) from None
        if self._last_scan is not None:
            self.lost += (scan - self._last_scan - 1) % 2 ** 16
        self._last_scan = scan
        self.samples += 1
        return Sample(time.time(), signals=np.asarray([got[k] for k in range(TAXELS)], np.int64))

    def counts(self) -> dict:
        return {"samples": self.samples, "lost": self.lost, "bad": self.bad}

    def close(self) -> None:
        if self.port is not None:
            try:
                self.port.write(b"C\r")
                self.port.close()
            except Exception:                     # noqa: BLE001 - a vanished port closes anyway
                pass
            self.port = None
