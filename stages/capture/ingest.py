"""Node `ingest[sensor]`: one sensor of the GenForce authors' released dataset as a contact
sequence, read as their own loaders read it (stages.capture.authors_layout: the tree;
stages.capture.authors_files: each file).

Contacts are the `<indenter>/<point>` folders of the sensor's image tree, indenters in
stages.sim.indenters order (their names with '-' for '_', e.g. sphere-s, are the same
indenters; others follow by name), points as integers (the robot's counter 1, 2, ...).  A
contact without its force folder or ft.csv is left out, as the authors' loaders leave it out
(attrs `skipped`); anything else missing or malformed stops the node with one line naming the
file.  A contact's frames are NNNN.npy / NNNN.jpg counting from 0000 with none missing, one
ft.csv row each.

Per frame (N = all frames of the sensor):
  images       (N,H,W) uint8 0/255: the 480x640 mask area-resized to `size` (coverage >= 1/2)
  force        (N,3) float32 N, ft.csv's Fx, Fy, Fz as recorded (Fz < 0 pressing)
  torque       (N,3) float32 N m: ft.csv's Tx, Ty, Tz, recorded in N mm (only when every ft.csv has them)
  phase        (N,) int8: 0 press, 1 shear out, 2 shear back, 3 release, from last.csv's
               motion ends e0 < e1 < e2 (< e3): frames up to e0 press, up to e1 shear out, up to
               e2 shear back, the rest release (a last.csv of three lines, all M2M reads, is taken)
  paired       (N,) bool: the four frames M2M pairs (training_utils.py PairedDatasetReal):
               last.csv's first three (end of press, of shear out, of shear back) and 0000
  paired_position (N,) int8: that list's position 0..3 (0000 is 3); -1 elsewhere
  point        (N,) int32: the contact folder's number; contact_id (N,) int32: contacts in order
  indenter_id  (N,) int16: index into `indenters` (names)
  file_frame   (N,) int32: the frame file's NNNN
  frame        (N,) int64: a location key, equal in two sensors exactly where the authors pair
               them: indenter code * 10^8 + point * 10 + (paired_position + 1) % 4 on paired
               frames (code 1 + the indenter's index in stages.sim.indenters.ALL_INDENTERS, or
               100 + CRC-32 of an unknown name), and a negative number unique to the sensor
               elsewhere; so stages.m2m.data.paired_table pairs real sensors as it pairs the
               twins.  Frame counts differ between sensors at one location: frame numbers never
               pair.  Paired keys grow with the row (0000 first; contacts by code, then point),
               as the twins' frame numbers do: readers that take paired rows in key order read
               them in row order.
  depth, normalised_depth, loading   (N,) where the set has depth (modulus, hetero):
               inc_z.csv's rows then dec_z.csv's, which together must number the ft.csv rows;
               loading = the row is in inc_z (the authors evaluate their `_down` curve there,
               `_up` on dec_z).  hetero: the files hold the robot's z (mm, down is negative);
               normalised_depth = (top - z) / (top - bottom) with the authors' per-sensor
               constants (force/com/com_hetero/data_loader.py; another sensor: its files'
               largest and smallest z), depth = top - z mm.  modulus: their loader feeds the
               values to the curves unchanged, so normalised_depth = the value and depth = the
               value * modulus_depth_mm (their calibration pressed 1 mm).
Once: reference (H,W) (<sensor>_ref.npy or .jpg beside the sensor folders, else the first
contact's 0000), indenters (stages.sim.indenters.ALL_INDENTERS, then any other name found),
attrs (sensor, set, counts, skipped contacts, assumptions).
Images stream in chunks of CHUNK frames; the small labels are read first (every file is
checked before any frame is decoded).
"""
from __future__ import annotations

import os
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from stages.capture.authors_files import (FRAME_SUFFIXES, SOURCE_SIZE, read_column, read_frame, read_ft,
                                          read_last, unpack)
from stages.capture.authors_layout import SensorDirs, locate
from stages.common import InputError
from stages.sim.indenters import ALL_INDENTERS

CHUNK = 64                      # frames per streamed chunk (a 480x640 mask is 300 kB unpacked)
START_POSITION = 3              # 0000's place in the authors' list
MAX_POINT = 10 ** 7             # contact numbers fit their digits of the frame key
# com_hetero/data_loader.py: normalised = (top - z) / (top - bottom), per source sensor
HETERO_DEPTH = {"uskin": (1.08649, -0.0736), "tactip": (4.648126681, -0.049249177),
                "gelsight": (1.12310475, -0.07459319)}


def canonical_indenter(name: str) -> str:
    """The authors' spelling variants of one indenter (sphere-s, sphere_s) as one name."""
    alt = name.replace("-", "_")
    return alt if alt in ALL_INDENTERS else name


