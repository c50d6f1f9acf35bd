"""Can M2M tell skins of one marker layout apart?  (README, the elastomers' M2M FID.)

    python scripts/elastomer_m2m.py [--store artifacts] [--skins gelsight-r6 gelsight-r10 gelsight-r18]
                                    [--frames 200]

The generator knows a target only by its reference image.  For every skin as the source, its
test frames (the unseen indenters, `--frames` of them evenly spaced) are translated by the
fine-tuned model (`m2m`) into every skin, and the script prints, in pixels a frame that
differ: the translations into two skins against each other, the two skins' own
location-paired frames against each other, each translation against its target's own frame,
and the untranslated source against it.  Translations that differ far less than the targets
do mean the model does not know which skin it draws.
"""
import argparse
import sys
from itertools import combinations
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

from pipeline.artifact import Artifact  # noqa: E402
from stages.force.nodes import contact_runs  # noqa: E402
from store_lookup import artifact_path  # noqa: E402

TOOL = "elastomer_m2m"


def differing(a: np.ndarray, b: np.ndarray) -> float:
    """Mean count of pixels a frame that differ between two (N,H,W) image stacks."""
    return float((a != b).sum((1, 2)).mean())


def paired_frames(markers: dict, rows: np.ndarray) -> dict:
    """Every skin's images at the location-paired frames of `rows` of the first skin."""
    first = next(iter(markers))
    want = np.asarray(markers[first]["frame"])[rows]
    out = {}
    for skin, art in markers.items():
        frame = np.asarray(art["frame"])
        index = {int(f): i for i, f in enumerate(frame)}
        missing = [int(f) for f in want if int(f) not in index]
        if missing:
            sys.exit(f"{TOOL}: {skin} lacks {len(missing)} of {first}'s test frames (not location-paired)")
        out[skin] = np.stack([np.asarray(art["images"][index[int(f)]]) for f in want])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--store", default="artifacts")
    ap.add_argument("--skins", nargs="+", default=["gelsight-r6", "gelsight-r10", "gelsight-r18"])
    ap.add_argument("--frames", type=int, default=200)
    args = ap.parse_args()
    if args.frames < 1 or len(args.skins) < 2:
        sys.exit(f"{TOOL}: --frames must be at least 1 and --skins name at least two skins")
    from stages.m2m.model import load_translator
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    get = lambda inst: Artifact(artifact_path(args.store, inst, TOOL))  # noqa: E731
    translator = load_translator(get("m2m"))
    markers = {s: get(f"markers[skin={s}]") for s in args.skins}
    first = markers[args.skins[0]]
    rows = np.concatenate([np.arange(a, b) for a, b in contact_runs(first, params["splits"]["test_indenters"])])
    rows = rows[np.unique(np.linspace(0, rows.size - 1, min(args.frames, rows.size)).round().astype(int))]
    images = paired_frames(markers, rows)
    refs = {s: np.asarray(art["reference"]) for s, art in markers.items()}
    print(f"{rows.size} test frames; reference pixels that differ: "
          + ", ".join(f"{a} vs {b} {int((refs[a] != refs[b]).sum())}" for a, b in combinations(args.skins, 2)))
    for source in args.skins:
        out = {t: translator.translate(images[source], refs[source], refs[t]) for t in args.skins}
        print(f"source {source}:")
        for a, b in combinations(args.skins, 2):
            print(f"  into {a} vs into {b}: {differing(out[a], out[b]):6.1f} px   "
                  f"({a} vs {b} themselves: {differing(images[a], images[b]):6.1f})")
        for t in args.skins:
            print(f"  into {t} vs {t}'s own frames: {differing(out[t], images[t]):6.1f} px   "
                  f"(untranslated: {differing(images[source], images[t]):6.1f})")


if __name__ == "__main__":
    main()
