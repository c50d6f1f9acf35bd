"""Compare values of one param on the validation split: build the studies once per value and
print each method's validation means side by side (never the test split's).

    python scripts/choose.py KEY VALUE [VALUE ...] [--store artifacts] [--profile NAME]
                             [--targets homo material hetero] [--json OUT]

e.g. `python scripts/choose.py force.config.seq_len 12 24` (`-p KEY=VALUE` for each).  Every
value shares the store, so only what a value changes is recomputed; the current run is left
at the last value given, so a plain `pipeline run` afterwards restores the profile's.
Printed per value: `<study>_val/mean/<method>/mae_total` of every method beside its seed
spread (`..._sd`: a value wins only beyond it) and the study's validation FID of the M2M translations (`<study>_val/mean/m2m/fid`).

With `--images` (for M2M's own params): builds only the translations and the skins' features,
and prints the mean validation FID of the translations into each target over the `translate`
pairs (`translate_val/mean/m2m/fid`) and the `translate_sim` pairs
(`translate_sim_val/mean/m2m/fid`), M2M's own objective, without training a regressor.
"""
import argparse
import functools
import json
import os
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from store_lookup import REPO, artifact_path  # noqa: E402

METHODS = ("source_only", "genforce", "genforce_comp", "genforce_plus", "oracle")


def _pipeline(*args: str) -> subprocess.CompletedProcess:
    p = subprocess.run([sys.executable, "-m", "pipeline", *args], cwd=REPO, capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(REPO)})
    if p.returncode:
        sys.exit(f"choose: pipeline {' '.join(args)}: {(p.stderr or p.stdout).strip().splitlines()[-1]}")
    return p


def validation(metrics: dict, targets) -> dict:
    """The validation means this script prints, by name."""
    out = {}
    for study in targets:
        for m in METHODS:
            k = f"{study}_val/mean/{m}/mae_total"
            for name in (k, f"{k}_sd"):          # the mean over the regressor seeds, its spread
                if name in metrics:
                    out[name] = metrics[name]
        k = f"{study}_val/mean/m2m/fid"
        if k in metrics:
            out[k] = metrics[k]
    return out


def image_validation(store: str, common: list[str], params: tuple[str, ...], profile: str | None) -> dict:
    """Mean validation FID of the built translate and translate_sim artifacts against their
    targets' features (stages.imagemetrics.fid on the `features_val` sets); each artifact found
    through store_lookup.artifact_path, as `pipeline get` finds it."""
    sys.path.insert(0, str(REPO))
    import numpy as np
    from pipeline.artifact import Artifact
    from stages.imagemetrics import fid
    nodes = json.loads(_pipeline("status", "--json", *common, "translate", "translate_sim").stdout
                       .strip().splitlines()[-1])["nodes"]

    @functools.cache                     # a target's features serve every pair into it
    def val_features(name):
        with Artifact(artifact_path(store, name, "choose", params, profile)) as art:
            return np.asarray(art["features_val"])
    out = {}
    for family in ("translate", "translate_sim"):
        fids = []
        for name in sorted(n["name"] for n in nodes if n["name"].startswith(family + "[")):
            target = name.split("target=", 1)[1].rstrip("]")
            fids.append(fid(val_features(name), val_features(f"features[skin={target}]")))
        if fids:
            out[f"{family}_val/mean/m2m/fid"] = float(np.mean(fids))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("key")
    ap.add_argument("values", nargs="+")
    ap.add_argument("--store", default=str(REPO / "artifacts"))
    ap.add_argument("--profile", default=None)
    ap.add_argument("--targets", nargs="+", default=["homo", "material", "hetero"])
    ap.add_argument("--images", action="store_true", help="M2M's params: the translations' validation FID alone")
    ap.add_argument("--json", default=None, help="also write the table here")
    args = ap.parse_args()
    prof = ["--profile", args.profile] if args.profile else []
    table = {}
    for value in args.values:
        common = ["--store", args.store, *prof, "-p", f"{args.key}={value}"]
        targets = ["translate", "translate_sim", "features"] if args.images else args.targets
        print(f"choose: {args.key}={value}: pipeline run {' '.join(targets)}", file=sys.stderr, flush=True)
        _pipeline("run", "--executor", "process", *common, *targets)
        if args.images:
            table[value] = image_validation(args.store, common, (f"{args.key}={value}",), args.profile)
        else:
            metrics = json.loads(_pipeline("metrics", "--json", *common).stdout.strip().splitlines()[-1])
            table[value] = validation(metrics, args.targets)
    names = sorted({k for row in table.values() for k in row})
    print(f"{'validation metric':44s}" + "".join(f"{args.key.split('.')[-1] + '=' + v:>18s}" for v in args.values))
    for k in names:
        print(f"{k:44s}" + "".join(f"{table[v].get(k, float('nan')):18.4g}" for v in args.values))
    if args.json:
        Path(args.json).write_text(json.dumps({"key": args.key, "validation": table}, indent=1))


if __name__ == "__main__":
    main()
