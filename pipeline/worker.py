"""Runs one node instance: open inputs, call the function, write the artifact.

A task is a plain dict (keys, paths, params), so the same function runs in-process, in
a spawned process or on a Dask worker; no HDF5 object ever crosses a process boundary.
A node function returns a mapping (datasets, plus optional "attrs", "metrics" and "timing"),
or is a generator yielding chunks appended along axis 0 and returning that final mapping.
"timing" (numbers, nested mappings flattened to a/b/c names: seconds, images/s...) goes to the
provenance, beside the engine's own seconds, and out of the content digest: a re-run that
makes the same content at another speed is still an early cutoff.
A function with a `staging_dir` parameter gets `<store>/staging` (hardware capture keeps its
resumable staging files there).  A function with a `checkpoint` parameter gets a path of its
own in it, `<store>/staging/<key>.ckpt`: long training saves its progress there and a later
run of the same key (same code, params and inputs) resumes from it; the worker deletes the
file once the artifact is committed.  A function with an `after_publish` parameter gets a
callable: `after_publish(action)` runs `action()` once the artifact is durably published (its
file and its folder's entry fsync'd), never when the node or the write fails; hardware capture
deletes its staging file so, and a kill at any instant leaves the staging file or the artifact.
A function with a `forced` parameter learns whether this run was forced (`--force`): a
source node's staging left by an earlier, finished session is then not this run's.
An exception whose class sets `user_error = True` (a device that is missing or disconnects) is
reported as one line, like a PipelineError.  A task's "context" ("module:function", the
project's [tool.pipeline] node_context) is a context manager every node runs inside, whatever
executor runs it (the project pins its numeric libraries' threads there).
"""
from __future__ import annotations

import contextlib
import importlib
import inspect
import math
import sys
import time
import traceback
from pathlib import Path
from typing import Any, Mapping

from pipeline.errors import PipelineError

_RESERVED = ("attrs", "metrics", "timing")


_LOADED: dict[str, tuple[int, int]] = {}  # project source file -> (mtime_ns, size) at import
_ENGINE = Path(__file__).resolve().parent


def _stat(path: Path) -> tuple[int, int]:
    try:
        st = path.stat()
        return st.st_mtime_ns, st.st_size
    except OSError:
        return (0, 0)


_TOPS: dict[tuple[str, ...], dict[str, Path]] = {}
_PATHS: dict[tuple[str, int], Path | None] = {}


_SCANS: dict[tuple[str, ...], tuple[int, dict[str, Path]]] = {}  # roots -> (len(sys.modules), result)


def _project_modules(roots: list[str]) -> dict[str, Path]:
    """Loaded modules whose top-level package lives directly in a project root.

    Rescanned only when the number of loaded modules changed (an import adds to it; _import's
    forgetting clears the memo): a thousand trivial nodes otherwise spend a millisecond each
    walking sys.modules."""
    key = tuple(roots)
    memo = _SCANS.get(key)
    if memo is not None and memo[0] == len(sys.modules):
        return memo[1]
    if key not in _TOPS:
        tops = {}
        for r in roots:
            for p in Path(r).iterdir() if Path(r).is_dir() else []:
                tops.setdefault(p.stem if p.suffix == ".py" else p.name, p.resolve())
        _TOPS[key] = tops
    tops = _TOPS[key]
    out = {}
    for name, mod in list(sys.modules.items()):
        top = tops.get(name.partition(".")[0])
        if top is None:
            continue
        ck = (name, id(mod))
        if ck not in _PATHS:
            f = getattr(mod, "__file__", None)
            path = Path(f).resolve() if f else None
            ok = path is not None and path.is_relative_to(top) and not path.is_relative_to(_ENGINE)
            _PATHS[ck] = path if ok else None
        if _PATHS[ck] is not None:
            out[name] = _PATHS[ck]
    _SCANS[key] = (len(sys.modules), out)
    return out


def _import(ref: str, roots: list[str]):
    """Import a node function, never from code older than the files on disk.

    A long-lived process (a Dask worker, a notebook) keeps modules it imported; when any
    project source file changed since, every project module is forgotten and re-imported,
    so the code that runs is the code the cache key was computed from.
    """
    loaded = _project_modules(roots)
    if any(_stat(p) != _LOADED[str(p)] for p in loaded.values() if str(p) in _LOADED):
        for name in loaded:
            sys.modules.pop(name, None)
        _LOADED.clear()
        _SCANS.clear()
        importlib.invalidate_caches()
    module, _, name = ref.partition(":")
    try:
        func = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as exc:
        raise PipelineError(f"cannot import node function '{ref}': {exc}") from None
    for p in _project_modules(roots).values():
        if str(p) not in _LOADED:
            _LOADED[str(p)] = _stat(p)
    return func


