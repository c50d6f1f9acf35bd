"""The resumable staging file of a capture session: ``<staging_dir>/capture-<name>.h5``.

One resizable dataset per per-frame field (frame axis 0, chunked; camera frames lzf-compressed),
appended as samples arrive (in blocks of BLOCK rows and at every commit).  ``commit()`` after
every complete contact records how many rows and contacts are complete and flushes the file,
so an interruption loses at most the contact in progress: an error rolls the datasets back to
the committed rows, reopening after a crash does the same (the partial contact), and the
capture continues with the next contact.  The file also records the
capture's parameters (JSON); reopening it with different parameters is refused, since mixing
two set-ups in one artifact would be wrong.  Attributes: params, committed_rows,
committed_contacts, sessions (runs that opened it), counts (device counters at the last
commit, JSON), seconds (capture time of the committed contacts), complete, and free-form
values set with ``set``.
"""
from __future__ import annotations

import json
import os
from typing import Mapping

import numpy as np

from stages.common import InputError

_ROWS_PER_CHUNK = 256
BLOCK = 16                  # rows buffered between writes (a partial contact is dropped anyway)


def _flat(tree, prefix=""):
    out = {}
    for k, v in (tree or {}).items():
        name = f"{prefix}.{k}" if prefix else str(k)
        out.update(_flat(v, name) if isinstance(v, Mapping) else {name: v})
    return out


def _canonical(params: Mapping) -> str:
    return json.dumps(params, sort_keys=True, default=lambda v: np.asarray(v).tolist())


class Staging:
    """layout: dataset name -> (per-row shape, dtype)."""

    def __init__(self, path: str, params: Mapping, layout: Mapping[str, tuple]):
        import h5py
        self.path, self.layout = str(path), dict(layout)
        text = _canonical(params)
        fresh = not os.path.exists(self.path)
        try:
            self.f = h5py.File(self.path, "w" if fresh else "a")
        except OSError as exc:
            raise InputError(f"staging file {self.path} cannot be opened ({exc}); remove it to start "
                             "the capture over") from None
        if not fresh and self.f.attrs.get("params") != text and not int(self.f.attrs.get("committed_contacts", 0)):
            # other parameters but nothing captured yet (a run that failed before its first
            # contact): nothing to keep, start over
            self.f.close()
            self.f = h5py.File(self.path, "w")
            fresh = True
        if fresh:
            self.f.attrs.update({"params": text, "committed_rows": 0, "committed_contacts": 0,
                                 "sessions": 0, "counts": "{}", "seconds": 0.0, "complete": False})
        elif self.f.attrs.get("params") != text:
            old, new = _flat(json.loads(self.f.attrs.get("params", "{}"))), _flat(json.loads(text))
            keys = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
            self.f.close()
            raise InputError(f"staging file {self.path} holds a capture with other parameters "
                             f"(differs in {', '.join(keys[:6])}); finish it with its parameters, "
                             "or remove it (or choose another session name) to start over")
        for name, (shape, dtype) in self.layout.items():
            if name not in self.f:
                shape = tuple(int(v) for v in shape)
                big = int(np.prod(shape)) > 4096
                self.f.create_dataset(name, shape=(0,) + shape, maxshape=(None,) + shape, dtype=dtype,
                                      chunks=(1 if big else _ROWS_PER_CHUNK,) + shape,
                                      compression="lzf" if big else None)
        self._buffer: dict[str, list] = {name: [] for name in self.layout}
        self.f.attrs["sessions"] = int(self.f.attrs["sessions"]) + 1
        self.rollback()                                 # a partial contact left by a crash

    @property
    def contacts_done(self) -> int:
        return int(self.f.attrs["committed_contacts"])

    @property
    def complete(self) -> bool:
        return bool(self.f.attrs["complete"])

    def get(self, key: str, default=None):
        return self.f.attrs.get(key, default)

    def set(self, key: str, value) -> None:
        self.f.attrs[key] = value
        self.f.flush()

    def put(self, name: str, array) -> None:
        """A non-per-frame array (e.g. a reference image), written once."""
        if name not in self.f:
            self.f.create_dataset(name, data=np.asarray(array))
            self.f.flush()

    def append(self, row: Mapping) -> None:
        """One sample: every dataset of the layout gets one row (written in blocks of BLOCK)."""
        missing = set(self.layout) - set(row)
        if missing:
            raise KeyError(f"staging row lacks {', '.join(sorted(missing))}")
        for name, (_, dtype) in self.layout.items():
            self._buffer[name].append(np.asarray(row[name], dtype))
        self.rows += 1
        if len(self._buffer["frame"]) >= BLOCK:
            self._write()

    def _write(self) -> None:
        for name, rows in self._buffer.items():
            if rows:
                ds = self.f[name]
                n = ds.shape[0]
                ds.resize(n + len(rows), axis=0)
                ds[n:] = np.stack(rows)
                rows.clear()

    def commit(self, counts: Mapping, seconds: float) -> None:
        """The rows so far form complete contacts: write them, record them and flush."""
        self._write()
        self.f.attrs.update({"committed_rows": self.rows,
                             "committed_contacts": self.contacts_done + 1,
                             "counts": json.dumps(dict(counts), sort_keys=True),
                             "seconds": float(self.f.attrs["seconds"]) + float(seconds)})
        self.f.flush()

    def rollback(self) -> None:
        """Drop the rows of a contact that did not complete."""
        self.rows = int(self.f.attrs["committed_rows"])
        for name in self.layout:
            self._buffer[name].clear()
            self.f[name].resize(self.rows, axis=0)
        self.f.flush()

    def counts(self) -> dict:
        return json.loads(self.f.attrs["counts"])

    def read(self, name: str, start: int = 0, stop: int | None = None) -> np.ndarray:
        return self.f[name][start:stop]

    def close(self) -> None:
        if self.f.id.valid:
            self.f.flush()
            self.f.close()
