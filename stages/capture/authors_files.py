"""Readers of the GenForce authors' dataset files, each failing in one line that names the file.

What each file holds, from the authors' code (SuhangXia/GenForce_Code):
  NNNN.npy    np.save(np.packbits(mask)) of the whole 480x640 0/1 marker mask (white markers
              = 1): a 1-D uint8 array of 38,400 bytes, row-major, pixel 8k the top bit of byte
              k (marker_seg/homo/homo.py).  A 2-D 0/1 (or 0/255) array is taken as the mask.
  NNNN.jpg    a marker image written as a picture; binarised at > 50 as their loaders do
              (force/wo_com/data_loader.py), after PIL's conversion to grey.
  ft.csv      the recorder's header Fx(N),Fy(N),Fz(N),Tx(Nmm),Ty(Nmm),Tz(Nmm), one row per frame
              (data_collection/components/gelsight/ur5e.py).  Columns are found by name; the
              torques are optional; a unit missing from the header is the recorder's.
  last.csv    np.savetxt of four paths, the last frame of each motion; the basename counts.
  inc_z.csv / dec_z.csv   no header, one number a row (np.loadtxt(f, delimiter=",")).
  <s>_{down,up}.csv       polynomial coefficients, highest power first, for np.poly1d.

Text files may have CRLF endings and a UTF-8 byte-order mark.
"""
from __future__ import annotations

import io
import math
import re
from pathlib import Path

import numpy as np

from stages.common import InputError

SOURCE_SIZE = (480, 640)
PACKED_BYTES = SOURCE_SIZE[0] * SOURCE_SIZE[1] // 8
FRAME_SUFFIXES = (".npy", ".jpg")
JPG_THRESHOLD = 50                      # their loaders: (np.array(image) > 50) * 255
FT_HEADER = "Fx(N),Fy(N),Fz(N),Tx(Nmm),Ty(Nmm),Tz(Nmm)"
_FORCE_UNITS = {"": 1.0, "n": 1.0}        # divisors to N
_TORQUE_UNITS = {"": 1e3, "nmm": 1e3, "n.mm": 1e3, "n*mm": 1e3, "n·mm": 1e3, "nm": 1.0, "n.m": 1.0,
                 "n*m": 1.0, "n·m": 1.0}  # divisors to N m; no unit: the recorder's N mm
_CELL = re.compile(r"^\s*([A-Za-z]+)\s*(?:\(\s*([^)]*?)\s*\))?\s*$")


def _packed_header() -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.zeros(PACKED_BYTES, np.uint8))
    return buf.getvalue()[:-PACKED_BYTES]


_HEADER = _packed_header()


def _text_lines(path: Path) -> list[str]:
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except FileNotFoundError:
        raise InputError(f"missing file {path}") from None
    except UnicodeDecodeError:
        raise InputError(f"{path} is not a text file") from None
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc.strerror or exc}") from None
    return [ln.strip() for ln in text.splitlines()]


def _number(text: str, path: Path, line: int) -> float:
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"{path} line {line}: {text!r} is not a number") from None
    if not math.isfinite(value):
        raise InputError(f"{path} line {line}: {text!r} is not a finite number")
    return value


# ---------------------------------------------------------------------------------- frames

def unpack(packed: np.ndarray) -> np.ndarray:
    """(n, 38400) packed frames -> (n, 480, 640) 0/1 uint8, as np.unpackbits(f).reshape(480, 640)."""
    return np.unpackbits(packed, axis=-1).reshape(len(packed), *SOURCE_SIZE)


