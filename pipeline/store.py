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
crash leaves no readable partial artifact.  An artifact carries its own key (provenance
"key"), checked whenever it is read or verified; records, refs and run logs carry "check",
the digest of their content, checked whenever they are read.
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
from pipeline.hashing import digest_obj
from pipeline.space import raise_if_full

def _atomic_write_text(path: Path, text: str) -> None:
    """Whole or absent, never half-written; a failed write (a full disk) leaves no temp file.
    Not fsync'd: index records and refs are hints rebuilt from the artifacts themselves,
    which are fsync'd."""
    tmp = path.with_name(f".tmp-{path.name}-{os.getpid()}-{uuid.uuid4().hex[:8]}")
    try:
        with open(tmp, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(exc, OSError):
            raise_if_full(exc, path.parent, need=len(text.encode()))
        raise


def _read_json(path: Path, kind: type = dict):
    """A bookkeeping file's JSON if it parses to `kind`, else None (hints are rebuilt, never
    trusted when damaged)."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, kind) else None


def sealed(doc: dict) -> dict:
    """doc with "check", the digest of the rest of its content: an edit of a bookkeeping file
    (a metric in an index record, a key in a ref) is then found when it is read."""
    body = {k: v for k, v in doc.items() if k != "check"}
    return {**body, "check": digest_obj(body)}


def seal_state(doc) -> str:
    """"ok" (its check matches), "unsealed" (a mapping written before records were sealed)
    or "damaged" (not a mapping, or its check does not match its content)."""
    if not isinstance(doc, dict):
        return "damaged"
    if "check" not in doc:
        return "unsealed"
    body = {k: v for k, v in doc.items() if k != "check"}
    try:
        return "ok" if doc["check"] == digest_obj(body) else "damaged"
    except TypeError:
        return "damaged"


_RECORD_FIELDS = {"key": str, "digest": str, "bytes": int, "mtime_ns": int}


def _valid_record(rec) -> bool:
    return (isinstance(rec, dict) and all(isinstance(rec.get(f), t) for f, t in _RECORD_FIELDS.items())
            and seal_state(rec) == "ok")


def list_dir(folder: Path, pattern: str = "*") -> list[Path]:
    """The entries of a store folder matching `pattern`, sorted; [] when it does not exist.
    A folder that exists but cannot be read is a one-line error: read as empty, it would make
    gc delete what its files protect and verify forget every artifact."""
    import fnmatch
    try:
        with os.scandir(folder) as it:
            names = [e.name for e in it]
    except FileNotFoundError:
        return []
    except OSError as exc:
        raise PipelineError(f"cannot read {folder}: {exc.strerror or exc} (nothing was changed)") from None
    return sorted(folder / n for n in names if fnmatch.fnmatchcase(n, pattern))


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
        return [p for p in list_dir(self.objects, "*.h5") if not p.name.startswith(".")]

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
            rec = None   # missing, edited or of another key: rebuilt from the artifact
        if rec is not None and (not check or (rec["bytes"] == st.st_size and rec["mtime_ns"] == st.st_mtime_ns)):
            return rec
        # no index (crash between the two renames), a damaged record or a changed file:
        # trust only content
        from pipeline.artifact import read_record, verify_file
        ok, message = verify_file(path)
        if not ok:
            self.quarantine(key, message)
            return None
        rec = read_record(path)
        rec["path"] = os.path.relpath(path, self.root)
        rec["bytes"], rec["mtime_ns"] = st.st_size, st.st_mtime_ns
        return self.write_record(rec)

    def write_record(self, rec: dict) -> dict:
        rec = sealed(rec)
        try:
            _atomic_write_text(self._index_path(rec["key"]), json.dumps(rec, indent=1, sort_keys=True))
        except FileNotFoundError:   # index/ deleted: rebuilt record by record from the objects
            self.index.mkdir(parents=True, exist_ok=True)
            _atomic_write_text(self._index_path(rec["key"]), json.dumps(rec, indent=1, sort_keys=True))
        return rec

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

    def open(self, key: str, name: str):
        """Artifact `key` for reading by `name` (a node instance's input).  A file that carries
        another key (copied or moved over this one) is refused: moved aside, one line naming
        it, and the next run recomputes it."""
        from pipeline.artifact import Artifact
        try:
            art = Artifact(self.path(key))
        except PipelineError:          # a damaged superblock or header fails its checksum
            self.check_damage(key, name)
            raise
        try:
            found = art.provenance.get("key")
        except Exception:  # noqa: BLE001 - unreadable provenance: check_damage names it
            found = None
        if found != key:
            art.close()
            self.check_damage(key, name)   # re-checks the key first: raises
            raise PipelineError(f"{name}: artifact {key} carries key {found!r}")
        return art

    def records(self) -> list[dict]:
        out = []
        for p in list_dir(self.index, "*.json"):
            rec = _read_json(p)
            if _valid_record(rec) and rec["key"] == p.stem:
                out.append(rec)
        return sorted(out, key=lambda r: (r.get("created", ""), r["key"]))

    def find(self, text: str) -> dict:
        """A record by full key, unique key prefix (>= 6 chars), or None."""
        if len(text) >= 6 and all(c in "0123456789abcdef" for c in text):
            hits = [p.stem for p in list_dir(self.index, f"{text}*.json")]
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
        ref = _read_json(self.refs / f"{safe_name(instance)}.json")
        return ref if seal_state(ref) in ("ok", "unsealed") else None

    def write_ref(self, instance: str, ref: dict, *, changed: bool = False) -> None:
        """Only rewritten when it changes (dvc watches these files); `changed` skips the
        comparison when the caller knows."""
        path = self.refs / f"{safe_name(instance)}.json"
        text = json.dumps(sealed(ref), indent=1, sort_keys=True) + "\n"
        if not changed:
            with contextlib.suppress(OSError):
                if path.read_text() == text:
                    return
        _atomic_write_text(path, text)

    def last_run(self) -> dict | None:
        """The newest run log whose content checks out (its meta: targets, profile, params)."""
        for path in reversed(list_dir(self.runs, "*.json")):
            doc = _read_json(path)
            if isinstance(doc, dict) and seal_state(doc) in ("ok", "unsealed"):
                return doc
        return None

    def log_run(self, keys: list[str], meta: dict) -> None:
        stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime())
        path = self.runs / f"{stamp}-{os.getpid()}-{uuid.uuid4().hex[:6]}.json"
        _atomic_write_text(path, json.dumps(sealed({**meta, "keys": sorted(set(keys))}), indent=1))

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
        # the artifact carries its own key: a file copied over another key's path is found
        return ArtifactWriter(self, key, tmp, {**provenance, "key": key})

    def _publish(self, key: str, tmp: Path, record: dict, durable: bool = False) -> dict:
        try:
            _fsync(tmp)     # a filesystem that allocates late may find the disk full only now
        except OSError as exc:
            raise_if_full(exc, self.objects, tmp.stat().st_size)
            raise
        final = self.path(key)
        # no directory fsync by default: a rename lost to a power cut leaves the artifact
        # missing (recomputed), never partial; `durable` fsyncs it, for what cannot be recomputed
        os.replace(tmp, final)
        if durable:
            _fsync(self.objects)
        st = final.stat()
        record.update(path=os.path.relpath(final, self.root), bytes=st.st_size,
                      mtime_ns=st.st_mtime_ns, host=socket.gethostname())
        return self.write_record(record)

    # -- maintenance -----------------------------------------------------------------

    def verify(self, progress=None) -> list[tuple[str, str]]:
        """Re-digest every artifact and check every index record, ref and run log.

        Returns [(what, problem)]: `what` is an artifact's key, or the store-relative path of
        a damaged bookkeeping file (index/<key>.json, refs/<name>.json, runs/<name>.json).
        Every folder is listed first, so one that cannot be read is a one-line error before
        anything is judged (read as empty, it would make every artifact look missing)."""
        from pipeline.artifact import verify_content
        paths = self.object_paths()
        index, refs, runs = (list_dir(d, "*.json") for d in (self.index, self.refs, self.runs))
        present = {p.stem for p in paths}
        bad = [(p.stem, "file missing") for p in index if p.stem not in present]
        digests = {}
        for p in progress(paths) if progress else paths:
            ok, message, digest = verify_content(p)
            if ok:
                digests[p.stem] = digest
            else:
                bad.append((p.stem, message))
        for p in index:
            if p.stem not in digests:   # missing or corrupt: reported above
                continue
            rec = _read_json(p)
            if not _valid_record(rec) or rec["key"] != p.stem:
                bad.append((self._rel(p), "damaged record: its content does not match its check"))
            elif rec["digest"] != digests[p.stem]:
                bad.append((self._rel(p), f"record's digest {rec['digest'][:12]} != the artifact's "
                                          f"{digests[p.stem][:12]}"))
        for p in refs:
            if self._ref_key(p) is None:
                bad.append((self._rel(p), "damaged ref: not a ref, or its content does not match its check"))
        for p in runs:
            if self._run_keys(p) is None:
                bad.append((self._rel(p), "damaged run log: not a run log, or its content does not match its check"))
        return bad

    def _rel(self, path: Path) -> str:
        return os.path.relpath(path, self.root)

    @staticmethod
    def _ref_key(path: Path) -> str | None:
        """The key a ref file names, or None when it is damaged (unsealed refs of older stores
        are read as they are)."""
        ref = _read_json(path)
        if seal_state(ref) == "damaged" or not isinstance(ref.get("key"), str):
            return None
        return ref["key"]

    @staticmethod
    def _run_keys(path: Path) -> list[str] | None:
        doc = _read_json(path)
        if seal_state(doc) == "damaged":
            return None
        keys = doc.get("keys")
        if not isinstance(keys, list) or not all(isinstance(k, str) for k in keys):
            return None
        return keys

    def gc(self, keep: set[str], *, dry_run: bool = False, keep_runs: int = 5) -> list[str]:
        """Remove artifacts that neither `keep` (the current plan's keys), a ref nor one of the
        last `keep_runs` runs uses.

        Inputs of kept artifacts are kept too.  Anything gc cannot read (a folder, a ref, a
        run log, a kept artifact's inputs) stops it before it removes anything: what that
        file protects is unknown.  Returns the removed keys.
        """
        keep = set(keep)
        if keep_runs < 0:
            raise PipelineError(f"gc: keep_runs must be >= 0, got {keep_runs}")

        def damaged(p: Path) -> PipelineError:  # what it protected is unknown: delete nothing
            return PipelineError(f"gc: {p} is damaged, so what it keeps is unknown; fix or remove it, "
                                 "then run gc again (nothing was removed)")
        for p in list_dir(self.refs, "*.json"):
            key = self._ref_key(p)
            if key is None:
                raise damaged(p)
            keep.add(key)
        runs = list_dir(self.runs, "*.json")
        for p in runs[-keep_runs:] if keep_runs > 0 else []:
            keys = self._run_keys(p)
            if keys is None:
                raise damaged(p)
            keep.update(keys)
        present = {p.stem for p in self.object_paths()}
        records = {r["key"]: r for r in self.records()}
        temps = list_dir(self.objects, ".tmp-*")
        stack = list(keep)
        while stack:  # keep inputs of kept artifacts
            key = stack.pop()
            for k in self._inputs_of(key, records, key in present):
                if k not in keep:
                    keep.add(k)
                    stack.append(k)
        removed = []
        for key in sorted(set(records) | present):
            if key in keep:
                continue
            removed.append(key)
            if not dry_run:
                for p in (self.path(key), self._index_path(key), self.locks / f"{key}.lock"):
                    with contextlib.suppress(FileNotFoundError):
                        p.unlink()
        if not dry_run:
            for p in temps:
                if _abandoned(p):
                    p.unlink(missing_ok=True)
            for p in runs[:-keep_runs] if keep_runs > 0 else runs:
                p.unlink(missing_ok=True)
        return removed

    def _inputs_of(self, key: str, records: dict, present: bool) -> list[str]:
        """The input keys of artifact `key`: from its sealed record, else from the provenance
        the file carries (its content is not re-digested: gc never judges or moves artifacts)."""
        rec = records.get(key)
        if rec is None and present:
            from pipeline.artifact import read_record
            try:
                rec = read_record(self.path(key))
            except Exception as exc:  # noqa: BLE001 - h5py's many ways to fail on a damaged file
                if not self.path(key).exists():
                    return []
                raise PipelineError(f"gc: artifact {key} cannot be read ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__}), "
                                    "so which inputs it keeps is unknown; a `pipeline run` that needs it "
                                    f"moves it aside and recomputes it, or remove {self.path(key)} "
                                    "(nothing was removed)") from None
        out = []
        for v in ((rec or {}).get("inputs") or {}).values():
            out += list(v.values()) if isinstance(v, dict) else [v]
        return [k for k in out if isinstance(k, str)]

    def known_digest(self, key: str) -> dict | None:
        """{"key", "digest"} of artifact `key` as its sealed record or its file tells, without
        re-digesting or moving anything: what gc plans with, so that a damaged artifact still
        yields the keys of what depends on it.  None when neither can be read."""
        rec = _read_json(self._index_path(key))
        if _valid_record(rec) and rec["key"] == key:
            return rec
        if not self.path(key).exists():
            return None
        from pipeline.artifact import read_record
        try:
            rec = read_record(self.path(key))
        except Exception:  # noqa: BLE001 - unreadable: its digest is unknown
            return None
        return rec if rec.get("key") == key and isinstance(rec.get("digest"), str) else None

    def checkpoint_path(self, key: str) -> Path:
        """Where the node computing `key` keeps its training checkpoint."""
        return self.staging / f"{key}.ckpt"

    def orphan_checkpoints(self, live: set[str]) -> list[Path]:
        """Training checkpoints in `staging/` (<key>.ckpt, and the .bad and .tmp files beside
        them) whose key is not in `live`: a run of those keys can never resume from them."""
        found = self.staging.glob("*.ckpt*") if self.staging.is_dir() else []
        return sorted(p for p in found if p.name.partition(".")[0] not in live)


TMP_MAX_AGE_S = 24 * 3600


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


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


