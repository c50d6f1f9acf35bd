"""Where the main job's time goes: seconds per node family of a built store, beside its budget.

Run: python benchmarks/pipeline_time.py [--store artifacts] [--profile NAME] [--budget-min 30]

Reads the plan of `pipeline run` (every default target) with `--dry-run --json`, and each
planned artifact's record in the store (`index/<key>.json`: the seconds its node took and when
it was made).  Prints per node family the instances, the compute seconds (summed over
instances: what 2 cores share) and their share; then the run's wall time (first start to last
finish of the planned artifacts) against the budget.  The store must hold the whole plan:
build it first with the README's `make run` (an artifact not built shows as missing).
"""
import argparse
import json
import os
import subprocess
import sys
from collections import defaultdict
from datetime import datetime, timedelta
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.summary import record  # noqa: E402


def plan(store: str, profile: str | None) -> list[dict]:
    args = [sys.executable, "-m", "pipeline", "run", "--dry-run", "--json", "--store", store]
    args += ["--profile", profile] if profile else []
    out = subprocess.run(args, cwd=REPO, capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(REPO)})
    if out.returncode:
        sys.exit(f"pipeline_time: {out.stderr.strip() or out.stdout.strip()}")
    return json.loads(out.stdout.strip().splitlines()[-1])["nodes"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", default=str(REPO / "artifacts"))
    ap.add_argument("--profile", default=None)
    ap.add_argument("--budget-min", type=float, default=30.0, help="the profile's budget, minutes")
    args = ap.parse_args()
    nodes = plan(args.store, args.profile)
    families: dict[str, list[float]] = defaultdict(list)
    starts, ends, missing = [], [], []
    for n in nodes:
        path = Path(args.store) / "index" / f"{n['key']}.json"
        if n["status"] != "cached" or not path.is_file():
            missing.append(n["name"])
            continue
        rec = json.loads(path.read_text())
        seconds = float(rec.get("seconds") or 0.0)
        families[n["name"].split("[", 1)[0]].append(seconds)
        end = datetime.strptime(rec["created"], "%Y-%m-%dT%H:%M:%SZ")
        starts.append(end - timedelta(seconds=seconds))
        ends.append(end)
    total = sum(sum(v) for v in families.values())
    print(f"{'node family':24s} {'instances':>9s} {'compute s':>10s} {'share':>7s}")
    for family, secs in sorted(families.items(), key=lambda kv: -sum(kv[1])):
        print(f"{family:24s} {len(secs):9d} {sum(secs):10.0f} {sum(secs) / max(total, 1e-9):7.1%}")
    print(f"{'all':24s} {sum(map(len, families.values())):9d} {total:10.0f}")
    if missing:
        print(f"not built in {args.store}: {len(missing)} of {len(nodes)} ({', '.join(missing[:5])}"
              f"{' ...' if len(missing) > 5 else ''})")
    if starts:
        wall = (max(ends) - min(starts)).total_seconds() / 60
        print(f"wall time (first start to last finish): {wall:.1f} min; budget {args.budget_min:.0f} min; "
              f"ratio {wall / args.budget_min:.2f}")
        record("pipeline", f"main job ({args.profile or 'default'} profile) vs its budget",
               f"{wall:.1f} min", wall / args.budget_min, "<= 1")


if __name__ == "__main__":
    main()
