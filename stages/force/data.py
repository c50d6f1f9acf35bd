"""Contact sequences as the force nodes read them.

Inputs are contact-sequence artifacts (or plain dicts of arrays): `images` (N,H,W) uint8,
`reference` (H,W), `force` (N,3), `normalised_depth`, `phase`, `contact_id`, `indenter_id`
and `indenters` (the names indenter_id indexes).  A contact's frames are contiguous and in
time order.  Contacts are split by indenter name: models train on the training indenters,
choices are made on the validation indenters and results are scored on the test indenters.
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np


def indenter_names(art) -> np.ndarray:
    """The indenter name of every frame."""
    names = np.asarray(art["indenters"]).astype(str)
    return names[np.asarray(art["indenter_id"]).astype(int)]


def contact_runs(art, indenters: Sequence[str] | None = None) -> list[tuple[int, int]]:
    """(start, stop) frame ranges of the contacts pressed by `indenters` (None: all)."""
    cid = np.asarray(art["contact_id"])
    starts = np.flatnonzero(np.r_[True, cid[1:] != cid[:-1]]) if cid.size else np.zeros(0, int)
    if len(np.unique(cid)) != starts.size:
        raise ValueError("contact_runs: a contact's frames are not contiguous")
    stops = np.r_[starts[1:], cid.size].astype(int)
    runs = list(zip(starts.tolist(), stops.tolist()))
    if indenters is None:
        return runs
    known = set(np.asarray(art["indenters"]).astype(str))
    unknown = sorted(set(indenters) - known)
    if unknown:
        raise KeyError(f"indenter(s) {unknown} are not in the artifact's indenters {sorted(known)}")
    names = indenter_names(art)
    keep = set(indenters)
    return [(a, b) for a, b in runs if names[a] in keep]


def run_rows(runs) -> np.ndarray:
    """The frame rows of (start, stop) runs, in order."""
    return np.concatenate([np.arange(a, b) for a, b in runs]) if runs else np.zeros(0, int)


def whole_contacts(art, rows) -> np.ndarray:
    """The rows, in order, of every whole contact of `art` that one of `rows` falls in."""
    runs = contact_runs(art)
    starts = np.array([a for a, _ in runs])
    which = np.unique(np.searchsorted(starts, np.asarray(rows, int), side="right") - 1)
    return np.concatenate([np.arange(*runs[i]) for i in which])


def read_runs(art, key: str, runs) -> list[np.ndarray]:
    return [np.asarray(art[key][a:b]) for a, b in runs]


def scoring_set(art, indenters: Sequence[str], what: str = "scoring") -> dict:
    """The contacts of `indenters` as one block: images, contact_id, frame, force, reference."""
    runs = contact_runs(art, indenters)
    if not runs:
        raise ValueError(f"no {what} contacts of indenters {list(indenters)}")
    rows = run_rows(runs)
    return {"images": np.concatenate(read_runs(art, "images", runs)),
            "contact_id": np.asarray(art["contact_id"])[rows],
            "frame": np.asarray(art["frame"])[rows] if "frame" in art else None,
            "force": np.asarray(art["force"], np.float32)[rows],
            "reference": np.asarray(art["reference"])}


def predict_rows(model, art: Mapping, rows: np.ndarray) -> np.ndarray:
    """(K,3) the model's forces at the frames `rows` of `art`, each read in its whole contact
    (the GRU's state from the contact's first frame, as the studies and a control loop read)."""
    from stages.force.model import predict_contacts
    rows = np.asarray(rows, int)
    read = whole_contacts(art, rows)
    cid = np.asarray(art["contact_id"])
    pred = predict_contacts(model, np.asarray(art["images"][read.tolist()]), cid[read],
                            np.asarray(art["reference"]))
    return pred[np.searchsorted(read, rows)]