def indenter_code(name: str) -> int:
    """A number for an indenter name, the same in every sensor (frame keys)."""
    name = canonical_indenter(name)
    if name in ALL_INDENTERS:
        return 1 + ALL_INDENTERS.index(name)
    return 100 + zlib.crc32(name.encode())


@dataclass
class Contact:
    indenter: str               # canonical name
    folder: Path                # image folder
    point: int
    suffix: np.ndarray          # (n,) uint8: 0 .npy, 1 .jpg per frame
    ends: list[int]
    force: np.ndarray
    torque: np.ndarray | None
    inc: np.ndarray | None = None
    dec: np.ndarray | None = None

    @property
    def n(self) -> int:
        return len(self.suffix)

    def path(self, k: int) -> Path:
        return self.folder / f"{k:04d}{FRAME_SUFFIXES[self.suffix[k]]}"


def _by_canonical(folder: Path, what: str) -> dict[str, str]:
    """{canonical indenter: folder name} of the indenter folders under `folder`."""
    out: dict[str, str] = {}
    for e in sorted(os.scandir(folder), key=lambda e: e.name) if folder.is_dir() else []:
        if e.is_dir() and not e.name.startswith("."):
            c = canonical_indenter(e.name)
            if c in out:
                raise InputError(f"{folder} holds both {out[c]!r} and {e.name!r}, one indenter "
                                 f"in two spellings ({what})")
            out[c] = e.name
    return out


def _points(folder: Path) -> list[tuple[int, str]]:
    out = []
    for e in os.scandir(folder):
        if e.is_dir() and not e.name.startswith("."):
            if not e.name.isdigit() or int(e.name) >= MAX_POINT:
                raise InputError(f"contact folder {folder / e.name} is not a number below {MAX_POINT} "
                                 "(the robot's counter 1, 2, ...)")
            out.append((int(e.name), e.name))
    return sorted(out)


def _frames(folder: Path) -> np.ndarray:
    """(n,) suffix codes of NNNN.npy / NNNN.jpg frames 0..n-1, or an InputError naming the file."""
    found: dict[int, int] = {}
    for e in os.scandir(folder):
        stem, suffix = os.path.splitext(e.name)
        if suffix not in FRAME_SUFFIXES or e.name.startswith("."):
            continue
        if not stem.isdigit() or e.name != f"{int(stem):04d}{suffix}":
            raise InputError(f"{folder / e.name} is not a frame name (NNNN.npy or NNNN.jpg)")
        k = int(stem)
        if k in found:
            raise InputError(f"{folder} holds frame {k:04d} twice (.npy and .jpg)")
        found[k] = FRAME_SUFFIXES.index(suffix)
    if not found:
        raise InputError(f"{folder} holds no NNNN.npy or NNNN.jpg frames")
    n = max(found) + 1
    missing = [k for k in range(n) if k not in found]
    if missing:
        near = found.get(missing[0] + 1, found.get(missing[0] - 1, 0))
        raise InputError(f"missing frame {folder / f'{missing[0]:04d}{FRAME_SUFFIXES[near]}'}")
    return np.array([found[k] for k in range(n)], np.uint8)


def _check_ends(ends: list[int], n: int, path: Path, folder: Path) -> None:
    for e in ends:
        if e >= n:
            raise InputError(f"{path} names frame {e:04d}, which {folder} does not hold "
                             f"(frames 0000-{n - 1:04d})")
    if not all(a < b for a, b in zip([0, *ends], ends)):
        raise InputError(f"{path} names frames {', '.join(f'{e:04d}' for e in ends)}; expected the "
                         "motions' last frames in order, the first after 0000")


def scan(dirs: SensorDirs) -> tuple[list[Contact], list[str]]:
    """Every contact of a sensor with its labels read and checked, and the contacts left out."""
    images = _by_canonical(dirs.images, "images")
    if not images:
        raise InputError(f"no indenter folders under {dirs.images}")
    forces = _by_canonical(dirs.force, "forces")
    depths = _by_canonical(dirs.depth, "depth") if dirs.depth is not None else {}
    order = [n for n in ALL_INDENTERS if n in images] + sorted((n for n in images if n not in ALL_INDENTERS),
                                                               key=indenter_code)
    contacts, skipped = [], []
    for name in order:
        for point, pname in _points(dirs.images / images[name]):
            folder = dirs.images / images[name] / pname
            ft = dirs.force / forces.get(name, images[name]) / pname / "ft.csv"
            if not ft.is_file():
                skipped.append(f"{images[name]}/{pname}")
                continue
            suffix = _frames(folder)
            force, torque = read_ft(ft)
            if len(force) != len(suffix):
                raise InputError(f"{ft} has {len(force)} rows but {folder} holds {len(suffix)} frames")
            last = dirs.last_csv / images[name] / pname / "last.csv"
            ends = read_last(last)
            _check_ends(ends, len(suffix), last, folder)
            c = Contact(name, folder, point, suffix, ends, force, torque)
            if dirs.depth is not None:
                base = dirs.depth / depths.get(name, images[name]) / pname
                c.inc, c.dec = read_column(base / "inc_z.csv"), read_column(base / "dec_z.csv")
                if len(c.inc) + len(c.dec) != c.n:
                    raise InputError(f"{base / 'inc_z.csv'} and dec_z.csv have {len(c.inc)} + "
                                     f"{len(c.dec)} rows but {ft} has {c.n}")
            contacts.append(c)
    if not contacts:
        raise InputError(f"no contact of {dirs.images} has its ft.csv under {dirs.force}")
    return contacts, skipped


