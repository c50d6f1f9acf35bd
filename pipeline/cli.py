"""The `pipeline` command. Verbs and their --json output are contracts (see README).

Bad input exits 2 with one line on stderr; a failing node exits 1 with its traceback.
Deciding that nothing is stale imports no science: only the graph declaration, params,
the AST of the node functions' modules, and small JSON records.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

from pipeline.errors import NodeFailed, PipelineError


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit 2 (argparse prints usage too)
        raise PipelineError(message)


def _count(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0, got {text!r}") from None
    if n < 0:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0, got {n}")
    return n


def _common(p: argparse.ArgumentParser, *, params: bool = True, targets: bool = False) -> None:
    p.add_argument("--store", help="artifact store directory (default: artifacts/ or $PIPELINE_STORE)")
    if params:
        p.add_argument("--profile", default=None, help="params overlay: params/<NAME>.yaml")
        p.add_argument("-p", "--param", action="append", default=[], metavar="KEY=VALUE",
                       help="override one param (YAML value), repeatable")
    if targets:
        p.add_argument("targets", nargs="*", metavar="TARGET", help="node or node[var=value,...]")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="pipeline", description="Run and inspect the cached pipeline DAG.")
    sub = p.add_subparsers(dest="verb", required=True, parser_class=_Parser)
    r = sub.add_parser("run", help="run what is stale for the targets")
    _common(r, targets=True)
    r.add_argument("--executor", default="inline", choices=["inline", "process", "dask"])
    r.add_argument("--address", default=None, help="Dask scheduler address (tcp://host:port)")
    r.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="parallel workers")
    r.add_argument("--force", action="store_true", help="recompute the targets even if cached")
    r.add_argument("--dry-run", action="store_true", help="say what would run; run nothing")
    r.add_argument("--json", action="store_true")
    s = sub.add_parser("status", help="what is stale and why")
    _common(s, targets=True)
    s.add_argument("--json", action="store_true")
    d = sub.add_parser("dag", help="print the graph")
    _common(d, targets=True)
    g = d.add_mutually_exclusive_group()
    g.add_argument("--dot", action="store_true")
    g.add_argument("--json", action="store_true")
    ls = sub.add_parser("ls", help="list artifacts in the store")
    _common(ls, params=False)
    ls.add_argument("--json", action="store_true")
    sh = sub.add_parser("show", help="datasets, attributes and provenance of an artifact")
    _common(sh)
    sh.add_argument("what", metavar="NODE_OR_KEY")
    sh.add_argument("--json", action="store_true")
    ge = sub.add_parser("get", help="print an artifact's path")
    _common(ge)
    ge.add_argument("what", metavar="NODE")
    v = sub.add_parser("verify", help="re-digest every artifact; exit 1 if any is corrupt")
    _common(v, params=False)
    v.add_argument("--json", action="store_true")
    gc = sub.add_parser("gc", help="remove artifacts no ref or recent run uses")
    _common(gc)
    gc.add_argument("--keep-runs", type=_count, default=5, help="run logs whose artifacts gc keeps (default 5)")
    gc.add_argument("--dry-run", action="store_true")
    dv = sub.add_parser("dvc", help="write dvc.yaml from the DAG")
    _common(dv, params=False)
    dv.add_argument("--check", action="store_true", help="exit 1 if dvc.yaml is out of date")
    m = sub.add_parser("metrics", help="metrics of the current DAG's artifacts")
    _common(m)
    m.add_argument("--json", action="store_true")
    m.add_argument("--baseline", type=Path, help="exit 1 on a regression against this file")
    m.add_argument("--save-baseline", type=Path, help="write current metrics as the baseline")
    m.add_argument("--merge-baseline", type=Path,
                   help="rewrite this baseline keeping, per metric, the worse of its value and the "
                        "current one (a baseline that holds on every machine it was merged on)")
    rp = sub.add_parser("report", help="write the HTML report")
    _common(rp)
    rp.add_argument("--out", type=Path, default=None, help="output folder (default: report/)")
    return p


class Context:
    def __init__(self, args):
        from pipeline.config import find_project
        from pipeline.store import Store
        self.args = args
        self.project = find_project()
        if args.store is not None and not args.store.strip():
            raise PipelineError("--store is empty: name a store directory (default: artifacts/)")
        named = args.store or os.environ.get("PIPELINE_STORE")
        self.store = Store(named or self.project.store_dir)
        if self.store.root.exists() and not self.store.root.is_dir():
            raise PipelineError(f"store {self.store.root} is not a directory")
        if named and args.verb in READS_STORE and not self.store.root.is_dir():  # a typo, not an empty store
            raise PipelineError(f"no store at {self.store.root}: nothing is built there yet "
                                "(`pipeline run` builds it)")

    def scheduler(self):
        from pipeline import params as P
        from pipeline.scheduler import Scheduler
        # verbs without --profile/-p (dvc) see the default profile
        params = P.load(self.project.params_file, getattr(self.args, "profile", None),
                        getattr(self.args, "param", []), self.project.profiles_dir,
                        self.project.ranges_file)
        graph = self.project.load_graph()
        roots = [self.project.root, *self.project.source_roots]
        return Scheduler(graph, params, self.store, list(dict.fromkeys(str(r) for r in roots)),
                         node_context=self.project.node_context)


def _print_json(obj) -> None:
    sys.stdout.write(json.dumps(obj, indent=None) + "\n")


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def cmd_run(ctx: Context) -> int:
    a = ctx.args
    sched = ctx.scheduler()
    t0 = time.time()
    if a.dry_run:
        planned = sched.plan(a.targets)
        if a.json:
            _print_json({"nodes": [{"name": p.name, "key": p.key, "status": p.status, "reason": p.reason,
                                    "seconds": 0.0} for p in planned], "seconds": round(time.time() - t0, 4)})
        else:
            for p in planned:
                print(f"{'would run' if p.status == 'stale' else 'cached':10s} {p.name}"
                      + (f"  ({p.reason})" if p.reason else ""))
        return 0
    from pipeline.executors import make_executor
    executor = make_executor(a.executor, a.jobs, a.address)
    # SIGTERM (a job scheduler's or a machine's time limit) stops a run as Ctrl-C does: the
    # executor's workers are stopped too instead of computing on, orphaned
    main_thread = threading.current_thread() is threading.main_thread()   # signals need it
    previous = signal.signal(signal.SIGTERM, _interrupt) if main_thread else None
    interrupted = False
    try:
        results = sched.run(a.targets, executor, force=a.force, progress=not a.json,
                            meta={"targets": a.targets, "profile": a.profile or "default", "params": a.param})
    except KeyboardInterrupt:
        interrupted = True
        raise
    finally:
        executor.close(interrupted)
        if main_thread:
            signal.signal(signal.SIGTERM, previous)
    total = round(time.time() - t0, 4)
    if a.json:
        _print_json({"nodes": [{"name": r.name, "key": r.key, "status": r.status, "seconds": r.seconds}
                               for r in results], "seconds": total})
    else:
        counts: dict[str, int] = {}
        for r in results:
            counts[r.status] = counts.get(r.status, 0) + 1
            if r.status == "ran":
                print(f"ran     {r.seconds:8.2f}s  {r.name}")
        print(", ".join(f"{v} {k}" for k, v in sorted(counts.items())) + f" in {total:.2f}s")
    return 0


def _other_profile(ctx: Context, planned) -> None:
    """One line when the store's last run used another profile than this command and this
    profile's results are not all built: the results a user looks for are under that one."""
    if all(p.record is not None for p in planned):
        return
    last = ctx.store.last_run()
    mine = getattr(ctx.args, "profile", None) or "default"
    theirs = (last or {}).get("profile") or "default"
    if last is not None and theirs != mine:
        flag = "" if theirs == "default" else f"--profile {theirs}"
        print(f"note: the store's last run used the {theirs} profile, this command the {mine} one; "
              f"pass {flag or 'no --profile'} to see its results", file=sys.stderr)


