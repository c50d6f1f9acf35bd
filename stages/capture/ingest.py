"""Node `ingest`: the paper authors' published dataset layout -> a contact-sequence artifact.

Assumed layout (one folder per contact; names are what the loader looks for):

  <root>/<sensor>/reference.npy       optional no-contact marker image: (480, 80) uint8
                                      bit-packed like the frames, or (480, 640) 0/1 or 0/255
  <root>/<sensor>/<indenter>/<contact>/
      markers.npy   (N, 480, 80) uint8: N binary 480x640 marker images (white markers = 1),
                    np.packbits along the last axis (numpy's default big bit order: pixel
                    8k + 7 - b is bit b of byte k, so pixel 8k is the byte's top bit)
      ft.csv        header Fx,Fy,Fz,Tx,Ty,Tz, one row per frame: N and N m, the paper's sign
                    (Fz < 0 pressing); other columns are ignored
      depth.csv     header depth_mm and optionally x_mm,y_mm, one row per frame: the depth below
                    first touch and the tip's lateral position in the sensor frame, mm

Indenter folders are ordered as stages.sim.indenters.ALL_INDENTERS (unknown names after them,
sorted), contact folders in natural order (2 before 10); frames keep their order.

Derived labels, per contact: position = (x, y, -depth) (x, y = 0 without x_mm, y_mm);
shift = (x, y) less the first frame's; phase from the motion into each frame: depth up by more
than depth_tol_mm = press (0), down = release (3), otherwise a lateral step longer than
move_tol_mm is shear out (1) when it moves away from the touchdown point, shear back (2) when
it comes closer, and a frame that does not move keeps the previous frame's phase (the first
frame: press).  A movement is a run of equal phase; its last n_paired frames are `paired`.
`frame` numbers the frames of the whole dataset in that order (the authors collected every
sensor along the same protocol, so equal numbers are equal indenter locations when the
sensors' folders hold the same contacts).  normalised_depth = depth / max_depth_mm (default:
the deepest frame of the dataset).

Images are resized to `size` (H, W) with area interpolation of the 0/1 image and re-binarised
at one half (0/255 uint8); the reference is reference.npy if present, else the first frame of
the first contact.  Missing files and wrong shapes raise ValueError naming the file.
"""
from __future__ import annotations

import csv
import os
import re
from pathlib import Path

import numpy as np

from stages.common import InputError
from stages.sim.indenters import ALL_INDENTERS

SOURCE_SIZE = (480, 640)
FT_COLUMNS = ("Fx", "Fy", "Fz", "Tx", "Ty", "Tz")


def _natural(name: str):
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", name)]


def _contacts(sensor_dir: Path) -> tuple[list[str], list[tuple[str, Path]]]:
    """Indenter names (in id order) and the (indenter, contact folder) list."""
    found = sorted(p.name for p in sensor_dir.iterdir() if p.is_dir())
    if not found:
        raise InputError(f"ingest: {sensor_dir} holds no indenter folders")
    names = list(ALL_INDENTERS) + sorted(n for n in found if n not in ALL_INDENTERS)
    out = []
    for name in sorted(found, key=names.index):
        for c in sorted((p for p in (sensor_dir / name).iterdir() if p.is_dir()), key=lambda p: _natural(p.name)):
            out.append((name, c))
    if not out:
        raise InputError(f"ingest: no contact folders under {sensor_dir}/<indenter>/")
    return names, out


def _csv(path: Path, required, optional=()) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise InputError(f"ingest: missing file {path}")
    with open(path, newline="") as f:
        reader = csv.reader(f)
        header = [h.strip() for h in next(reader, [])]
        rows = [r for r in reader if r]
    missing = [c for c in required if c not in header]
    if missing:
        raise InputError(f"ingest: {path} lacks column(s) {', '.join(missing)} (header {','.join(header)})")
    try:
        table = np.array([[float(v) for v in r] for r in rows], float).reshape(len(rows), len(header))
    except ValueError:
        raise InputError(f"ingest: {path} has a malformed row (every row needs {len(header)} numbers)") from None
    if not np.isfinite(table).all():
        row = int(np.flatnonzero(~np.isfinite(table).all(axis=1))[0])
        raise InputError(f"ingest: {path} row {row + 2} holds a value that is not a finite number")
    return {c: table[:, header.index(c)] for c in (*required, *optional) if c in header}


def _unpack(packed: np.ndarray) -> np.ndarray:
    """(..., 480, 80) bit-packed -> (..., 480, 640) 0/1 uint8."""
    return np.unpackbits(packed, axis=-1)[..., :SOURCE_SIZE[1]]


def _load_npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise InputError(f"ingest: {path} is not a readable .npy array ({str(exc).splitlines()[0]})") from None