def contact_labels(c: Contact) -> dict[str, np.ndarray]:
    """phase, paired, paired_position and file_frame of one contact."""
    k = np.arange(c.n)
    phase = np.searchsorted(np.asarray(c.ends[:3]), k, side="left").astype(np.int8)
    position = np.full(c.n, -1, np.int8)
    position[c.ends[:3]] = np.arange(3)
    position[0] = START_POSITION
    return {"phase": phase, "paired": position >= 0, "paired_position": position,
            "file_frame": k.astype(np.int32)}


def _depth_frame(sensor: str, set_name: str, contacts: list[Contact], modulus_depth_mm: float):
    """(normalise: z (n,) -> (depth mm, normalised), attrs) for a set with depth."""
    if set_name == "modulus":
        scale = float(modulus_depth_mm)
        if not (np.isfinite(scale) and scale > 0):
            raise InputError(f"data.modulus_depth_mm must be a positive number of mm, got {modulus_depth_mm!r}")
        return (lambda z: (z * scale, z)), {"depth_values": "normalised depth (the curves' input)",
                                            "modulus_depth_mm": scale}
    if sensor in HETERO_DEPTH:
        top, bottom = HETERO_DEPTH[sensor]
        source = "the authors' constants (com_hetero/data_loader.py)"
    else:
        zs = np.concatenate([np.r_[c.inc, c.dec] for c in contacts])
        top, bottom = float(zs.max()), float(zs.min())
        source = "this sensor's largest and smallest z"
    if not top > bottom:
        raise InputError(f"{sensor}'s depth files span no depth (z from {bottom} to {top})")
    return (lambda z: (top - z, (top - z) / (top - bottom))), {
        "depth_values": "robot z, mm", "depth_top": top, "depth_bottom": bottom, "depth_constants": source}


