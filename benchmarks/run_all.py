"""Run every benchmark, then print one table of the figures they recorded.

Run: python benchmarks/run_all.py [--quick] [NAME ...]   (`make bench`; NAME: e.g. engine render;
gpu, the GPU against the CPU at the paper's sizes, runs by default only where torch sees a GPU)

Each script runs as a subprocess, in order, its own output streamed as it comes; `--quick` is
passed on to the scripts that take it.  Each script records its ratios and targeted figures
through benchmarks/summary.py into a JSON-lines file named by BENCH_SUMMARY.  The table:
benchmark | figure | measured | ratio | target | pass? (pass when the target reads ">= x" or
"<= x"); then each script's wall time.  A failed script is listed as FAILED with its exit code,
and run_all exits 1 after printing everything.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
BENCHMARKS = ("engine", "contact", "render", "m2m", "force", "capture", "ingest", "control", "gpu",
              "pipeline_time")
ONLY_WITH_CUDA = ("gpu",)     # left out of the default list where torch sees no GPU
TARGET = re.compile(r"^\s*(>=|<=)\s*([-+0-9.eE]+)\s*$")


def cuda_present() -> bool:
    import torch
    return torch.cuda.is_available()


def takes_quick(script: Path) -> bool:
    """Whether the script declares a --quick option."""
    return '"--quick"' in script.read_text()


def meets(ratio: float | None, target: str) -> str:
    """"yes"/"NO" for a ">= x" / "<= x" target, "" for any other target or no ratio."""
    m = TARGET.match(target or "")
    if not m or ratio is None or math.isnan(ratio):
        return ""
    op, bound = m.group(1), float(m.group(2))
    return "yes" if (ratio >= bound if op == ">=" else ratio <= bound) else "NO"


def fmt(ratio: float | None) -> str:
    """A ratio with about three significant figures, "" when there is none."""
    if ratio is None:
        return ""
    a = abs(ratio)
    if a != 0 and (a < 1e-3 or a >= 1e5):
        return f"{ratio:.2e}"
    return f"{ratio:.3f}" if a < 10 else f"{ratio:.1f}" if a < 1000 else f"{ratio:.0f}"


def table(rows: list[list[str]], head: list[str]) -> str:
    """Rows aligned under `head`, the fourth column (ratio) right-aligned."""
    widths = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]
    right = {3}                                                  # the ratio column
    line = lambda r: "  ".join(c.rjust(w) if i in right else c.ljust(w)
                               for i, (c, w) in enumerate(zip(r, widths))).rstrip()
    return "\n".join([line(head), line(["-" * w for w in widths])] + [line(r) for r in rows])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="pass --quick to the scripts that take it")
    ap.add_argument("names", nargs="*", metavar="NAME",
                    help=f"benchmarks to run (default all: {' '.join(BENCHMARKS)})")
    args = ap.parse_args()
    unknown = [n for n in args.names if n not in BENCHMARKS]
    if unknown:
        ap.error(f"unknown benchmark {unknown[0]!r}; choose from {', '.join(BENCHMARKS)}")
    names = args.names or [n for n in BENCHMARKS if n not in ONLY_WITH_CUDA or cuda_present()]
    rows, walls, failed = [], [], False
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            script = HERE / f"{name}.py"
            summary = Path(tmp) / f"{name}.jsonl"
            cmd = [sys.executable, str(script)] + (["--quick"] if args.quick and takes_quick(script) else [])
            print(f"\n===== {name}: {' '.join([f'benchmarks/{name}.py', *cmd[2:]])}", flush=True)
            env = {**os.environ, "BENCH_SUMMARY": str(summary), "PYTHONUNBUFFERED": "1"}
            t = time.perf_counter()
            code = subprocess.run(cmd, env=env).returncode
            wall = time.perf_counter() - t
            print(f"===== {name}: {wall:.1f} s, exit {code}", flush=True)
            walls.append([name, f"{wall:.1f}", "ok" if code == 0 else f"FAILED (exit {code})"])
            recorded = [json.loads(line) for line in summary.read_text().splitlines()] if summary.exists() else []
            for r in recorded:
                rows.append([r["bench"], r["name"], r["measured"], fmt(r["ratio"]), r["target"],
                             meets(r["ratio"], r["target"])])
            if code != 0:
                failed = True
                rows.append([name, f"FAILED (exit {code})", "", "", "", "NO"])
    print(f"\n===== summary{' (--quick)' if args.quick else ''}")
    print(table(rows, ["benchmark", "figure", "measured", "ratio", "target", "pass?"]))
    print()
    print(table([[n, w.rjust(7), s] for n, w, s in walls], ["script", "wall s", "status"]))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
