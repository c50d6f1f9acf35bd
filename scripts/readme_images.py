"""Refresh the README's picture (docs/img/translation.png) from a store: a GelSight A-II frame,
its M2M translation into TacTip's style, and TacTip's own frame at the same contact.

    python scripts/readme_images.py [--store artifacts] [--out docs/img]

Run it after `make run` (the default profile).
"""
import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

from store_lookup import artifact_path  # noqa: E402

INSTANCE = "translate[source=gelsight-A-II,target=tactip]"
FIGURE = "figures/examples"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", default="artifacts")
    ap.add_argument("--out", default=str(REPO / "docs" / "img"))
    args = ap.parse_args()
    import numpy as np
    from pipeline.artifact import Artifact
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with Artifact(artifact_path(args.store, INSTANCE, "readme_images")) as art:
        if FIGURE not in art:
            sys.exit(f"readme_images: {INSTANCE} has no {FIGURE}")
        (out / "translation.png").write_bytes(np.asarray(art[FIGURE]).tobytes())
    print(f"{out / 'translation.png'}  <- {INSTANCE} {FIGURE}")


if __name__ == "__main__":
    main()
