"""How a camera skin's force models read its frames against other noise realisations of its
no-contact reference.

    python scripts/reference_noise.py [--store artifacts] [--skin gelsight-A-II]
        [--source gelsight-A-I ...] [--seeds 11 12 13] [--band 0.5 2]

A sensor takes its reference (the no-contact marker image the models subtract) when it is set
up; the camera's noise makes each take differ from the last at a few marker-edge pixels. This
renders the skin's no-contact pad again with other noise seeds (the render node's Renderer,
segmented as the markers node segments), and scores the skin's own model (`own[skin]`) and
each transfer into it (`transfer[source,skin]`, genforce_comp) on the skin's frames of the
test indenters, once with the skin's own reference and once with each fresh one: the median
of predicted over true normal force in the force band (N), the R2 of Fz over every test frame,
and how many pixels the reference differs by. A model that is robust to the set-up reads
every row alike.
"""
import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

from store_lookup import artifact_path  # noqa: E402


def fresh_references(deform, patterns, spec: dict, segmentation: dict, seeds,
                     size=(128, 128)) -> list[np.ndarray]:
    """The skin's no-contact marker image (H,W = size) under each camera-noise seed: rendered as
    the render node renders (its Renderer on the deform artifact's pad, the skin's look, light,
    noise and upsample; one scene, the seed changed between shots) and segmented as the markers
    node segments (the render seed gives the markers node's reference)."""
    from stages.markers.render import Renderer, marker_set
    from stages.markers.segment import segment
    from stages.markers.unify import segmentation_params

    look = spec.get("look", "none")
    if look not in ("gelsight", "tactip"):
        raise ValueError(f"reference_noise: look {look!r} has no camera noise (gelsight, tactip)")
    params = segmentation_params(segmentation, look)
    still = np.zeros(np.shape(deform["surface_z"]) + (3,), np.float32)
    r = Renderer(deform["grid_x"], deform["grid_y"], deform["surface_z"], deform["on_pad"],
                 marker_set(patterns, spec["pattern"]), look=look, size=size,
                 light=spec.get("light"), noise=float(spec.get("noise", 0.0)),
                 upsample=float(spec.get("upsample", 1.0)))
    out = []
    for seed in seeds:
        r.seed = int(seed)                  # the noise of the shot: rng (seed, index + 1)
        out.append(segment(r.render(still, -1)["raw"], **params))
    return out


def readings(predict, images, contact_id, force, references, band=(0.5, 2.0)) -> list[dict]:
    """Per reference: `gain` (median predicted / true |Fz| over the frames whose true |Fz| is in
    `band`), `r2_fz` (every frame) and `pixels` (how many pixels it differs from the first).
    predict(images, contact_id, reference) -> (N,3) forces."""
    from sklearn.metrics import r2_score

    force = np.asarray(force, float)
    true = -force[:, 2]
    sel = (true > band[0]) & (true < band[1])
    if not sel.any():
        raise ValueError(f"reference_noise: no frame has a normal force in {band} N")
    out = []
    for ref in references:
        p = np.asarray(predict(images, contact_id, ref), float)
        out.append({"gain": float(np.median(-p[sel, 2] / true[sel])),
                    "r2_fz": float(r2_score(force[:, 2], p[:, 2])),
                    "pixels": int((np.asarray(ref) != np.asarray(references[0])).sum())})
    return out


def main(argv=None):
    import yaml

    from pipeline.artifact import Artifact
    from stages.force.model import load_model, predict_contacts
    from stages.common import attrs_of
    from stages.force.nodes import _test_set

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--store", default="artifacts")
    ap.add_argument("--skin", default="gelsight-A-II")
    ap.add_argument("--source", nargs="*", default=["gelsight-A-I"])
    ap.add_argument("--seeds", nargs="*", type=int, default=[11, 12, 13])
    ap.add_argument("--band", nargs=2, type=float, default=[0.5, 2.0])
    args = ap.parse_args(argv)
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    if args.skin not in params["skins"]:
        sys.exit(f"reference_noise: unknown skin {args.skin!r}")
    spec = params["skins"][args.skin]

    def get(name):
        return Artifact(artifact_path(args.store, name, "reference_noise"))

    markers = get(f"markers[skin={args.skin}]")
    test = _test_set(markers, params["splits"]["test_indenters"])
    fresh = fresh_references(get(f"deform[sensor={spec['sensor']}]"), get("patterns"), spec,
                             params.get("segmentation") or {}, args.seeds,
                             size=np.shape(test["reference"]))
    render_seed = int(attrs_of(get(f"render[skin={args.skin}]"))["seed"])   # the reference's shot
    refs = [test["reference"]] + fresh
    names = [f"own reference (seed {render_seed})"] + [f"seed {s}" for s in args.seeds]
    models = [(f"own[{args.skin}]", load_model(get(f"own[skin={args.skin}]"), "weights"))]
    models += [(f"transfer[{s}->{args.skin}]",
                load_model(get(f"transfer[source={s},target={args.skin}]"), "genforce_comp"))
               for s in args.source]
    print(f"{args.skin}: {len(test['force'])} test frames; median predicted / true |Fz| in "
          f"{args.band[0]}-{args.band[1]} N, R2 of Fz, pixels the reference differs by")
    print(f"{'model':40s} {'reference':28s} {'gain':>6s} {'r2_fz':>6s} {'pixels':>6s}")
    for label, model in models:
        rows = readings(lambda x, c, r: predict_contacts(model, x, c, r), test["images"],
                        test["contact_id"], test["force"], refs, tuple(args.band))
        for name, row in zip(names, rows):
            print(f"{label:40s} {name:28s} {row['gain']:6.3f} {row['r2_fz']:6.3f} {row['pixels']:6d}")


if __name__ == "__main__":
    main()
