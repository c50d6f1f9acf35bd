"""Helpers shared by the capture tests (a module of its own: `conftest` names clash across folders)."""
import numpy as np

LABELS = ("force", "torque", "position", "target", "depth", "normalised_depth", "shift", "phase",
          "contact_id", "indenter_id", "paired", "frame")


def drain(gen):
    chunks = []
    while True:
        try:
            chunks.append(next(gen))
        except StopIteration as stop:
            return chunks, stop.value


def concat(chunks) -> dict:
    out = {}
    for key, value in chunks[0].items():
        if isinstance(value, dict):
            out[key] = {k: np.concatenate([c[key][k] for c in chunks]) for k in value}
        else:
            out[key] = np.concatenate([c[key] for c in chunks])
    return out