def _resize(bits: np.ndarray, size) -> np.ndarray:
    """(n,h,w) 0/1 -> (n,H,W) 0/255: area-resized coverage >= 1/2."""
    import cv2
    h, w = size
    if bits.shape[1:] == (h, w):
        return bits * np.uint8(255)
    out = np.empty((len(bits), h, w), np.uint8)
    for i, b in enumerate(bits):
        cover = cv2.resize(b.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
        out[i] = np.where(cover >= 0.5, 255, 0)
    return out


class _Decoder:
    """Frames -> (n,H,W) 0/255, every frame of a sensor of one source size."""

    def __init__(self, size):
        self.size = size
        self.shape: tuple[int, int] | None = None

    def check(self, shape, path: Path) -> None:
        if self.shape is None:
            self.shape = tuple(shape)
        elif tuple(shape) != self.shape:
            raise InputError(f"frame {path} is wrongly sized: {shape[0]}x{shape[1]}, the sensor's "
                             f"other frames are {self.shape[0]}x{self.shape[1]}")

    def decode(self, paths: list[Path]) -> np.ndarray:
        read = [read_frame(p) for p in paths]
        packed = [i for i, (kind, _) in enumerate(read) if kind == "packed"]
        if len(packed) == len(read):                     # the usual case: one unpack for all
            self.check(SOURCE_SIZE, paths[0])
            return _resize(unpack(np.stack([a for _, a in read])), self.size)
        out = np.empty((len(read), *self.size), np.uint8)
        for i, ((kind, arr), p) in enumerate(zip(read, paths)):
            bits = unpack(arr[None])[0] if kind == "packed" else arr
            self.check(bits.shape, p)
            out[i] = _resize(bits[None], self.size)[0]
        return out


def _reference(dirs: SensorDirs, first: Contact, size) -> tuple[np.ndarray, str]:
    for suffix in FRAME_SUFFIXES:
        path = dirs.reference_dir / f"{dirs.sensor}_ref{suffix}"
        if path.is_file():
            break
    else:
        path = first.path(0)
    kind, arr = read_frame(path)
    bits = unpack(arr[None])[0] if kind == "packed" else arr
    return _resize(bits[None], size)[0], str(path)


def ingest(*, root: str, sensor: str, size, modulus_depth_mm: float = 1.0):
    """Node `ingest[sensor]`: yields chunks of images and per-frame labels, returns reference,
    indenters and attrs (see the module docstring)."""
    from tqdm import tqdm
    if len(size) != 2 or not all(isinstance(v, int) and v >= 8 for v in size):
        raise InputError(f"render.size must be [height, width] in pixels, each >= 8, got {size!r}")
    size = (int(size[0]), int(size[1]))
    dirs = locate(root, sensor)
    contacts, skipped = scan(dirs)
    # every indenter name, as the twin's sequences list them: a split naming an indenter this
    # sensor lacks then selects no contact of it instead of failing
    names = list(ALL_INDENTERS) + [n for n in dict.fromkeys(c.indenter for c in contacts) if n not in ALL_INDENTERS]
    with_torque = all(c.torque is not None for c in contacts)
    normalise, depth_attrs = (_depth_frame(sensor, dirs.set, contacts, modulus_depth_mm)
                              if dirs.depth is not None else (None, {}))
    unpaired_base = -(zlib.crc32(sensor.encode()) * 10 ** 9)
    labels: dict[str, list] = {}
    row0 = 0
    for cid, c in enumerate(contacts):
        lab = contact_labels(c)
        slot = (lab["paired_position"].astype(np.int64) + 1) % 4          # 0000 first
        key = indenter_code(c.indenter) * 10 ** 8 + c.point * 10 + slot
        lab["frame"] = np.where(lab["paired"], key, unpaired_base - 1 - (row0 + np.arange(c.n)))
        row0 += c.n
        lab.update(force=c.force.astype(np.float32), contact_id=np.full(c.n, cid, np.int32),
                   indenter_id=np.full(c.n, names.index(c.indenter), np.int16),
                   point=np.full(c.n, c.point, np.int32))
        if with_torque:
            lab["torque"] = c.torque.astype(np.float32)
        if normalise is not None:
            z = np.r_[c.inc, c.dec]
            depth, norm = normalise(z)
            lab.update(depth=depth.astype(np.float32), normalised_depth=norm.astype(np.float32),
                       loading=np.arange(c.n) < len(c.inc))
        for k, v in lab.items():
            labels.setdefault(k, []).append(v)
    labels = {k: np.concatenate(v) for k, v in labels.items()}
    decoder = _Decoder(size)
    n = row0
    for start in tqdm(range(0, n, CHUNK), desc=f"ingest[{sensor}]", unit="chunk", disable=None, leave=False):
        stop = min(start + CHUNK, n)
        rows = zip(labels["contact_id"][start:stop].tolist(), labels["file_frame"][start:stop].tolist())
        images = decoder.decode([contacts[cid].path(k) for cid, k in rows])
        yield {"images": images, **{k: v[start:stop] for k, v in labels.items()}}
    reference, reference_from = _reference(dirs, contacts[0], size)
    return {"reference": reference, "indenters": names,
            "attrs": {"sensor": sensor, "set": dirs.set, "root": str(root), "contacts": len(contacts),
                      "frames": n, "source_size": list(decoder.shape or SOURCE_SIZE), "image_size": list(size),
                      "skipped": skipped, "reference_from": reference_from,
                      "last_csv_dir": str(dirs.last_csv), "torque_units": "N m" if with_torque else "absent",
                      "jpg_frames": int(sum(int(c.suffix.sum()) for c in contacts)), **depth_attrs}}


def pair_rows(a: Mapping, b: Mapping, indenters: Sequence[str] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(rows_a (K,), rows_b (K,)): the frames of two ingested sensors the authors pair: the same
    indenter, contact point and motion position (paired_position), for `indenters` (None: all
    both hold), in a's row order.  Never by frame number."""
    keys = []
    for art in (a, b):
        names = [n.decode() if isinstance(n, bytes) else str(n) for n in np.asarray(art["indenters"]).ravel()]
        rows = np.flatnonzero(np.asarray(art["paired"], bool))
        ind = np.asarray(art["indenter_id"])[rows]
        point = np.asarray(art["point"])[rows]
        pos = np.asarray(art["paired_position"])[rows]
        keys.append({(names[i], int(p), int(q)): int(r) for i, p, q, r in zip(ind, point, pos, rows)})
    if indenters is not None:
        wanted = {canonical_indenter(n) for n in indenters}
        keys[0] = {k: r for k, r in keys[0].items() if k[0] in wanted}
    common = [k for k in keys[0] if k in keys[1]]
    return (np.array([keys[0][k] for k in common], np.int64), np.array([keys[1][k] for k in common], np.int64))
