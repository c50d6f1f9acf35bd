"""Content-addressed artifact store: one HDF5 file per cache key.

Layout under the store root:
  objects/<key>.h5      the artifact; provenance in its root attribute "pipeline" (JSON)
  index/<key>.json      a small record (digest, size, mtime...) so that deciding
                        "nothing to do" never opens HDF5
  refs/<instance>.json  the key last built for each node instance (for status and gc)
  runs/<time>.json      the keys each run used (gc keeps recent runs)
  locks/<key>.lock      per-key lock: two processes never compute one key twice
  corrupt/              artifacts that failed verification, moved aside, never deleted

Writes go to a temp file in objects/, are fsync'd, then os.replace'd into place, so a
crash leaves no readable partial artifact.
"""
from __future__ import annotations

import contextlib
import fcntl
import json
import os
import socket
import time
import uuid
from pathlib import Path
from typing import Any, Iterator

from pipeline.errors import PipelineError

def _atomic_write_text(path: Path, text: str) -> None:
    """Whole or absent, never half-written. Not fsync'd: index records and refs are
    hints rebuilt from the artifacts themselves, which are fsync'd."""
    tmp = path.with_name(f".tmp-{path.name}-{os.getpid()}-{uuid.uuid4().hex[:8]}")
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, path)


def _read_json(path: Path, kind: type = dict):
    """A bookkeeping file's JSON if it parses to `kind`, else None (hints are rebuilt, never
    trusted when damaged)."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, kind) else None


_RECORD_FIELDS = {"key": str, "digest": str, "bytes": int, "mtime_ns": int}


def _valid_record(rec) -> bool:
    return isinstance(rec, dict) and all(isinstance(rec.get(f), t) for f, t in _RECORD_FIELDS.items())


def safe_name(instance: str) -> str:
    """'render[sensor=a]' -> 'render@sensor=a' (a file name with no brackets)."""
    return instance.replace("[", "@").replace("]", "").replace("/", "_")


class Store:
    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        self.objects = self.root / "objects"
        self.index = self.root / "index"
        self.refs = self.root / "refs"
        self.runs = self.root / "runs"
        self.locks = self.root / "locks"
        self.corrupt = self.root / "corrupt"
        self.staging = self.root / "staging"    # capture staging files, training checkpoints

    def init(self) -> "Store":
        try:
            for d in (self.objects, self.index, self.refs, self.runs, self.locks):
                d.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise PipelineError(f"cannot create store at {self.root}: {exc.strerror}") from None
        return self

    def path(self, key: str) -> Path:
        return self.objects / f"{key}.h5"

    def object_paths(self) -> list[Path]:
        """Published artifacts (temp files of writers in progress start with '.')."""
        if not self.objects.is_dir():
            return []
        return sorted(p for p in self.objects.glob("*.h5") if not p.name.startswith("."))

    # -- records ---------------------------------------------------------------------

    def _index_path(self, key: str) -> Path:
        return self.index / f"{key}.json"

    def record(self, key: str, *, check: bool = True) -> dict | None:
        """The record of a complete, intact artifact, or None.

        Fast path: the index record and a stat() that matches it. When the file changed
        behind the store's back (size or mtime differ), its content is re-digested; an
        artifact whose content no longer matches is moved to corrupt/.
        """
        path = self.path(key)
        try:
            st = path.stat()
        except OSError:
            return None
        rec = _read_json(self._index_path(key))
        if not _valid_record(rec) or rec["key"] != key:
            rec = None
        if rec is not None and (not check or (rec["bytes"] == st.st_size and rec["mtime_ns"] == st.st_mtime_ns)):
            return rec
        # no index (crash between the two renames) or a changed file: trust only content
        from pipeline.artifact import read_record, verify_file
        ok, message = verify_file(path)
        if not ok:
            self.quarantine(key, message)
            return None
        rec = read_record(path)
        rec["path"] = os.path.relpath(path, self.root)
        rec["bytes"], rec["mtime_ns"] = st.st_size, st.st_mtime_ns
        _atomic_write_text(self._index_path(key), json.dumps(rec, indent=1, sort_keys=True))
        return rec

    def write_record(self, rec: dict) -> None:
        _atomic_write_text(self._index_path(rec["key"]), json.dumps(rec, indent=1, sort_keys=True))

    def quarantine(self, key: str, why: str) -> Path | None:
        """Move a damaged artifact aside (kept for inspection) and forget its record."""
        try:
            self.corrupt.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise PipelineError(f"artifact {key} is damaged ({why}) and cannot be moved aside: "
                                f"{self.corrupt}: {exc.strerror}") from None
        src = self.path(key)
        dest = self.corrupt / f"{key}-{int(time.time())}-{uuid.uuid4().hex[:6]}.h5"
        try:
            os.replace(src, dest)
            (self.corrupt / f"{dest.stem}.txt").write_text(why + "\n")
        except FileNotFoundError:
            dest = None
        with contextlib.suppress(FileNotFoundError):
            self._index_path(key).unlink()
        return dest

    def check_damage(self, key: str, name: str) -> None:
        """After reading artifact `key` (of node instance `name`) failed although its record
        matched: re-digest it and, if its content is damaged, move it aside and raise a
        one-line error naming it. Returns when the content is intact."""
        from pipeline.artifact import verify_file
        path = self.path(key)
        if not path.exists():
            raise PipelineError(f"{name}: artifact {key} vanished from the store; `pipeline run` recomputes it")
        ok, message = verify_file(path)
        if ok:
            return
        dest = self.quarantine(key, message)
        raise PipelineError(f"{name}: artifact {key} is corrupt ({message}); moved to "
                            f"{os.path.relpath(dest, self.root) if dest else 'nowhere'}, "
                            "`pipeline run` recomputes it")

    def records(self) -> list[dict]:
        out = []
        for p in sorted(self.index.glob("*.json")) if self.index.is_dir() else []:
            rec = _read_json(p)
            if _valid_record(rec) and rec["key"] == p.stem:
                out.append(rec)
        return sorted(out, key=lambda r: (r.get("created", ""), r["key"]))

    def find(self, text: str) -> dict:
        """A record by full key, unique key prefix (>= 6 chars), or None."""
        if len(text) >= 6 and all(c in "0123456789abcdef" for c in text):
            hits = [p.stem for p in self.index.glob(f"{text}*.json")] if self.index.is_dir() else []
            if len(hits) > 1:
                raise PipelineError(f"key prefix '{text}' is ambiguous ({len(hits)} artifacts)")
            if hits:
                rec = self.record(hits[0])
                if rec is None:
                    raise PipelineError(f"artifact {hits[0]} is missing or corrupt")
                return rec
        raise PipelineError(f"no artifact with key '{text}' in store {self.root}")

    # -- refs and runs ---------------------------------------------------------------

    def read_ref(self, instance: str) -> dict | None:
        return _read_json(self.refs / f"{safe_name(instance)}.json")

    def write_ref(self, instance: str, ref: dict, *, changed: bool = False) -> None:
        """Only rewritten when it changes (dvc watches these files); `changed` skips the
        comparison when the caller knows."""
        path = self.refs / f"{safe_name(instance)}.json"
        text = json.dumps(ref, indent=1, sort_keys=True) + "\n"
        if not changed:
            with contextlib.suppress(OSError):
                if path.read_text() == text:
                    return
        _atomic_write_text(path, text)

    def log_run(self, keys: list[str], meta: dict) -> None:
        stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime())
        path = self.runs / f"{stamp}-{os.getpid()}-{uuid.uuid4().hex[:6]}.json"
        _atomic_write_text(path, json.dumps({**meta, "keys": sorted(set(keys))}, indent=1))

    # -- locking ---------------------------------------------------------------------

    @contextlib.contextmanager
    def lock(self, key: str) -> Iterator[None]:
        self.locks.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.locks / f"{key}.lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            yield
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)

    # -- writing ---------------------------------------------------------------------

    def writer(self, key: str, provenance: dict[str, Any]):
        from pipeline.artifact import ArtifactWriter
        self.init()
        tmp = self.objects / f".tmp-{key}-{os.getpid()}-{uuid.uuid4().hex[:8]}-{socket.gethostname()}.h5"
        return ArtifactWriter(self, key, tmp, provenance)

    def _publish(self, key: str, tmp: Path, record: dict) -> dict:
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        final = self.path(key)
        # no directory fsync: a rename lost to a power cut leaves the artifact missing
        # (recomputed), never partial
        os.replace(tmp, final)
        st = final.stat()
        record.update(path=os.path.relpath(final, self.root), bytes=st.st_size,
                      mtime_ns=st.st_mtime_ns, host=socket.gethostname())
        self.write_record(record)
        return record

    # -- maintenance -----------------------------------------------------------------

    def verify(self, progress=None) -> list[tuple[str, str]]:
        """Re-digest every artifact; return [(key, problem)] for the damaged ones."""
        from pipeline.artifact import verify_file
        bad = []
        paths = self.object_paths()
        known = {p.stem for p in self.index.glob("*.json")} if self.index.is_dir() else set()
        for key in sorted(known - {p.stem for p in paths}):
            bad.append((key, "file missing"))
        for p in progress(paths) if progress else paths:
            ok, message = verify_file(p)
            if not ok:
                bad.append((p.stem, message))
        return bad

    def gc(self, keep: set[str], *, dry_run: bool = False, keep_runs: int = 5) -> list[str]:
        """Remove artifacts neither a ref nor one of the last `keep_runs` runs uses.

        Inputs of kept artifacts are kept too. Returns the removed keys.
        """
        keep = set(keep)
        if keep_runs < 0:
            raise PipelineError(f"gc: keep_runs must be >= 0, got {keep_runs}")

        def damaged(p: Path) -> PipelineError:  # what it protected is unknown: delete nothing
            return PipelineError(f"gc: {p} is damaged, so what it keeps is unknown; fix or remove it, "
                                 "then run gc again (nothing was removed)")
        for p in self.refs.glob("*.json") if self.refs.is_dir() else []:
            key = (_read_json(p) or {}).get("key")
            if not isinstance(key, str):
                raise damaged(p)
            keep.add(key)
        runs = sorted(self.runs.glob("*.json")) if self.runs.is_dir() else []
        for p in runs[-keep_runs:] if keep_runs > 0 else []:
            keys = (_read_json(p) or {}).get("keys")
            if not isinstance(keys, list) or not all(isinstance(k, str) for k in keys):
                raise damaged(p)
            keep.update(keys)
        records = {r["key"]: r for r in self.records()}
        stack = list(keep)
        while stack:  # keep inputs of kept artifacts (a damaged index record is rebuilt)
            key = stack.pop()
            rec = records.get(key) or self.record(key)
            for v in (rec or {}).get("inputs", {}).values():
                for k in (v.values() if isinstance(v, dict) else [v]):
                    if k not in keep:
                        keep.add(k)
                        stack.append(k)
        removed = []
        for key in sorted(set(records) | {p.stem for p in self.object_paths()}):
            if key in keep:
                continue
            removed.append(key)
            if not dry_run:
                for p in (self.path(key), self._index_path(key), self.locks / f"{key}.lock"):
                    with contextlib.suppress(FileNotFoundError):
                        p.unlink()
        if not dry_run:
            for p in self.objects.glob(".tmp-*"):
                if _abandoned(p):
                    p.unlink(missing_ok=True)
            for p in runs[:-keep_runs] if keep_runs > 0 else runs:
                p.unlink(missing_ok=True)
        return removed

    def checkpoint_path(self, key: str) -> Path:
        """Where the node computing `key` keeps its training checkpoint."""
        return self.staging / f"{key}.ckpt"

    def orphan_checkpoints(self, live: set[str]) -> list[Path]:
        """Training checkpoints in `staging/` (<key>.ckpt, and the .bad and .tmp files beside
        them) whose key is not in `live`: a run of those keys can never resume from them."""
        found = self.staging.glob("*.ckpt*") if self.staging.is_dir() else []
        return sorted(p for p in found if p.name.partition(".")[0] not in live)


TMP_MAX_AGE_S = 24 * 3600


def _abandoned(tmp: Path) -> bool:
    """A writer's temp file whose writer is gone: a dead process on this host, or (for
    writers on other hosts sharing the store, whose processes we cannot see) a day old."""
    parts = tmp.name[len(".tmp-"):-len(".h5")].split("-", 3)  # key, pid, uuid, host
    try:
        age = time.time() - tmp.stat().st_mtime
    except OSError:
        return False
    if age > TMP_MAX_AGE_S:
        return True
    if len(parts) == 4 and parts[1].isdigit() and parts[3] == socket.gethostname():
        return not _alive(int(parts[1]))
    return False


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