def cmd_status(ctx: Context) -> int:
    planned = ctx.scheduler().plan(ctx.args.targets)
    _other_profile(ctx, planned)
    if ctx.args.json:
        _print_json({"nodes": [{"name": p.name, "key": p.key, "status": p.status, "reason": p.reason}
                               for p in planned]})
        return 0
    stale = [p for p in planned if p.status == "stale"]
    for p in planned:
        print(f"{p.status:7s} {p.name}" + (f"  ({p.reason})" if p.reason else ""))
    print(f"{len(stale)} stale, {len(planned) - len(stale)} cached")
    return 0


def cmd_dag(ctx: Context) -> int:
    sched = ctx.scheduler()
    names = sched.graph.closure(sched.instances, sched.targets(ctx.args.targets))
    edges = [(u, n) for n in names for u in sched.instances[n].upstream()]
    if ctx.args.json:
        _print_json({"nodes": [{"name": n, "node": sched.instances[n].node.name,
                                "func": sched.instances[n].node.func,
                                "params": sched.instances[n].param_keys,
                                "inputs": sched.instances[n].inputs} for n in names],
                     "edges": [list(e) for e in edges]})
    elif ctx.args.dot:
        print("digraph pipeline {\n  rankdir=LR;\n  node [shape=box];")
        for n in names:
            print(f'  "{n}";')
        for u, n in edges:
            print(f'  "{u}" -> "{n}";')
        print("}")
    else:
        for n in names:
            ups = sched.instances[n].upstream()
            print(n + (f"  <- {', '.join(ups)}" if ups else ""))
    return 0


