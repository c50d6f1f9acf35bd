"""Write the ci profile's regression baseline (baselines/ci.yaml) from measured noise.

    python scripts/ci_baseline.py [--seeds 5] [--k 8] [--store artifacts-ci] [--out baselines/ci.yaml]

Runs the ci DAG once per seed (every learned node's seed: M2M's, and the force regressors' seed
list shifted along; the twin is shared, so it is built once) and once more at seed 0 with the
CPU kernels restricted as another machine would choose them (`RESTRICTED`: torch's and
oneDNN's AVX2 kernels and OpenCV's without AVX2/AVX-512, in a store of its own, so that every
node is recomputed).  Each metric's baseline
is the value the ci DAG gives at its own seeds (what CI computes), and its `spread` the
standard deviation over all those runs; `pipeline metrics --baseline` allows a metric to be
worse by k standard deviations.  Another machine's kernels move a learned metric by a
ten-thousandth of its seed spread (the twin's content being the same bit for bit), so the gate
holds on any x86-64 machine, and a change that trains worse by a few seeds' spread fails it.  A
metric the runs agree on exactly (the twin's) is allowed no change.  Stores are kept, so a
second run reuses every seed built before.

`make baseline` runs it with the defaults.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
SEED_KEYS = ("m2m.pretrain.seed", "m2m.finetune.seed")   # and force.seeds, shifted (seed_overrides)
# the kernel choices of a CPU without AVX-512 (torch's own kernels and oneDNN's, whose
# convolutions compute the InceptionV3 features and the networks) and without AVX2 (OpenCV's)
RESTRICTED = {"ATEN_CPU_CAPABILITY": "avx2", "DNNL_MAX_CPU_ISA": "AVX2",
              "OPENCV_CPU_DISABLE": "AVX512-SKX,AVX2"}
HEADER = """\
# Metric regression baseline of the ci profile (tiny sizes, a few training steps), written by
# `make baseline` (scripts/ci_baseline.py): each metric as the ci DAG gives it, and in `spread`
# its standard deviation over {runs} runs ({seeds} seeds of every learned node, and seed 0 again
# with {restricted}).
# tests/test_project.py fails when a metric is worse by more than k standard deviations; a
# metric on which every run agreed (the twin's: bit for bit on any x86-64 machine) may not change.
"""


def pipeline(*args: str, env: dict | None = None) -> str:
    p = subprocess.run([sys.executable, "-m", "pipeline", *args], cwd=ROOT, capture_output=True,
                       text=True, env={**os.environ, **(env or {})})
    if p.returncode:
        sys.exit(f"ci_baseline: pipeline {' '.join(args)} failed:\n{p.stderr[-3000:]}")
    return p.stdout


def seed_overrides(seed: int) -> list[str]:
    """-p arguments for run `seed`: M2M's seeds set to it, the ci profile's n regressor seeds
    (force.seeds) shifted to the n after the n * seed first (run 0: the profile's own)."""
    from pipeline import params as P
    from pipeline.config import find_project
    project = find_project(ROOT)
    ci = P.load(project.params_file, "ci", [], project.profiles_dir)["force"]["seeds"]
    shifted = [int(v) + seed * len(ci) for v in ci]
    return [a for key in SEED_KEYS for a in ("-p", f"{key}={seed}")] + ["-p", f"force.seeds={shifted}"]


def run(store: Path, seed: int, env: dict | None = None) -> dict[str, float]:
    """The ci DAG's metrics at one seed of every learned node."""
    over = seed_overrides(seed)
    pipeline("run", "--profile", "ci", "--executor", "process", "--store", str(store), *over, env=env)
    return json.loads(pipeline("metrics", "--profile", "ci", "--store", str(store), "--json", *over, env=env))


def summarise(runs: list[dict[str, float]]) -> tuple[dict[str, float], dict[str, float]]:
    """(the first run's value, the sample standard deviation over all runs) of each metric
    that every run reports as a finite number."""
    base, spread = {}, {}
    names = sorted(set.intersection(*(set(r) for r in runs)))
    for name in names:
        values = [r[name] for r in runs]
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
            continue
        base[name] = float(values[0])
        if max(values) == min(values):
            spread[name] = 0.0
            continue
        mean = math.fsum(values) / len(values)
        spread[name] = math.sqrt(math.fsum((v - mean) ** 2 for v in values) / (len(values) - 1))
    return base, spread


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=5, help="seeds of the learned nodes (>= 2)")
    ap.add_argument("--k", type=float, default=4.0, help="standard deviations a metric may be worse by")
    ap.add_argument("--store", type=Path, default=ROOT / "artifacts-ci")
    ap.add_argument("--out", type=Path, default=ROOT / "baselines" / "ci.yaml")
    args = ap.parse_args(argv)
    if args.seeds < 2:
        ap.error("--seeds must be at least 2")
    runs = []
    for seed in range(args.seeds):
        print(f"ci_baseline: seed {seed}", file=sys.stderr, flush=True)
        runs.append(run(args.store, seed))
    print("ci_baseline: seed 0, restricted CPU kernels", file=sys.stderr, flush=True)
    runs.append(run(args.store.with_name(args.store.name + "-restricted"), 0, RESTRICTED))
    base, spread = summarise(runs)
    restricted = ", ".join(f"{k}={v}" for k, v in RESTRICTED.items())
    head = HEADER.format(runs=len(runs), seeds=args.seeds, restricted=restricted)
    body = yaml.safe_dump({"k": args.k, "metrics": base, "spread": spread}, sort_keys=False)
    args.out.write_text(head + body)
    noisy = sum(v > 0 for v in spread.values())
    print(f"ci_baseline: wrote {len(base)} metrics ({noisy} with a spread) to {args.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