def _flatten(mapping: Mapping[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    out = []
    for k, v in mapping.items():
        name = f"{prefix}/{k}" if prefix else str(k)
        if isinstance(v, Mapping):
            out += _flatten(v, name)
        else:
            out.append((name, v))
    return out


def _write_final(writer, result: Mapping[str, Any]) -> None:
    if not isinstance(result, Mapping):
        raise PipelineError(f"returned {type(result).__name__}; "
                            "expected a mapping of arrays (or a generator of chunks)")
    writer.set_attrs(result.get("attrs", {}))
    for name, value in dict(result.get("metrics", {})).items():
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise PipelineError(f"metric '{name}' is not a number: {value!r}") from None
        if math.isnan(value):
            raise PipelineError(f"metric '{name}' is NaN")
        writer.metrics[name] = value
    for name, value in _flatten(dict(result.get("timing", {}))):
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise PipelineError(f"timing '{name}' is not a number: {value!r}") from None
        writer.timing[name] = value if math.isfinite(value) else None
    for name, value in _flatten({k: v for k, v in result.items() if k not in _RESERVED}):
        writer.put(name, value)


def _consume(result: Any, writer) -> None:
    if inspect.isgenerator(result):
        while True:
            try:
                chunk = next(result)
            except StopIteration as stop:
                final = stop.value
                break
            if not isinstance(chunk, Mapping):
                raise PipelineError(f"yielded {type(chunk).__name__}; expected a mapping of arrays")
            for name, value in _flatten(chunk):
                writer.append(name, value)
        _write_final(writer, final or {})
    else:
        _write_final(writer, result)


def _damaged_input(store, task: dict) -> str | None:
    """After a node failed: the one-line error for the first of its inputs whose content is
    damaged (moved aside so that the next run recomputes it), or None if all are intact."""
    for arg, ref in task["inputs"].items():
        for label, key in (ref.items() if isinstance(ref, dict) else [(None, ref)]):
            name = f"input '{arg}{f'[{label}]' if label is not None else ''}' of {task['instance']}"
            try:
                store.check_damage(key, name)
            except PipelineError as exc:
                return str(exc)
    return None


def execute(task: dict) -> dict:
    """Compute one artifact (unless another process already did). Never raises for node errors."""
    for root in task.get("roots", []):
        if root not in sys.path:
            sys.path.insert(0, root)
    from pipeline.artifact import Artifact
    from pipeline.store import Store

    store = Store(task["store"]).init()
    key = task["key"]
    with store.lock(key):
        if not task.get("force"):
            rec = store.record(key)
            if rec is not None:  # another process computed it while we waited
                return {"record": rec, "computed": False}
        t0 = time.time()
        opened: list[Artifact] = []
        writer = None
        try:
            func = _import(task["func"], task.get("roots", []))
            kwargs: dict[str, Any] = dict(task["grid"])
            kwargs.update(task["params"])
            takes = inspect.signature(func).parameters
            checkpoint = store.checkpoint_path(key) if "checkpoint" in takes else None
            if "staging_dir" in takes or checkpoint:  # resumable staging / training
                store.staging.mkdir(exist_ok=True)
            if "staging_dir" in takes:
                kwargs["staging_dir"] = str(store.staging)
            if checkpoint:
                kwargs["checkpoint"] = str(checkpoint)
            if "forced" in takes:       # a source node's --force run: its staging is not this run's
                kwargs["forced"] = bool(task.get("force"))
            published: list = []
            if "after_publish" in takes:
                kwargs["after_publish"] = published.append
            for arg, ref in task["inputs"].items():
                if isinstance(ref, dict):
                    kwargs[arg] = {}
                    for label, k in ref.items():
                        kwargs[arg][label] = store.open(k, f"input '{arg}[{label}]' of {task['instance']}")
                        opened.append(kwargs[arg][label])
                else:
                    kwargs[arg] = store.open(ref, f"input '{arg}' of {task['instance']}")
                    opened.append(kwargs[arg])
            prov = {k: task[k] for k in ("node", "instance", "key", "code", "params", "grid",
                                         "inputs", "input_digests", "engine")}
            prov["setup_seconds"] = time.time() - t0
            writer = store.writer(key, prov)
            context = _import(task["context"], task.get("roots", [])) if task.get("context") else None
            with context() if context else contextlib.nullcontext():
                _consume(func(**kwargs), writer)
            rec = writer.commit(durable=bool(published))
            writer = None
            if checkpoint:
                checkpoint.unlink(missing_ok=True)   # the artifact holds what it was for
            for action in published:
                try:
                    action()
                except Exception as exc:  # noqa: BLE001 - the artifact is safe; say what is left over
                    print(f"pipeline: warning: {task['instance']}: after publishing: "
                          f"{type(exc).__name__}: {exc}", file=sys.stderr)
            return {"record": rec, "computed": True}
        except BaseException as exc:  # report, don't crash the executor
            if writer is not None:
                writer.abort()
            if isinstance(exc, KeyboardInterrupt):
                raise
            from pipeline.space import StoreFull, disk_full
            if not isinstance(exc, PipelineError) and disk_full(exc):  # the node's own files
                exc = StoreFull(store.root, None)
            # errors meant for the user (bad input, a missing device): one line, no traceback
            user = isinstance(exc, PipelineError) or getattr(exc, "user_error", False) is True
            if not user:  # a damaged input (intact size and mtime) is the store's, not the node's
                for a in opened:
                    a.close()
                opened = []
                damaged = _damaged_input(store, task)
                if damaged:
                    return {"error": damaged, "user_error": True, "traceback": ""}
            return {"error": f"{type(exc).__name__}: {exc}" if not user else str(exc),
                    "user_error": user, "traceback": "" if user else traceback.format_exc()}
        finally:
            for a in opened:
                a.close()