def cmd_ls(ctx: Context) -> int:
    recs = ctx.store.records()
    rows = [{"name": r.get("instance"), "node": r.get("node"), "key": r["key"],
             "path": str(ctx.store.root / r["path"]), "bytes": r.get("bytes"), "created": r.get("created")}
            for r in recs]
    if ctx.args.json:
        _print_json(rows)
    else:
        for r in rows:
            print(f"{r['key'][:12]}  {r['created']}  {r['bytes']:>12,}  {r['name']}")
    return 0


def _resolve(ctx: Context, what: str) -> dict:
    """A record from a node/instance selector (current params) or a key prefix."""
    from pipeline.graph import parse_selector
    try:
        node, _ = parse_selector(what)
    except PipelineError:
        node = None
    sched = ctx.scheduler()
    if node is not None and node in sched.graph.nodes:
        chosen = sched.targets([what])
        if len(chosen) > 1:
            raise PipelineError(f"'{what}' names {len(chosen)} instances; pick one: {', '.join(chosen[:5])}")
        p = [x for x in sched.plan(chosen) if x.name == chosen[0]][0]
        if p.record is None:
            raise PipelineError(f"{p.name} is not built ({p.reason}); run `pipeline run '{p.name}'`")
        return p.record
    return ctx.store.find(what)


def cmd_show(ctx: Context) -> int:
    rec = _resolve(ctx, ctx.args.what)
    try:
        with ctx.store.open(rec["key"], rec.get("instance") or rec["key"]) as a:
            info = {"name": rec.get("instance"), "key": rec["key"], "path": str(a.path),
                    "datasets": {n: {"shape": list(a[n].shape), "dtype": str(a[n].dtype)} for n in a},
                    "attrs": a.attrs, "provenance": a.provenance}
    except PipelineError:
        raise
    except Exception:  # unreadable though its size and mtime match its record: check content
        ctx.store.check_damage(rec["key"], rec.get("instance") or rec["key"])
        raise
    if ctx.args.json:
        _print_json(info)
        return 0
    print(f"{info['name']}  key {info['key']}\n{info['path']}\ndatasets:")
    for n, d in info["datasets"].items():
        print(f"  {n:30s} {d['dtype']:10s} {tuple(d['shape'])}")
    if info["attrs"]:
        print("attributes:")
        for k, v in info["attrs"].items():
            print(f"  {k} = {v!r}")
    print("provenance:")
    for k, v in info["provenance"].items():
        print(f"  {k} = {json.dumps(v) if isinstance(v, (dict, list)) else v}")
    return 0


def cmd_get(ctx: Context) -> int:
    rec = _resolve(ctx, ctx.args.what)
    print(ctx.store.path(rec["key"]))
    return 0


def cmd_verify(ctx: Context) -> int:
    bar = None
    if sys.stderr.isatty() and not ctx.args.json:
        from tqdm import tqdm
        bar = lambda it: tqdm(it, unit="artifact", file=sys.stderr, leave=False)  # noqa: E731
    bad = ctx.store.verify(bar)
    for what, _ in bad:  # the next run rebuilds these records from content (and recomputes
        # corrupt artifacts); damaged refs are rewritten by the next run, run logs are the user's
        if "/" not in what:
            (ctx.store.index / f"{what}.json").unlink(missing_ok=True)
        elif what.startswith("index/"):
            (ctx.store.root / what).unlink(missing_ok=True)
    n = len(ctx.store.object_paths())
    if ctx.args.json:
        _print_json({"checked": n, "corrupt": [{"file" if "/" in w else "key": w, "problem": m}
                                               for w, m in bad]})
    else:
        for w, m in bad:
            print(f"corrupt {w}: {m}")
        print(f"{n} artifacts checked (and their records, refs and run logs), {len(bad)} corrupt")
    return 1 if bad else 0