def _markers(path: Path) -> np.ndarray:
    if not path.is_file():
        raise InputError(f"ingest: missing file {path}")
    packed = _load_npy(path)
    want = (SOURCE_SIZE[0], SOURCE_SIZE[1] // 8)
    if packed.dtype != np.uint8 or packed.ndim != 3 or packed.shape[1:] != want:
        raise InputError(f"ingest: {path} holds {packed.dtype} {packed.shape}; expected uint8 "
                         f"(N, {want[0]}, {want[1]}) bit-packed 480x640 images")
    return packed


def _binarise(bits: np.ndarray, size) -> np.ndarray:
    """(N, 480, 640) 0/1 -> (N, H, W) 0/255: area-resized coverage >= 1/2."""
    import cv2
    h, w = (int(v) for v in size)
    if bits.shape[-2:] == (h, w):
        return (bits.astype(np.uint8) * 255).astype(np.uint8)
    out = np.empty((bits.shape[0], h, w), np.uint8)
    for i, b in enumerate(bits):
        cover = cv2.resize(b.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
        out[i] = np.where(cover >= 0.5, 255, 0)
    return out


def infer_phase(depth, xy=None, *, depth_tol_mm: float = 0.01, move_tol_mm: float = 0.01) -> np.ndarray:
    """(N,) int8 phases of one contact from its depth (N,) and lateral position (N, 2), mm."""
    depth = np.asarray(depth, float)
    n = depth.size
    xy = np.zeros((n, 2)) if xy is None else np.asarray(xy, float)
    radius = np.hypot(*(xy - xy[:1]).T)
    phase = np.zeros(n, np.int8)
    prev_d, prev_xy, prev_r, prev_p = 0.0, xy[0] if n else None, 0.0, 0
    for k in range(n):
        dd = depth[k] - prev_d
        if dd > depth_tol_mm:
            p = 0
        elif dd < -depth_tol_mm:
            p = 3
        elif np.hypot(*(xy[k] - prev_xy)) > move_tol_mm:
            p = 1 if radius[k] > prev_r else 2
        else:
            p = prev_p
        phase[k] = prev_p = p
        prev_d, prev_xy, prev_r = depth[k], xy[k], radius[k]
    return phase


def paired_frames(phase: np.ndarray, n_paired: int = 4) -> np.ndarray:
    """(N,) bool: the last n_paired frames of every run of equal phase."""
    phase = np.asarray(phase)
    ends = np.append(np.flatnonzero(np.diff(phase)), phase.size - 1)
    pos = np.arange(phase.size)
    return (ends[np.searchsorted(ends, pos)] - pos) < int(n_paired)


def _reference(sensor_dir: Path, first_contact: Path, size) -> np.ndarray:
    path = sensor_dir / "reference.npy"
    if path.is_file():
        ref = _load_npy(path)
        if ref.dtype == np.uint8 and ref.shape == (SOURCE_SIZE[0], SOURCE_SIZE[1] // 8):
            bits = _unpack(ref)
        elif ref.shape == SOURCE_SIZE:
            bits = (np.asarray(ref) > 0).astype(np.uint8)
        else:
            raise InputError(f"ingest: {path} holds {ref.dtype} {ref.shape}; expected (480, 80) "
                             "bit-packed uint8 or a (480, 640) image")
    else:
        bits = _unpack(_markers(first_contact / "markers.npy")[:1])[0]
    return _binarise(bits[None], size)[0]


def ingest(*, root: str, sensor: str, size, max_depth_mm: float | None = None, n_paired: int = 4,
           depth_tol_mm: float = 0.01, move_tol_mm: float = 0.01):
    """Node `ingest`: yields one chunk per contact (images (n,H,W) 0/255 and the contact-sequence
    labels, plus torque (n,3)), returns reference (H,W), indenters (names) and attrs.  See the
    module docstring for the layout and how labels are derived."""
    if len(size) != 2 or not all(isinstance(v, int) and v >= 8 for v in size):
        raise InputError(f"ingest.size must be [height, width] in pixels, each >= 8, got {size!r}")
    sensor_dir = Path(root) / sensor
    if not sensor_dir.is_dir():
        raise InputError(f"ingest: no folder {sensor_dir} (expected <root>/<sensor>/<indenter>/<contact>/)")
    names, contacts = _contacts(sensor_dir)
    tables = []
    for _, folder in contacts:                         # read the small files first: check, max depth
        depth = _csv(folder / "depth.csv", ("depth_mm",), ("x_mm", "y_mm"))
        ft = _csv(folder / "ft.csv", FT_COLUMNS)
        if len(ft["Fx"]) != len(depth["depth_mm"]):
            raise InputError(f"ingest: {folder / 'ft.csv'} has {len(ft['Fx'])} rows but "
                             f"{folder / 'depth.csv'} has {len(depth['depth_mm'])}")
        tables.append((depth, ft))
    deepest = max(float(np.max(d["depth_mm"], initial=0.0)) for d, _ in tables)
    max_depth = float(max_depth_mm or deepest or 1.0)
    frame = 0
    for cid, ((name, folder), (depth, ft)) in enumerate(zip(contacts, tables)):
        packed = _markers(folder / "markers.npy")
        n = len(depth["depth_mm"])
        if packed.shape[0] != n:
            raise InputError(f"ingest: {folder / 'markers.npy'} has {packed.shape[0]} frames but "
                             f"{folder / 'depth.csv'} has {n} rows")
        d = depth["depth_mm"]
        xy = np.column_stack([depth.get("x_mm", np.zeros(n)), depth.get("y_mm", np.zeros(n))])
        phase = infer_phase(d, xy, depth_tol_mm=depth_tol_mm, move_tol_mm=move_tol_mm)
        yield {"images": _binarise(_unpack(packed), size),
               "force": np.column_stack([ft[c] for c in FT_COLUMNS[:3]]).astype(np.float32),
               "torque": np.column_stack([ft[c] for c in FT_COLUMNS[3:]]).astype(np.float32),
               "depth": d, "normalised_depth": (d / max_depth).astype(np.float32),
               "position": np.column_stack([xy, -d]), "shift": xy - xy[:1],
               "phase": phase, "contact_id": np.full(n, cid, np.int32),
               "indenter_id": np.full(n, names.index(name), np.int16),
               "paired": paired_frames(phase, n_paired), "frame": np.arange(frame, frame + n, dtype=np.int64)}
        frame += n
    return {"reference": _reference(sensor_dir, contacts[0][1], size), "indenters": names,
            "attrs": {"sensor": sensor, "root": str(root), "contacts": len(contacts), "frames": frame,
                      "source_size": list(SOURCE_SIZE), "size": [int(v) for v in size],
                      "max_depth_mm": max_depth}}


def write_example_dataset(root, sensor: str = "gelsight", indenters=("sphere", "prism"), contacts: int = 2,
                          frames: int = 12, seed: int = 0) -> str:
    """Write a small dataset in the layout above; returns `<root>/<sensor>`.

    Each contact presses to a random depth (0.5..1.5 mm) over the first third of its frames,
    shears 1 mm out and back along a random direction over the second, and releases over the
    rest; forces follow a Hertz-like law with noise.  Marker images are the GelSight A-II
    pattern with markers pushed radially away from the contact point in proportion to the
    depth and dragged along by the shear.  A reference.npy (the undeformed pattern) is written.
    """
    from stages.markers.patterns import MarkerSet, gelsight_pattern, rasterize
    if frames < 6 or contacts < 1:
        raise ValueError("write_example_dataset: frames must be >= 6 and contacts >= 1")
    rng = np.random.default_rng(seed)
    base = gelsight_pattern("A-II")
    h, w = SOURCE_SIZE
    pad_h = base.pad_size_mm[1]

    def draw(centres):
        bits = rasterize(MarkerSet(centres, base.axes, base.angles, (pad_h * w / h, pad_h)), size=(h, w),
                         supersample=1) > 0
        return np.packbits(bits, axis=-1)

    out = Path(root) / sensor
    out.mkdir(parents=True, exist_ok=True)
    np.save(out / "reference.npy", draw(base.centers))
    third = frames // 3
    for name in indenters:
        for c in range(contacts):
            folder = out / name / f"{c + 1}"
            folder.mkdir(parents=True, exist_ok=True)
            d_max, ang = rng.uniform(0.5, 1.5), rng.uniform(0, 2 * np.pi)
            point = rng.uniform(-3, 3, 2)
            rest = frames - 2 * third
            out_n = third // 2
            s = np.concatenate([np.linspace(0, 1, out_n + 1)[1:], np.linspace(1, 0, third - out_n + 1)[1:]])
            depth = np.concatenate([d_max * np.arange(1, third + 1) / third, np.full(third, d_max),
                                    d_max * np.arange(rest - 1, -1, -1) / rest])
            shift = np.outer(np.concatenate([np.zeros(third), s, np.zeros(rest)]), [np.cos(ang), np.sin(ang)])
            xy = point + shift
            fz = -2.0 * depth ** 1.5 + rng.normal(0, 0.01, frames)
            fxy = 0.8 * shift + rng.normal(0, 0.005, (frames, 2))
            ft = np.column_stack([fxy, fz, rng.normal(0, 1e-3, (frames, 3))])
            images = []
            for k in range(frames):
                rel = base.centers - xy[k]
                r = np.hypot(*rel.T)[:, None]
                push = 0.3 * depth[k] * rel / np.maximum(r, 1e-6) * np.exp(-(r / 4.0) ** 2)
                drag = shift[k] * np.exp(-(r / 4.0) ** 2)
                images.append(draw(base.centers + push + drag))
            np.save(folder / "markers.npy", np.stack(images))
            np.savetxt(folder / "ft.csv", ft, delimiter=",", header=",".join(FT_COLUMNS), comments="", fmt="%.17g")
            np.savetxt(folder / "depth.csv", np.column_stack([depth, xy]), delimiter=",",
                       header="depth_mm,x_mm,y_mm", comments="", fmt="%.17g")
    return os.fspath(out)
