"""Reading and writing one HDF5 artifact (imports h5py; not on the no-op path).

Datasets are numeric arrays or lists of strings, never pickled objects. Nested
mappings become groups ("model/encoder.weight"). Streamed datasets grow along axis 0
in chunks, so a node making thousands of frames never holds them all.
"""
from __future__ import annotations

import errno
import io
import json
import os
import threading
import time
from pathlib import Path
from typing import Any, Iterator, Mapping

import h5py
import numpy as np

from pipeline.errors import PipelineError
from pipeline.hashing import ContentDigest

COMPRESS_MIN_BYTES = 1 << 16
# Every numeric array is chunked with HDF5's Fletcher32 checksum on each chunk, and the file's
# metadata (object headers, attributes) carries HDF5's own checksums (format v110 and later):
# a damaged byte makes its read fail, where lzf alone would decompress it into other values
# without a word.  A node whose read fails has its inputs re-digested (pipeline.worker).
CHECKSUM = {"fletcher32": True}
LIBVER = ("v110", "latest")
CHUNK_BYTES = 1 << 20
OVERLAP_BYTES = 1 << 20   # arrays this large are digested in a thread while HDF5 writes them
READ_BLOCK_BYTES = 1 << 24
_STR = h5py.string_dtype("utf-8")
PROVENANCE_ATTR = "pipeline"  # one JSON attribute: node, params, code, inputs, digest, ...


def _as_array(name: str, value: Any) -> np.ndarray:
    if isinstance(value, np.ndarray):
        arr = value
    elif hasattr(value, "detach") and hasattr(value, "numpy"):  # a torch tensor
        arr = value.detach().cpu().numpy()
    else:
        arr = np.asarray(value)
    if arr.dtype.kind == "U" or (arr.dtype.kind == "O" and all(isinstance(s, str) for s in arr.ravel())):
        return arr.astype(object)
    if arr.dtype.kind not in "biufc":
        raise PipelineError(f"dataset '{name}': unsupported dtype {arr.dtype} "
                            "(numbers or strings only; the store holds no pickles)")
    return arr if arr.flags.c_contiguous else arr.copy(order="C")


