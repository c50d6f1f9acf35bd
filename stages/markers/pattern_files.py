"""Which marker patterns come from image files, decided at plan time (light: no numpy, no
OpenCV; stages.markers.pattern_image reads the images when the `patterns` node runs).

A sensor's `pattern` may name a PNG or JPEG file instead of a drawn pattern; `patterns.dir`
names a folder whose `<name>.jpg` / `.jpeg` / `.png` replace the drawings of the 12 simulation
patterns (the authors' `sim/marker/marker_pattern`).  The listing holds each file's checksum,
so editing an image in place re-runs `patterns` and everything its markers reach.
"""
from __future__ import annotations

import hashlib
import os
import zlib
from typing import Mapping

SUFFIXES = (".png", ".jpg", ".jpeg")
POLARITIES = ("bright", "dark")
SIM_PAD_MM = (20.0, 20.0)        # the drawn simulation patterns' pad (stages.markers.patterns.pattern)


class PatternFileError(ValueError):
    """A pattern file the plan cannot use: one line naming it, exit 2 when a run needs it."""
    user_error = True


def is_image_path(pattern) -> bool:
    """Whether a sensor's `pattern` names an image file rather than a drawn pattern."""
    return isinstance(pattern, str) and pattern.lower().endswith(SUFFIXES)


def image_pattern_name(path: str) -> str:
    """The name an image pattern goes by in the patterns artifact (no '/': an HDF5 group):
    its file name and a checksum of its absolute path."""
    full = os.path.abspath(os.path.expanduser(path))
    stem = os.path.splitext(os.path.basename(full))[0]
    return f"file-{stem}-{zlib.crc32(full.encode()):08x}"


def _entry(path: str, pad_mm, polarity: str, what: str) -> dict:
    full = os.path.abspath(os.path.expanduser(path))
    if polarity not in POLARITIES:
        raise PatternFileError(f"{what}: pattern_polarity must be one of {', '.join(POLARITIES)}, got {polarity!r}")
    try:
        with open(full, "rb") as f:
            digest = hashlib.sha256(f.read()).hexdigest()[:16]
    except FileNotFoundError:
        raise PatternFileError(f"{what}: pattern image {full}: no such file") from None
    except OSError as exc:
        raise PatternFileError(f"{what}: pattern image {full}: unreadable ({exc.strerror})") from None
    return {"path": full, "pad_mm": [float(v) for v in pad_mm], "polarity": polarity, "sha256": digest}


def pattern_files(*, sensors: Mapping, pattern_dir: str, names) -> dict:
    """Plan-time listing of node `patterns`: name -> {path, pad_mm, polarity, sha256} of every
    pattern that comes from a file (a Listing param: part of the node's key)."""
    out: dict[str, dict] = {}
    for sensor, spec in sensors.items():
        if isinstance(spec, Mapping) and is_image_path(spec.get("pattern")):
            out.setdefault(image_pattern_name(spec["pattern"]),
                           _entry(spec["pattern"], spec.get("pad_mm", SIM_PAD_MM),
                                  spec.get("pattern_polarity", "bright"), f"sensors.{sensor}.pattern"))
    if pattern_dir:
        folder = os.path.abspath(os.path.expanduser(pattern_dir))
        if not os.path.isdir(folder):
            raise PatternFileError(f"patterns.dir {folder}: no such folder")
        for name in names:
            found = [os.path.join(folder, name + s) for s in SUFFIXES + tuple(x.upper() for x in SUFFIXES)
                     if os.path.isfile(os.path.join(folder, name + s))]
            if not found:
                raise PatternFileError(f"patterns.dir {folder}: no {name}.jpg, .jpeg or .png")
            users = [s for s in sensors.values() if isinstance(s, Mapping) and s.get("pattern") == name]
            pad = users[0].get("pad_mm", SIM_PAD_MM) if users else SIM_PAD_MM
            out[name] = _entry(found[0], pad, "bright", f"patterns.dir {name}")
    return out
