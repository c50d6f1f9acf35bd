"""Canonical serialisation and digests: cache keys and content digests.

A cache key changes only when something that can change a node's output changes:
its name, code, params subset, its inputs' content digests, or ENGINE_VERSION.
"""
from __future__ import annotations

import hashlib
import json
import math
from typing import Any, Mapping

# Bump when the store layout or the meaning of a key changes: every key changes with it.
ENGINE_VERSION = "2"  # 2: nested attributes read back decoded (json_attrs)
KEY_LENGTH = 32  # hex chars (128 bits)


def _plain(obj: Any) -> Any:
    """Convert to JSON-able plain values with one spelling per value."""
    if isinstance(obj, Mapping):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, bool) or obj is None or isinstance(obj, str):
        return obj
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):
        if math.isnan(obj) or math.isinf(obj):
            return repr(obj)
        # 1 and 1.0 are the same parameter value to a numeric node
        return int(obj) if obj.is_integer() and abs(obj) < 2**53 else obj
    tolist = getattr(obj, "tolist", None)  # numpy arrays and scalars
    if callable(tolist):
        return _plain(tolist())
    raise TypeError(f"cannot hash value of type {type(obj).__name__}")


def canonical(obj: Any) -> str:
    return json.dumps(_plain(obj), sort_keys=True, separators=(",", ":"), ensure_ascii=True)


def digest_text(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def digest_obj(obj: Any) -> str:
    return digest_text(canonical(obj))


def cache_key(node: str, code: str, params: Mapping[str, Any], inputs: Mapping[str, Any]) -> str:
    """Input-addressed key: name + code fingerprint + params subset + input content digests."""
    payload = {"engine": ENGINE_VERSION, "node": node, "code": code,
               "params": params, "inputs": inputs}
    return digest_obj(payload)[:KEY_LENGTH]


class ContentDigest:
    """Digest of an artifact's logical content, not of its HDF5 bytes.

    Per dataset: name, dtype, shape and the C-order bytes; then the user attributes in
    canonical order. Datasets may be fed in chunks along axis 0 (streamed writes).
    """

    def __init__(self) -> None:
        self._datasets: dict[str, tuple[Any, str, list[int]]] = {}

    def update(self, name: str, chunk, *, dtype: str, shape_tail: tuple[int, ...]) -> None:
        h, _, shape = self._datasets.setdefault(name, (hashlib.sha256(), dtype, [0, *shape_tail]))
        data = memoryview(chunk).cast("B") if chunk.nbytes else b""
        h.update(data)
        shape[0] += chunk.shape[0] if chunk.ndim else 1

    def update_whole(self, name: str, array) -> None:
        """A dataset written in one piece (any rank, scalars included)."""
        h = hashlib.sha256()
        if array.dtype.kind == "O":
            h.update(canonical([str(s) for s in array.ravel()]).encode())
            dtype = "str"
        else:
            h.update(memoryview(array).cast("B") if array.nbytes else b"")
            dtype = array.dtype.str
        self._datasets[name] = (h, dtype, list(array.shape))

    def hexdigest(self, attrs: Mapping[str, Any]) -> str:
        outer = hashlib.sha256(b"pipeline-content-v1\0")
        for name in sorted(self._datasets):
            h, dtype, shape = self._datasets[name]
            outer.update(f"{name}\0{dtype}\0{shape}\0{h.hexdigest()}\n".encode())
        outer.update(canonical(attrs).encode())
        return outer.hexdigest()