def _plain_attr(name: str, value: Any) -> Any:
    """What an attribute reads back as, so that write- and verify-time digests agree."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, (list, tuple, np.ndarray)):
        arr = np.asarray(value)
        if arr.dtype.kind in "biuf" and arr.ndim == 1:
            return arr.tolist()
    try:
        return json.dumps(value, sort_keys=True)
    except TypeError:
        raise PipelineError(f"attribute '{name}': cannot store {type(value).__name__}") from None


def _overlapped(write, digest, nbytes: int) -> None:
    """write() and digest() of one array, both done on return.  A large array is digested in
    a thread meanwhile: hashlib releases the GIL on large buffers, so the hash and HDF5's
    compression and write share two cores instead of taking turns on one.  Waiting for the
    hash before returning keeps the caller free to refill its buffer."""
    if nbytes < OVERLAP_BYTES:
        write()
        digest()
        return
    failed: list[BaseException] = []

    def run() -> None:
        try:
            digest()
        except BaseException as exc:  # noqa: BLE001 - re-raised in the caller's thread
            failed.append(exc)

    thread = threading.Thread(target=run, name="artifact-digest", daemon=True)
    thread.start()
    try:
        write()
    finally:
        thread.join()
    if failed:
        raise failed[0]


class _TempFile(io.FileIO):
    """The temp file HDF5 writes an artifact to.  A write that finds the disk full is
    remembered, and it and every later write are discarded: HDF5 never sees the failure, since
    after one it can neither flush nor close the file (and crashes the process as it exits).
    The writer then raises StoreFull and deletes the file."""

    _write = io.FileIO.write

    def __init__(self, path: Path):
        super().__init__(path, "w+b")
        self.full: OSError | None = None
        self.size = 0           # the furthest byte written: the size the artifact reached

    def write(self, data) -> int:
        view = memoryview(data).cast("B")
        start = self.tell()
        if self.full is None:
            try:
                done = 0
                while done < len(view):
                    done += self._write(view[done:])
            except OSError as exc:
                if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
                    raise
                self.full = exc
            else:
                self.size = max(self.size, start + len(view))
                return len(view)
        self.size = max(self.size, start + len(view))
        self.seek(start + len(view))
        return len(view)


class ArtifactWriter:
    """Collects datasets (whole or appended) and attributes; commit() publishes atomically."""

    def __init__(self, store, key: str, tmp: Path, provenance: dict[str, Any]):
        self.store, self.key, self.tmp = store, key, tmp
        self.provenance = dict(provenance)
        self._raw = _TempFile(tmp)
        try:
            self.file = h5py.File(self._raw, "w", libver=LIBVER)
        except BaseException:
            self._raw.close()
            tmp.unlink(missing_ok=True)
            raise
        self.digest = ContentDigest()
        self.attrs: dict[str, Any] = {}
        self.metrics: dict[str, float] = {}
        self.timing: dict[str, float | None] = {}   # provenance, not content: not digested
        self._streams: dict[str, h5py.Dataset] = {}
        self._whole: set[str] = set()
        self._json_attrs: set[str] = set()
        self._t0 = time.time()

    def put(self, name: str, value: Any) -> None:
        if name in self._streams or name in self._whole:
            raise PipelineError(f"dataset '{name}' written twice")
        arr = _as_array(name, value)

        def write() -> None:
            if arr.dtype.kind == "O":
                self.file.create_dataset(name, data=arr, dtype=_STR)
            elif arr.ndim and arr.size:
                packed = {"compression": "lzf"} if arr.nbytes >= COMPRESS_MIN_BYTES else {}
                self.file.create_dataset(name, data=arr, chunks=True, **packed, **CHECKSUM)
            else:
                self.file.create_dataset(name, data=arr)
        _overlapped(write, lambda: self.digest.update_whole(name, arr),
                    0 if arr.dtype.kind == "O" else arr.nbytes)
        self._whole.add(name)
        self._check_space()

    def append(self, name: str, chunk: Any) -> None:
        if name in self._whole:
            raise PipelineError(f"dataset '{name}' written whole and then appended to")
        arr = _as_array(name, chunk)
        if arr.ndim == 0 or arr.dtype.kind == "O":
            raise PipelineError(f"dataset '{name}': appended chunks must be numeric arrays with a frame axis")
        ds = self._streams.get(name)
        if ds is None:
            row = max(1, arr[0:1].nbytes)
            rows = max(1, min(4096, CHUNK_BYTES // row))
            ds = self.file.create_dataset(name, shape=(0, *arr.shape[1:]), maxshape=(None, *arr.shape[1:]),
                                          dtype=arr.dtype, chunks=(rows, *arr.shape[1:]), compression="lzf",
                                          **CHECKSUM)
            self._streams[name] = ds
        elif ds.dtype != arr.dtype or ds.shape[1:] != arr.shape[1:]:
            raise PipelineError(f"dataset '{name}': chunk {arr.dtype}{arr.shape[1:]} does not match "
                                f"earlier chunks {ds.dtype}{ds.shape[1:]}")
        n = ds.shape[0]

        def write() -> None:
            ds.resize(n + arr.shape[0], axis=0)
            ds[n:] = arr
        # hashed before returning: the caller may refill the same buffer for the next chunk
        _overlapped(write, lambda: self.digest.update(name, arr, dtype=arr.dtype.str, shape_tail=arr.shape[1:]),
                    arr.nbytes)
        self._check_space()

    def _check_space(self) -> None:
        if self._raw.full is not None:
            from pipeline.space import StoreFull
            raise StoreFull(self.tmp.parent, self._raw.size)

    def set_attrs(self, attrs: Mapping[str, Any]) -> None:
        for k, v in attrs.items():
            if k == PROVENANCE_ATTR:
                raise PipelineError(f"attribute name '{k}' is reserved")
            self.attrs[k] = _plain_attr(k, v)
            if isinstance(self.attrs[k], str) and not isinstance(v, str):  # stored as JSON text
                self._json_attrs.add(k)
            else:
                self._json_attrs.discard(k)

    def commit(self, durable: bool = False) -> dict:
        """Publish the artifact; `durable`: its folder's entry is fsync'd too, so that what the
        caller deletes next (a capture's staging file) is never the only copy after a crash."""
        for name in self._streams:  # an empty stream is still a dataset
            if name not in self.digest._datasets:
                ds = self._streams[name]
                self.digest.update(name, np.empty((0, *ds.shape[1:]), ds.dtype),
                                   dtype=ds.dtype.str, shape_tail=ds.shape[1:])
        digest = self.digest.hexdigest({"attrs": self.attrs, "metrics": self.metrics})
        seconds = round(time.time() - self._t0 + self.provenance.pop("setup_seconds", 0.0), 4)
        prov = {**self.provenance, "digest": digest, "seconds": seconds,
                "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                "metrics": self.metrics, "json_attrs": sorted(self._json_attrs)}
        if self.timing:
            prov["timing"] = self.timing
        for k, v in self.attrs.items():
            self.file.attrs[k] = v
        self.file.attrs[PROVENANCE_ATTR] = json.dumps(prov, sort_keys=True)
        self.file.flush()
        self.file.close()
        self._raw.close()
        self._check_space()
        record = {k: prov.get(k) for k in ("key", "digest", "node", "instance", "created",
                                             "seconds", "metrics", "inputs")}
        return self.store._publish(self.key, self.tmp, record, durable=durable)

    def abort(self) -> None:
        try:
            self.file.close()
        finally:
            self._raw.close()
            self.tmp.unlink(missing_ok=True)


class LazyArray:
    """An HDF5 dataset that reads only what is sliced; np.asarray() reads it all."""

    def __init__(self, ds: h5py.Dataset):
        self._ds = ds
        self.shape, self.dtype, self.ndim = ds.shape, ds.dtype, ds.ndim

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, item):
        if self._ds.dtype.kind == "O":  # UTF-8 strings
            out = self._ds.asstr()[item]
            return np.asarray(out, dtype=object) if isinstance(out, np.ndarray) else out
        return self._ds[item]

    def __array__(self, dtype=None, copy=None):
        arr = np.asarray(self[()])  # a 0-d dataset reads as a scalar
        return arr.astype(dtype) if dtype is not None else arr

    def iter_chunks(self, rows: int) -> Iterator[np.ndarray]:
        for i in range(0, self.shape[0], rows):
            yield self[i:i + rows]


class Artifact(Mapping):
    """Read-only view of an artifact: a mapping of dataset name -> LazyArray."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        try:
            self._file = h5py.File(self.path, "r")
        except OSError as exc:
            raise PipelineError(f"cannot open artifact {self.path}: {exc}") from None
        self._listed: list[str] | None = None

    @property
    def _names(self) -> list[str]:
        """Every dataset's name, sorted: walked on first need (iteration, a missing name)."""
        if self._listed is None:
            self._listed = _dataset_names(self._file)
        return self._listed

    def __getitem__(self, name: str) -> LazyArray:
        obj = self._file.get(name) if isinstance(name, str) else None
        if not isinstance(obj, h5py.Dataset):
            raise KeyError(f"{name!r} not in artifact {self.path.name} (has {self._names})")
        return LazyArray(obj)

    def __contains__(self, name) -> bool:
        return isinstance(name, str) and isinstance(self._file.get(name), h5py.Dataset)

    def __iter__(self):
        return iter(self._names)

    def __len__(self) -> int:
        return len(self._names)

    @property
    def attrs(self) -> dict[str, Any]:
        """Attributes as written: nested values (dicts, lists of strings...) are stored as
        JSON text and read back decoded."""
        attrs = _user_attrs(self._file)
        for k in self.provenance.get("json_attrs", []):
            if k in attrs:
                attrs[k] = json.loads(attrs[k])
        return attrs

    @property
    def provenance(self) -> dict[str, Any]:
        return _provenance(self._file)

    @property
    def metrics(self) -> dict[str, float]:
        return self.provenance.get("metrics", {})

    @property
    def timing(self) -> dict[str, float | None]:
        """The node's own timings (flattened names -> seconds, rates): provenance, so outside
        the content digest."""
        return self.provenance.get("timing", {})

    def close(self) -> None:
        self._file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _read_attr(v: Any) -> Any:
    if isinstance(v, bytes):
        return v.decode()
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    return v


def _user_attrs(f: h5py.File) -> dict[str, Any]:
    return {k: _read_attr(v) for k, v in f.attrs.items() if k != PROVENANCE_ATTR}


def _provenance(f: h5py.File) -> dict[str, Any]:
    text = _read_attr(f.attrs.get(PROVENANCE_ATTR, "{}"))
    return json.loads(text) if isinstance(text, str) else {}


def _dataset_names(f: h5py.File) -> list[str]:
    names: list[str] = []
    f.visititems(lambda n, o: names.append(n) if isinstance(o, h5py.Dataset) else None)
    return sorted(names)


def content_digest(f: h5py.File) -> str:
    d = ContentDigest()
    for name in _dataset_names(f):
        ds = f[name]
        if ds.dtype.kind == "O":  # strings, digested as written: an object array of str
            d.update_whole(name, np.asarray(ds.asstr()[()], dtype=object))
            continue
        if ds.ndim == 0:
            d.update_whole(name, np.asarray(ds[()]))
            continue
        row = max(1, int(np.prod(ds.shape[1:], dtype=np.int64)) * ds.dtype.itemsize)
        step = max(1, READ_BLOCK_BYTES // row)
        if ds.shape[0] == 0:
            d.update(name, np.empty(ds.shape, ds.dtype), dtype=ds.dtype.str, shape_tail=ds.shape[1:])
        for i in range(0, ds.shape[0], step):
            block = np.ascontiguousarray(ds[i:i + step])
            d.update(name, block, dtype=ds.dtype.str, shape_tail=ds.shape[1:])
    metrics = _provenance(f).get("metrics", {})
    return d.hexdigest({"attrs": _user_attrs(f), "metrics": metrics})


def verify_file(path: Path) -> tuple[bool, str]:
    """(ok, message): the file carries the key in its name, and its content re-digests to
    the digest it carries."""
    ok, message, _ = verify_content(path)
    return ok, message


def verify_content(path: Path) -> tuple[bool, str, str]:
    """verify_file's (ok, message) and the content digest the file carries ("" if none).

    An artifact's own key is checked first: a file copied or moved over another key's path
    carries a digest that matches its content, so only its key tells it does not belong."""
    path = Path(path)
    try:
        with h5py.File(path, "r") as f:
            prov = _provenance(f)
            stored = prov.get("digest", "")
            if not stored:
                return False, "no content digest (incomplete artifact)", ""
            if prov.get("key") != path.stem:
                return False, f"holds artifact {prov.get('key')}, not {path.stem} (copied or moved over it)", stored
            actual = content_digest(f)
    except Exception as exc:  # h5py raises OSError/KeyError/RuntimeError on damaged files
        return False, f"unreadable: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}", ""
    if actual != stored:
        return False, f"content digest {actual[:12]} != recorded {stored[:12]}", stored
    return True, "ok", stored


def read_record(path: Path) -> dict:
    with Artifact(path) as a:
        prov = a.provenance
    rec = {k: prov.get(k) for k in ("key", "digest", "node", "instance", "created",
                                      "seconds", "metrics", "inputs", "host")}
    return rec
