"""Refresh the README's pictures (docs/img) from a store: figures of a few artifacts and a
screenshot of the report's first screen.

    python scripts/readme_images.py [--store artifacts] [--out docs/img]

Run it after `make run` (the default profile) and `pipeline report`; the screenshot needs
Chromium (`scripts/setup.sh --test` installs it) and is skipped without it.
"""
import argparse
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests" / "pipeline"))
sys.path.insert(0, str(REPO / "scripts"))

from store_lookup import artifact_path  # noqa: E402

# README picture -> (node instance, figure)
FIGURES = {
    "render-gelsight.png": ("render[skin=gelsight-A-II]", "frames"),
    "markers-tactip.png": ("markers[skin=tactip]", "examples"),
    "markers-uskin.png": ("markers[skin=uskin-3axis]", "examples"),
    "sim-m2m-fid.png": ("sim_m2m", "fid"),
    "homo-radar.png": ("homo", "force_radar"),
    "homo-seen.png": ("homo", "force_seen_unseen"),
    "material-trace.png": ("material", "force_trace"),
    "hetero-radar.png": ("hetero", "force_radar"),
    "control-grasp.png": ("control", "grasp_plum"),
}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", default="artifacts")
    ap.add_argument("--out", default=str(REPO / "docs" / "img"))
    ap.add_argument("--report", default=str(REPO / "report" / "index.html"))
    args = ap.parse_args()
    import numpy as np
    from pipeline.artifact import Artifact
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name, (instance, figure) in FIGURES.items():
        art = Artifact(artifact_path(args.store, instance, "readme_images"))
        key = f"figures/{figure}"
        if key not in art:
            sys.exit(f"readme_images: {instance} has no {key}")
        (out / name).write_bytes(np.asarray(art[key]).tobytes())
        print(f"{out / name}  <- {instance} {key}")
    report = Path(args.report)
    from browser import Browser, find_chromium
    binary = find_chromium()
    if not report.exists() or binary is None:
        print(f"no screenshot: {'no ' + str(report) if not report.exists() else 'no chromium'}")
        return
    with tempfile.TemporaryDirectory() as tmp, Browser.launch(binary, Path(tmp) / "profile") as browser:
        page = browser.open(report.resolve().as_uri())
        page.screenshot(out / "report.png", max_height=900)
    print(f"{out / 'report.png'}  <- {report}")


if __name__ == "__main__":
    main()
