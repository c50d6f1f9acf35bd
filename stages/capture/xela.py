"""The XELA uSkin server's WebSocket messages as raw taxel readings (stages.capture.tactile
reads them; stages.markers.uskin draws them as marker images)."""
from __future__ import annotations

import json
from typing import Mapping

import numpy as np


def _values(sensor, data) -> np.ndarray:
    if isinstance(data, str):
        data = [v for v in data.replace(" ", "").split(",") if v]
    if not isinstance(data, (list, tuple)):
        raise ValueError(f"parse_xela: sensor {sensor!r}: `data` must be a list or a comma-separated "
                         f"string, got {type(data).__name__}")
    if len(data) != 48:
        raise ValueError(f"parse_xela: sensor {sensor!r}: expected 48 values (16 taxels x 3), "
                         f"got {len(data)}")
    out = []
    for v in data:
        if isinstance(v, bool) or not isinstance(v, (int, str)):
            raise ValueError(f"parse_xela: sensor {sensor!r}: value {v!r} is not an integer or a "
                             f"hex string")
        try:
            out.append(int(v, 16) if isinstance(v, str) else v)
        except ValueError:
            raise ValueError(f"parse_xela: sensor {sensor!r}: value {v!r} is not a hex string") from None
    values = np.asarray(out, np.int64)
    if values.min() < 0 or values.max() > 65535:
        raise ValueError(f"parse_xela: sensor {sensor!r}: values outside 0..65535")
    return values.reshape(16, 3).astype(np.int32)


def parse_xela(message) -> dict:
    """Raw readings of one XELA server WebSocket message: {sensor id: (16, 3) int32 x, y, z}.

    The message (JSON text, bytes, or the decoded dict) holds one entry per sensor under its
    id ("1", "2", ...), each a dict whose `data` lists 48 values, x, y, z per taxel row-major:
    integers, or hex strings in older server versions (a list or one comma-separated string).
    Other top-level keys (message, time, sensors) and other fields of a sensor entry, such as
    `calibrated`, are ignored; a message with no sensor entry (the server's welcome) gives {}.
    """
    if isinstance(message, (bytes, bytearray)):
        try:
            message = message.decode("utf-8")
        except UnicodeDecodeError:
            raise ValueError("parse_xela: message is not UTF-8 text") from None
    if isinstance(message, str):
        try:
            message = json.loads(message)
        except json.JSONDecodeError as err:
            raise ValueError(f"parse_xela: message is not JSON ({err.msg} at char {err.pos})") from None
    if not isinstance(message, Mapping):
        raise ValueError(f"parse_xela: message must be a JSON object, got {type(message).__name__}")
    sensors = {}
    for key, entry in message.items():
        if isinstance(entry, Mapping) and "data" in entry:
            sensors[str(key)] = _values(key, entry["data"])
        elif str(key).isdigit():
            raise ValueError(f"parse_xela: sensor {key!r} has no `data` list")
    return sensors
