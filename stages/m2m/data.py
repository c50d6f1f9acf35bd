"""Marker artifacts as M2M data: indenter look-up, training pairs and evaluation frames.

Numpy only, so the frame selection can be shared by every node that scores images
(`image_features`, `translate_sequence`, `flow_warp_sequence`) without importing torch.

A marker artifact (`markers[skin]`) is a mapping with `images` (N,H,W) uint8 0/255,
`reference` (H,W) uint8, the contact-sequence labels (`indenter_id`, `paired`, `frame`, ...)
and `indenters`, the names `indenter_id` indexes. Plain dicts of numpy arrays work as well
as store artifacts (whose arrays are read lazily).
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np



def indenter_names(art) -> list[str]:
    """The names `indenter_id` indexes, from the artifact's `indenters` dataset."""
    if "indenters" not in art:
        raise KeyError("marker artifact has no 'indenters' dataset (the names indenter_id indexes)")
    return [n.decode() if isinstance(n, bytes) else str(n) for n in np.asarray(art["indenters"]).ravel()]


def frames_of(art, indenters: Sequence[str], paired_only: bool = True) -> np.ndarray:
    """Row indices whose indenter is one of `indenters` (and, by default, location-paired)."""
    names = indenter_names(art)
    unknown = sorted(set(indenters) - set(names))
    if unknown:
        raise KeyError(f"indenters {unknown} not in the artifact's indenters {names}")
    wanted = np.array([names.index(n) for n in indenters], int)
    keep = np.isin(np.asarray(art["indenter_id"]), wanted)
    if paired_only:
        keep &= np.asarray(art["paired"], bool)
    return np.flatnonzero(keep)


def evenly(idx: np.ndarray, n: int) -> np.ndarray:
    """At most n entries of idx, evenly spread (the middle of n equal bins)."""
    idx = np.asarray(idx)
    if n <= 0 or idx.size <= n:
        return idx
    return idx[((np.arange(n) + 0.5) * idx.size / n).astype(int)]


def eval_frame_indices(art, eval_indenters: Sequence[str], n_eval: int) -> np.ndarray:
    """Rows of `art` scored by the image metrics: location-paired frames of the evaluation
    indenters, at most n_eval of them, evenly spread.  Depends only on the labels, so every
    skin that follows the same trajectory gets the same `frame` values."""
    rows = evenly(frames_of(art, eval_indenters), int(n_eval))
    if rows.size < 2:
        raise ValueError(f"only {rows.size} evaluation frame(s) for indenters {list(eval_indenters)}; "
                         "FID/KID need at least 2")
    return rows


def read_rows(arr, rows: np.ndarray) -> np.ndarray:
    """arr[rows] for a numpy array or a lazily read dataset (rows sorted, unique)."""
    rows = np.asarray(rows, int)
    if isinstance(arr, np.ndarray):
        return arr[rows]
    if rows.size == 0:
        return np.asarray(arr[0:0])
    if rows[-1] - rows[0] + 1 == rows.size:         # contiguous: one slice, not a point selection
        return np.asarray(arr[int(rows[0]):int(rows[-1]) + 1])
    return np.asarray(arr[rows.tolist()])


def take_rows(arr, rows) -> np.ndarray:
    """arr[rows] for rows in any order, repeats allowed (read_rows wants them sorted, unique)."""
    unique, inverse = np.unique(np.asarray(rows, int), return_inverse=True)
    return read_rows(arr, unique)[inverse]


def paired_table(markers: Mapping, skins: Sequence[str], indenters: Sequence[str],
                 per_skin: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Location-paired training frames shared by all `skins`.

    Returns (frames (K,), rows (S,K)): the `frame` values paired in every skin for the given
    indenters, and the row of each in each skin's artifact.  per_skin > 0 keeps that many
    frames, evenly spread (few-pair fine-tuning).
    """
    missing = [s for s in skins if s not in markers]
    if missing:
        raise KeyError(f"skins {missing} have no marker artifact (have {sorted(markers)})")
    common = None
    lookup = []
    for s in skins:
        rows = frames_of(markers[s], indenters)
        frame = np.asarray(markers[s]["frame"])[rows]
        lookup.append(dict(zip(frame.tolist(), rows.tolist())))
        common = set(frame.tolist()) if common is None else common & set(frame.tolist())
    frames = np.array(sorted(common or ()), np.int64)
    frames = evenly(frames, int(per_skin))
    if frames.size == 0:
        raise ValueError(f"no location-paired frame of indenters {list(indenters)} is shared by skins {list(skins)}")
    rows = np.array([[lk[f] for f in frames.tolist()] for lk in lookup], np.int64)
    return frames, rows


# References that differ in no more than this fraction of their pixels are one marker style.
# One layout on other gels (the material twins, a re-fabricated gel) differs by camera noise at
# the markers' edges: up to 0.2% of the pixels of the default profile's references at M2M's
# size; two layouts, even GelSight A-I against A-II (moved by 0.3 mm), by 4% and more.
SAME_STYLE_FRACTION = 0.01


def same_style(a: np.ndarray, b: np.ndarray, tolerance: float = SAME_STYLE_FRACTION) -> bool:
    """Whether two no-contact reference images (binary, same shape) show one marker style."""
    a, b = np.asarray(a) > 0, np.asarray(b) > 0
    return a.shape == b.shape and float(np.mean(a != b)) <= tolerance


def styles(references: Sequence[np.ndarray], tolerance: float = SAME_STYLE_FRACTION) -> list[int]:
    """For each reference, the index of the first reference of its style (itself if it is new)."""
    firsts: list[int] = []
    out = []
    for i, ref in enumerate(references):
        j = next((j for j in firsts if same_style(references[j], ref, tolerance)), None)
        if j is None:
            firsts.append(j := i)
        out.append(j)
    return out