def read_frame(path: Path):
    """A frame file as ("packed", (38400,) uint8) or ("mask", (H, W) 0/1 uint8)."""
    if path.suffix == ".jpg":
        return "mask", _read_jpg(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"missing frame {path}") from None
    except OSError as exc:
        raise InputError(f"cannot read frame {path}: {exc.strerror or exc}") from None
    if len(data) == len(_HEADER) + PACKED_BYTES and data.startswith(_HEADER):
        return "packed", np.frombuffer(data, np.uint8, offset=len(_HEADER))
    try:
        arr = np.load(io.BytesIO(data), allow_pickle=False)
    except (ValueError, EOFError, OSError) as exc:
        raise InputError(f"frame {path} is truncated or not a .npy array "
                         f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    if arr.ndim == 1:
        if arr.dtype != np.uint8 or arr.size != PACKED_BYTES:
            raise InputError(f"frame {path} is wrongly sized: {arr.dtype} ({arr.size},), expected "
                             f"uint8 ({PACKED_BYTES},), np.packbits of a 480x640 mask")
        return "packed", arr
    if arr.ndim != 2 or not (arr.dtype == bool or np.issubdtype(arr.dtype, np.integer)):
        raise InputError(f"frame {path} holds {arr.dtype} {arr.shape}; expected a bit-packed "
                         f"(38400,) uint8 mask or a 2-D 0/1 image")
    return "mask", _binary(arr, path)


def _binary(arr: np.ndarray, path: Path) -> np.ndarray:
    values = np.unique(arr)
    if values.size and not (set(values.tolist()) <= {0, 1} or set(values.tolist()) <= {0, 255}):
        raise InputError(f"frame {path} is not binary: values {values[:6].tolist()}"
                         f"{'...' if values.size > 6 else ''} (expected 0/1 or 0/255)")
    return (arr > 0).astype(np.uint8)


def _read_jpg(path: Path) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError
    try:
        with Image.open(path) as im:
            grey = np.asarray(im.convert("L"))
    except FileNotFoundError:
        raise InputError(f"missing frame {path}") from None
    except (OSError, UnidentifiedImageError, SyntaxError) as exc:
        raise InputError(f"frame {path} is truncated or not a JPEG image ({exc})") from None
    return (grey > JPG_THRESHOLD).astype(np.uint8)


# ----------------------------------------------------------------------------- csv files

def _header_cell(cell: str):
    m = _CELL.match(cell)
    return (m.group(1).lower(), (m.group(2) or "").lower().replace(" ", "")) if m else (None, None)


def read_ft(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """ft.csv -> (force (n,3) float64 N, torque (n,3) float64 N m or None)."""
    lines = [ln for ln in _text_lines(path) if ln]
    if not lines:
        raise InputError(f"{path} is empty (expected the header {FT_HEADER} and one row per frame)")
    header = [c.strip() for c in lines[0].split(",")]
    cells = [_header_cell(c) for c in header]
    names = [c[0] for c in cells]
    if names[:3] != ["fx", "fy", "fz"]:
        raise InputError(f"{path} has the header {lines[0]!r}; expected {FT_HEADER} "
                         "(Fx, Fy, Fz first)")
    scale = []
    for (name, unit), cell in zip(cells[:3], header):
        if unit not in _FORCE_UNITS:
            raise InputError(f"{path} header {cell!r}: unit {unit!r} is not N")
        scale.append(_FORCE_UNITS[unit])
    torque_cols = None
    if names[3:6] == ["tx", "ty", "tz"]:
        torque_cols = []
        for (name, unit), cell in zip(cells[3:6], header[3:6]):
            if unit not in _TORQUE_UNITS:
                raise InputError(f"{path} header {cell!r}: unit {unit!r} is not N mm or N m")
            torque_cols.append(_TORQUE_UNITS[unit])
    rows = []
    for k, ln in enumerate(lines[1:], start=2):
        parts = ln.split(",")
        if len(parts) != len(header):
            raise InputError(f"{path} line {k} has {len(parts)} values, the header {len(header)}")
        rows.append([_number(p, path, k) for p in parts[:6 if torque_cols else 3]])
    table = np.asarray(rows, float).reshape(len(rows), 6 if torque_cols else 3)
    force = table[:, :3] / np.asarray(scale)
    torque = table[:, 3:6] / np.asarray(torque_cols) if torque_cols else None
    return force, torque


def read_column(path: Path) -> np.ndarray:
    """inc_z.csv / dec_z.csv: (n,) float64, one number a row, no header."""
    out = []
    for k, ln in enumerate(_text_lines(path), start=1):
        if not ln:
            continue
        parts = [p for p in ln.split(",") if p.strip()]
        if len(parts) != 1:
            raise InputError(f"{path} line {k} holds {len(parts)} values; expected one number a row")
        out.append(_number(parts[0], path, k))
    return np.asarray(out, float)


def read_coefficients(path: Path) -> np.ndarray:
    """<sensor>_{down,up}.csv: polynomial coefficients (highest power first) as np.loadtxt reads
    them with delimiter ",": one line of values, or one value a line."""
    rows = []
    for k, ln in enumerate(_text_lines(path), start=1):
        if ln and not ln.startswith("#"):
            rows.append([_number(p.strip(), path, k) for p in ln.split(",")])
    if not rows:
        raise InputError(f"{path} holds no coefficients")
    if len(rows) > 1 and any(len(r) != 1 for r in rows):
        raise InputError(f"{path} holds a {len(rows)}-row table; expected one line of polynomial "
                         "coefficients or one a line")
    return np.asarray([v for r in rows for v in r], float)


def read_last(path: Path) -> list[int]:
    """last.csv -> the frame numbers its lines name (the basenames' NNNN): four, or the three
    M2M reads (their [:3]; the fourth, the end of the release, bounds nothing)."""
    entries = [ln for ln in _text_lines(path) if ln]
    if len(entries) not in (3, 4):
        raise InputError(f"{path} names {len(entries)} frame(s); expected 4, the last frame of "
                         "press, shear out, shear back and release")
    out = []
    for k, entry in enumerate(entries, start=1):
        base = re.split(r"[\\/]", entry.strip().strip('"'))[-1]
        stem, dot, suffix = base.rpartition(".")
        if not (dot and stem.isdigit() and f".{suffix}" in FRAME_SUFFIXES):
            raise InputError(f"{path} line {k}: {entry!r} names no NNNN.npy or NNNN.jpg frame")
        out.append(int(stem))
    return out
