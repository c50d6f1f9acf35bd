"""Small helpers every science package shares."""
from __future__ import annotations

from typing import Mapping


def attrs_of(art) -> dict:
    """An input's attributes: a store artifact's `.attrs` (nested values decoded), or the
    "attrs" entry of a node's output dict (tests and direct calls pass those)."""
    attrs = getattr(art, "attrs", None)
    if attrs is None and isinstance(art, Mapping):
        attrs = art.get("attrs", {})
    return dict(attrs or {})