def cmd_gc(ctx: Context) -> int:
    sched = ctx.scheduler()
    plan = sched.plan(trust=True)   # judges nothing: a damaged upstream keeps its dependents' keys
    keep = {p.key for p in plan if p.key is not None}
    removed = ctx.store.gc(keep, dry_run=ctx.args.dry_run, keep_runs=ctx.args.keep_runs)
    verb = "would remove" if ctx.args.dry_run else "removed"
    for k in removed:
        print(f"{verb} {k}")
    # a checkpoint of a key the current params no longer plan can never be resumed
    orphans = ctx.store.orphan_checkpoints({p.key for p in plan})
    for path in orphans:
        if not ctx.args.dry_run:
            path.unlink(missing_ok=True)
        print(f"{verb} staging/{path.name}")
    print(f"{len(removed)} artifacts {'to remove' if ctx.args.dry_run else 'removed'}"
          + (f", {len(orphans)} checkpoints" if orphans else ""))
    return 0


def cmd_dvc(ctx: Context) -> int:
    from pipeline import dvc
    text = dvc.export(ctx.scheduler(), ctx.project)
    path = ctx.project.root / "dvc.yaml"
    if ctx.args.check:
        current = path.read_text() if path.exists() else ""
        if current != text:
            print(f"{path} is out of date: run `pipeline dvc`", file=sys.stderr)
            return 1
        print(f"{path} is up to date")
        return 0
    path.write_text(text)
    print(path)
    return 0


def cmd_metrics(ctx: Context) -> int:
    from pipeline import metrics as M
    planned = ctx.scheduler().plan()
    _other_profile(ctx, planned)
    stale = [p.name for p in planned if p.record is None]
    if stale:
        print(f"warning: {len(stale)} nodes are not built (e.g. {stale[0]}); "
              "their metrics are missing", file=sys.stderr)
    current = M.collect(planned)
    if ctx.args.save_baseline:
        M.save_baseline(ctx.args.save_baseline, current)
        print(f"wrote {len(current)} metrics to {ctx.args.save_baseline}", file=sys.stderr)
    if ctx.args.merge_baseline:
        merged = M.merged_worse(M.load_baseline(ctx.args.merge_baseline)["metrics"], current)
        M.save_baseline(ctx.args.merge_baseline, merged)
        print(f"merged {len(current)} metrics into {ctx.args.merge_baseline}", file=sys.stderr)
    if ctx.args.json:
        _print_json(current)
    elif not ctx.args.baseline:
        for k, v in current.items():
            print(f"{k:60s} {v:.6g}")
    if ctx.args.baseline:
        rows = M.compare(current, M.load_baseline(ctx.args.baseline))
        bad = [r for r in rows if r["regression"]]
        out = sys.stderr if ctx.args.json else sys.stdout
        for r in rows:
            cur = "missing" if r["current"] is None else f"{r['current']:.6g}"
            flag = "REGRESSION" if r["regression"] else "ok"
            print(f"{flag:10s} {r['metric']:55s} {r['baseline']:.6g} -> {cur} (allowed {r['allowed']:.3g})",
                  file=out)
        print(f"{len(bad)} regressions in {len(rows)} metrics", file=out)
        return 1 if bad else 0
    return 0


def cmd_report(ctx: Context) -> int:
    from pipeline import report
    sched = ctx.scheduler()
    planned = sched.plan()
    # an on-demand node (the ablation) is shown once it is built and current
    have = {p.name for p in planned}
    extra = [n for n, i in sched.instances.items() if i.node.on_demand and i.problem is None and n not in have]
    if extra:
        planned += [p for p in sched.plan(extra) if p.name in extra and p.status == "cached"]
    _other_profile(ctx, planned)
    out = ctx.args.out or ctx.project.root / "report"
    print(report.write(planned, ctx.store, out, info={"profile": ctx.args.profile or "default"}))
    return 0


# verbs that only read what is built: a named store that does not exist is a typo
READS_STORE = {"ls", "show", "get", "verify", "gc", "metrics", "report"}

VERBS = {"run": cmd_run, "status": cmd_status, "dag": cmd_dag, "ls": cmd_ls, "show": cmd_show,
         "get": cmd_get, "verify": cmd_verify, "gc": cmd_gc, "dvc": cmd_dvc, "metrics": cmd_metrics,
         "report": cmd_report}


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
        return VERBS[args.verb](Context(args))
    except PipelineError as exc:
        print(f"pipeline: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except NodeFailed as exc:
        if exc.traceback_text:
            sys.stderr.write(exc.traceback_text)
        print(f"pipeline: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("pipeline: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `pipeline ls | head`
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as exc:  # the store or an output folder: read-only, full, vanished
        from pipeline.space import StoreFull, disk_full
        if disk_full(exc):
            print(f"pipeline: error: {StoreFull(Path(exc.filename or '.'), None)}", file=sys.stderr)
            return 2
        what = f" {exc.filename}" if exc.filename else ""
        print(f"pipeline: error: cannot use{what}: {exc.strerror or exc}", file=sys.stderr)
        return 2


def entry() -> None:
    sys.exit(main())
