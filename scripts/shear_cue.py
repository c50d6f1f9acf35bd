"""How a taxel skin's marker images carry shear, in its twin and in M2M's translations into it.

    python scripts/shear_cue.py [--store artifacts] [--target uskin-z] [--source gelsight-A-II ...]

For every frame with a contact, the centroid of the pixels the contact turned on (image minus
reference) is taken relative to its contact's mean centroid, and correlated with the frame's
shear force (x with Fx, y with Fy); so is the centroid of the pixels it turned off (dots
shrunk below their rest size, which a z-only skin draws when its min_area is below its
base_area); the dots' mean motion (their centroids against the reference's, per 4x4 cell) is
regressed on Fx.  On the 3-axis uSkin the dots move with the shear.  On the z-only uSkin they
cannot move: a sheared pad sinks behind the contact and rises before it (Cerruti's solution,
(1 - 2 nu) of the normal response), so the growth centroid runs against the shear and the
shrink centroid with it.  A translation that draws either with the wrong sign, or moves
z-only dots, teaches the transferred regressor a wrong shear cue.
"""
import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

from pipeline.artifact import Artifact  # noqa: E402
from stages.force.nodes import contact_runs  # noqa: E402
from store_lookup import artifact_path  # noqa: E402


def _corr(a, b) -> float:
    return float(np.corrcoef(a, b)[0, 1]) if a.std() > 0 and b.std() > 0 else float("nan")


def cue(art, max_contacts: int = 400) -> dict:
    runs = contact_runs(art, None)[:max_contacts]
    ref = np.asarray(art["reference"], float)
    force = np.asarray(art["force"], float)
    h, w = ref.shape
    cell = (np.arange(h)[:, None] * 4 // h) * 4 + (np.arange(w)[None] * 4 // w)
    yy, xx = np.mgrid[:h, :w]
    masks = [cell == c for c in range(16)]

    def dot_centres(im):
        out = []
        for m in masks:
            v = im * m
            s = v.sum() + 1e-9
            out.append(((v * xx).sum() / s, (v * yy).sum() / s))
        return np.array(out)

    ref_c = dot_centres(ref)
    cx, cy, fs, move, fmove = [], [], [], [], []
    sx, sy, sf = [], [], []
    for a, b in runs:
        im = np.asarray(art["images"][a:b], float)
        for sign, (ox, oy, of) in ((1, (cx, cy, fs)), (-1, (sx, sy, sf))):
            d = np.clip(sign * (im - ref), 0, None)     # pixels turned on (grown) / off (shrunk)
            mass = d.sum((1, 2))
            on = mass > (50 if sign > 0 else 10) * 255
            if on.sum() < 3:
                continue
            x = (d * xx).sum((1, 2))[on] / mass[on]
            y = (d * yy).sum((1, 2))[on] / mass[on]
            ox.append(x - x.mean())
            oy.append(y - y.mean())
            of.append(force[a:b][on])
        for i in range(0, len(im), 3):
            move.append((dot_centres(im[i]) - ref_c)[:, 0].mean())
            fmove.append(force[a + i, 0])
    cx, cy, fs = map(np.concatenate, (cx, cy, fs))
    shrink = (0, float("nan"), float("nan"))       # frames with shrunk dots, corr x, corr y
    if sf:                                          # every group holds >= 3 frames
        sx, sy, sf = map(np.concatenate, (sx, sy, sf))
        shrink = (len(sx), _corr(sx, sf[:, 0]), _corr(sy, sf[:, 1]))
    move, fmove = np.array(move), np.array(fmove)
    return {"frames": len(cx),
            "corr_x": _corr(cx, fs[:, 0]),
            "corr_y": _corr(cy, fs[:, 1]),
            "shrink_frames": shrink[0], "shrink_x": shrink[1], "shrink_y": shrink[2],
            "dot_move_px_per_N": float(np.polyfit(fmove, move, 1)[0]),
            "dot_move_std_px": float(move.std())}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--store", default="artifacts")
    ap.add_argument("--target", default="uskin-z")
    ap.add_argument("--source", nargs="*", default=["gelsight-A-II"])
    args = ap.parse_args(argv)
    store = Path(args.store).resolve()

    def get(name):
        return Artifact(artifact_path(store, name, "shear_cue"))

    rows = [(f"{args.target} twin", get(f"markers[skin={args.target}]"))]
    rows += [(f"{s} -> {args.target} (M2M)", get(f"translate[source={s},target={args.target}]"))
             for s in args.source]
    print(f"{'images':40s} {'frames':>6s} {'corr(cx,Fx)':>11s} {'corr(cy,Fy)':>11s} "
          f"{'shrunk':>6s} {'corr(sx,Fx)':>11s} {'corr(sy,Fy)':>11s} "
          f"{'dot move px/N':>13s} {'move std px':>11s}")
    for name, art in rows:
        c = cue(art)
        print(f"{name:40s} {c['frames']:6d} {c['corr_x']:11.3f} {c['corr_y']:11.3f} "
              f"{c['shrink_frames']:6d} {c['shrink_x']:11.3f} {c['shrink_y']:11.3f} "
              f"{c['dot_move_px_per_N']:13.3f} {c['dot_move_std_px']:11.3f}")


if __name__ == "__main__":
    main()
