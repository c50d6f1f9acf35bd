"""Planning (what is stale and why) and running (in topological order, with early cutoff).

A key is known only once every upstream digest is known, so planning walks the graph in
order: cached upstreams give digests; a stale upstream makes its dependents "stale
because upstream is stale". Running submits ready instances to an executor; after an
upstream re-runs, a dependent whose key is unchanged (same input digests) is a cutoff.
"""
from __future__ import annotations

import sys
from pathlib import Path
from dataclasses import dataclass, field
from typing import Any

from pipeline.errors import NodeFailed, PipelineError
from pipeline.fingerprint import Fingerprinter
from pipeline.graph import Graph, Instance
from pipeline.hashing import ENGINE_VERSION, cache_key, digest_obj
from pipeline.store import Store
from pipeline.worker import execute


@dataclass
class Planned:
    name: str
    status: str                # cached | stale   (after a run: ran | cached | cutoff)
    reason: str = ""
    key: str | None = None
    record: dict | None = None
    seconds: float = 0.0
    parts: dict = field(default_factory=dict)


class Scheduler:
    def __init__(self, graph: Graph, params: dict, store: Store, roots: list[str],
                 node_context: str | None = None):
        self.graph, self.params, self.store = graph, params, store
        self.node_context = node_context     # "module:function": what every node runs inside
        self.roots = [str(r) for r in roots]
        self.instances = graph.expand(params)
        self.fingerprinter = Fingerprinter([Path(r) for r in self.roots])
        self._code: dict[str, str] = {}

    def code(self, inst: Instance) -> str:
        node = inst.node
        if node.name not in self._code:
            if node.source:  # captured data outlives the capture code
                self._code[node.name] = "source"
            elif node.version is not None:
                self._code[node.name] = f"v:{node.version}:{node.func}"
            else:
                self._code[node.name] = self.fingerprinter.fingerprint(node.func)
        return self._code[node.name]

    def targets(self, targets: list[str] | None) -> list[str]:
        return self.graph.select(self.instances, targets)

    def _key(self, inst: Instance, done: dict[str, dict]) -> tuple[str, dict]:
        def pick(field):  # per input: the upstream's field, or {label: field} for a gather
            return {arg: {label: done[n][field] for label, n in ref.items()} if isinstance(ref, dict)
                    else done[ref][field] for arg, ref in inst.inputs.items()}

        digests = pick("digest")
        params = {"params": inst.params, "grid": dict(inst.bindings)}
        code = self.code(inst)
        parts = {"code": code, "params_digest": digest_obj(params), "input_digests": digests,
                 "inputs": pick("key")}
        return cache_key(inst.name, code, params, digests), parts

    def _why(self, inst: Instance, parts: dict) -> str:
        ref = self.store.read_ref(inst.name)
        if ref is None:
            return "missing"
        if ref.get("code") != parts["code"]:
            return "code changed"
        if ref.get("params_digest") != parts["params_digest"]:
            return "params changed"
        old = ref.get("input_digests", {})
        changed = [a for a in parts["input_digests"] if old.get(a) != parts["input_digests"][a]]
        if changed:
            return f"input changed ({', '.join(changed)})"
        return "missing"

    def _lookup(self, key: str, trust: bool = False) -> tuple[dict | None, str]:
        if trust:
            rec = self.store.known_digest(key)
            return rec, "" if rec else "missing"
        if not self.store.path(key).exists():
            return None, "missing"
        rec = self.store.record(key)
        return rec, "" if rec else "corrupt (moved to corrupt/)"

    def plan(self, targets: list[str] | None = None, *, trust: bool = False) -> list[Planned]:
        """What is stale and why.  `trust`: take each artifact's digest from its sealed record
        or the digest its file carries, re-digesting and moving nothing (gc: a damaged upstream
        still gives the keys of what depends on it, which its recomputation would give too)."""
        lookup = (lambda key: self._lookup(key, trust=True)) if trust else self._lookup
        names = self.graph.closure(self.instances, self.targets(targets))
        done: dict[str, dict] = {}
        out = []
        for n in names:
            inst = self.instances[n]
            stale_up = [u for u in inst.upstream() if u not in done]
            if stale_up:
                out.append(Planned(n, "stale", f"upstream stale ({stale_up[0]})"))
                continue
            key, parts = self._key(inst, done)
            rec, problem = lookup(key)
            if rec is not None:
                done[n] = rec
                out.append(Planned(n, "cached", "", key, rec, parts=parts))
            else:
                reason = problem if problem != "missing" else self._why(inst, parts)
                out.append(Planned(n, "stale", reason, key, parts=parts))
        return out

    def _task(self, inst: Instance, key: str, parts: dict, force: bool) -> dict:
        return {"store": str(self.store.root), "key": key, "func": inst.node.func,
                "roots": self.roots, "node": inst.node.name, "instance": inst.name,
                "params": inst.params, "grid": dict(inst.bindings), "inputs": parts["inputs"],
                "input_digests": parts["input_digests"], "code": parts["code"],
                "engine": ENGINE_VERSION, "force": force, "context": self.node_context}

    def run(self, targets: list[str] | None = None, executor=None, *, force: bool = False,
            progress: bool = False, meta: dict | None = None) -> list[Planned]:
        from pipeline.executors import InlineExecutor
        executor = executor or InlineExecutor()
        chosen = self.targets(targets)
        names = self.graph.closure(self.instances, chosen)
        explicit = set(chosen)
        done: dict[str, dict] = {}
        results: dict[str, Planned] = {}
        ran: set[str] = set()
        pending = list(names)
        running: dict[Any, tuple[str, str, dict]] = {}
        failure: tuple[str, dict] | None = None
        bar = _bar(len(names)) if progress else None
        self.store.init()
        depth = chain_lengths(self.instances, names)
        ready: list[tuple[str, str, dict]] = []     # stale instances whose inputs are all done
        slots = getattr(executor, "slots", None)    # tasks the executor runs at once (None: it queues)
        try:
            while ((pending or ready) and failure is None) or running:
                for n in list(pending) if failure is None else []:
                    inst = self.instances[n]
                    if any(u not in done for u in inst.upstream()):
                        continue
                    pending.remove(n)
                    key, parts = self._key(inst, done)
                    rec = None if (force and n in explicit) else self._lookup(key)[0]
                    if rec is not None:
                        done[n] = rec
                        status = "cutoff" if any(u in ran for u in inst.upstream()) else "cached"
                        results[n] = Planned(n, status, "", key, rec, parts=parts)
                        self._ref(n, rec, parts)
                        if bar:
                            bar.update(1)
                        continue
                    if inst.node.source and n not in explicit:
                        raise PipelineError(f"source node {n} has no artifact for these params; "
                                            f"capture it explicitly with `pipeline run '{n}'`")
                    ready.append((n, key, parts))
                # the longest chain of dependents first, so the critical path never waits behind
                # work that could fill a free slot later (ties: plan order)
                ready.sort(key=lambda r: -depth[r[0]])
                while ready and failure is None and (slots is None or len(running) < slots):
                    n, key, parts = ready.pop(0)
                    fut = executor.submit(execute, self._task(self.instances[n], key, parts, force and n in explicit),
                                          priority=depth[n])
                    running[fut] = (n, key, parts)
                if not running:
                    if pending and failure is None:
                        raise PipelineError(f"cannot schedule {pending[0]}: an input is unavailable")
                    break
                for fut in executor.wait(list(running)):
                    n, key, parts = running.pop(fut)
                    out = executor.result(fut)
                    if "error" in out:
                        failure = failure or (n, out)
                        continue
                    rec = out["record"]
                    done[n] = rec
                    if out["computed"]:
                        ran.add(n)
                    status = "ran" if out["computed"] else "cached"
                    seconds = rec.get("seconds", 0.0) if out["computed"] else 0.0
                    results[n] = Planned(n, status, "", key, rec, seconds, parts)
                    self._ref(n, rec, parts, changed=out["computed"])
                    if bar:
                        bar.update(1)
                        bar.set_postfix_str(n, refresh=False)
        finally:
            if bar:
                bar.close()
            if done:
                self.store.log_run([r["key"] for r in done.values()], meta or {})
        if failure:
            n, out = failure
            if out.get("user_error"):   # one line; the worker's messages leave the node to us
                raise PipelineError(f"node {n}: {out['error']}")
            raise NodeFailed(n, out["error"], out.get("traceback", ""))
        return [results[n] for n in names]

    def _ref(self, name: str, rec: dict, parts: dict, changed: bool = False) -> None:
        self.store.write_ref(name, {"key": rec["key"], "digest": rec["digest"], "code": parts["code"],
                                    "params_digest": parts["params_digest"],
                                    "input_digests": parts["input_digests"]}, changed=changed)


def chain_lengths(instances: dict[str, Instance], names: list[str]) -> dict[str, int]:
    """For each of `names` (topologically ordered), how many instances its longest chain of
    dependents among `names` holds, itself included: a sink's is 1."""
    down: dict[str, list[str]] = {n: [] for n in names}
    for n in names:
        for u in instances[n].upstream():
            if u in down:
                down[u].append(n)
    out: dict[str, int] = {}
    for n in reversed(names):
        out[n] = 1 + max((out[d] for d in down[n]), default=0)
    return out


def _bar(total: int):
    if not sys.stderr.isatty():
        return None
    from tqdm import tqdm
    return tqdm(total=total, unit="node", file=sys.stderr, leave=False)
