"""Does study sim-m2m's FID drop grow with the generator's width and training?  (README, M2M.)

    python scripts/m2m_scale.py [--store artifacts] [--width 32] [--steps 20000] [--batch-size 32]
                                [--lr 0.002] [--n-eval 100] [--save DIR | --load DIR] [--json FILE]
    python scripts/m2m_scale.py --markers-dir DIR --baseline FILE ...    # without a store

Trains the pretrained generator (node m2m_sim's function, stages.m2m.nodes.pretrain) on the
simulation patterns' markers at the given width, steps and batch size, on
stages.common.torch_device (the GPU when torch sees one; the paper profile's sizes are width 32,
batch 32, 20000 steps), or loads one saved by --save.  Then it scores that model and the
store's m2m_sim as study sim-m2m does (translate_sequence, image_features, image_study over
sim_m2m.pairs), both on the same --n-eval evaluation frames per set, and prints each pair's
FID and the mean FID and KID: before, the store's model, the new one.  --markers-dir holds
<skin>.h5 marker artifacts and --baseline an m2m_sim artifact file, for a machine without the
store.
"""
import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

from benchmarks.summary import drain  # noqa: E402
from pipeline.artifact import Artifact  # noqa: E402
from pipeline.params import load as load_params  # noqa: E402
from stages.common import attrs_of, torch_device  # noqa: E402
from stages.m2m.nodes import image_features, image_study, pair_label, pretrain, translate_sequence  # noqa: E402

TOOL = "m2m_scale"


def open_inputs(args, skins: list[str]) -> tuple[dict, object]:
    """{skin: marker artifact} and the stored m2m_sim artifact, from the store or the folders."""
    if args.markers_dir:
        paths = {s: Path(args.markers_dir) / f"{s}.h5" for s in skins}
        missing = [str(p) for p in paths.values() if not p.is_file()]
        if missing or not args.baseline:
            sys.exit(f"{TOOL}: --markers-dir needs <skin>.h5 for every pattern and --baseline; "
                     f"missing {missing[:3] or '--baseline'}")
        return {s: Artifact(p) for s, p in paths.items()}, Artifact(args.baseline)
    from store_lookup import artifact_path
    markers = {s: Artifact(artifact_path(args.store, f"markers[skin={s}]", TOOL)) for s in skins}
    return markers, Artifact(args.baseline or artifact_path(args.store, "m2m_sim", TOOL))


def save_model(model: dict, folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    np.savez(folder / "weights.npz", **model["weights"])
    (folder / "attrs.json").write_text(json.dumps(model["attrs"], indent=1))
    np.save(folder / "loss.npy", model["loss"])


def load_model(folder: Path) -> dict:
    if not (folder / "weights.npz").is_file():
        sys.exit(f"{TOOL}: --load {folder}: no weights.npz (written by --save)")
    with np.load(folder / "weights.npz") as w:
        weights = {k: w[k] for k in w.files}
    return {"weights": weights, "attrs": json.loads((folder / "attrs.json").read_text())}


def score(model, markers: dict, pairs: list, features: dict, params: dict, n_eval: int, kid_subset: int) -> dict:
    """study sim-m2m's metrics for `model` (image_study's metrics dict)."""
    test = params["splits"]["test_indenters"]
    translated = {}
    for s, t in pairs:
        translated[pair_label(s, t)] = drain(translate_sequence(
            model=model, source_markers=markers[s], target_markers=markers[t], eval_indenters=test,
            n_eval=n_eval, sampler_steps=int(params["m2m"]["sampler_steps"]), source=s, target=t))
    return image_study(study="sim-m2m", pairs=pairs, features=features, translated=translated,
                       kid_subset=kid_subset)["metrics"]


def report(stored: dict, new: dict, stored_attrs: dict, new_attrs: dict, pairs: list) -> None:
    """Per-pair and mean FID before / stored / new, and the mean FID and KID drops."""
    def described(attrs):
        return f"width {attrs['config']['width']}, {attrs['steps']} steps of {attrs.get('batch_size', '?')}"

    def ratio(before, after):
        return f"{before / after:.1f}x" if after > 0 else "at the noise floor"

    print(f"\n{'pair':22s} {'before':>9s} {'stored':>9s} {'new':>9s}   (FID; stored: {described(stored_attrs)}; "
          f"new: {described(new_attrs)})")
    for s, t in list(pairs) + [("mean", None)]:
        key = "sim-m2m/mean" if t is None else f"sim-m2m/{s}_{t}"
        name = "mean" if t is None else f"{s}->{t}"
        print(f"{name:22s} {stored[f'{key}/before/fid']:9.2f} {stored[f'{key}/m2m/fid']:9.2f} "
              f"{new[f'{key}/m2m/fid']:9.2f}")
    m = "sim-m2m/mean"
    for what in ("fid", "kid"):
        b, old, now = stored[f"{m}/before/{what}"], stored[f"{m}/m2m/{what}"], new[f"{m}/m2m/{what}"]
        print(f"mean {what.upper()}: before {b:.4g}, stored {old:.4g} ({ratio(b, old)}), "
              f"new {now:.4g} ({ratio(b, now)})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--store", default="artifacts")
    ap.add_argument("--profile", default="default", help="the params profile the store was run with")
    ap.add_argument("--width", type=int, default=32)
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--batch-size", type=int, default=32)
    ap.add_argument("--lr", type=float, default=None, help="default: m2m.pretrain.lr")
    ap.add_argument("--n-eval", type=int, default=100, help="evaluation frames per image set")
    ap.add_argument("--kid-subset", type=int, default=50)
    ap.add_argument("--save", help="folder to save the trained model in")
    ap.add_argument("--load", help="folder of a model saved by --save: score it, train nothing")
    ap.add_argument("--markers-dir")
    ap.add_argument("--baseline", help="an m2m_sim artifact file (default: the store's)")
    ap.add_argument("--json", help="write the metrics to this file")
    args = ap.parse_args()
    if args.steps < 1 or args.width < 1 or args.batch_size < 1 or args.n_eval < 2:
        sys.exit(f"{TOOL}: --steps, --width and --batch-size must be at least 1 and --n-eval at least 2")
    if args.kid_subset > args.n_eval:
        sys.exit(f"{TOOL}: --kid-subset {args.kid_subset} is larger than --n-eval {args.n_eval}")
    params = load_params(REPO / "params.yaml", args.profile)
    pre = params["m2m"]["pretrain"]
    skins, pairs = list(pre["skins"]), [tuple(p) for p in params["sim_m2m"]["pairs"]]
    markers, baseline = open_inputs(args, skins)
    print(f"{TOOL}: {len(skins)} patterns, {len(pairs)} pairs, n_eval {args.n_eval}, on {torch_device()}")

    if args.load:
        model = load_model(Path(args.load))
    else:
        t0 = time.perf_counter()
        model = pretrain(markers=markers, skins=skins, train_indenters=params["splits"]["train_indenters"],
                         size=params["render"]["size"], steps=args.steps, batch_size=args.batch_size,
                         lr=float(pre["lr"] if args.lr is None else args.lr), seed=int(pre["seed"]),
                         width=args.width, timesteps=int(pre["timesteps"]),
                         change_weight=float(pre["change_weight"]), change_share=float(pre["change_share"]),
                         source_gate=bool(pre["source_gate"]), identity_share=float(pre["identity_share"]))
        print(f"trained width {args.width}, {args.steps} steps of {args.batch_size} in "
              f"{time.perf_counter() - t0:.0f} s; final loss {model['attrs']['final_loss']:.4f}")
        if args.save:
            save_model(model, Path(args.save))
    test = params["splits"]["test_indenters"]
    features = {s: image_features(markers=markers[s], eval_indenters=test, n_eval=args.n_eval) for s in skins}
    stored_attrs = attrs_of(baseline)
    stored = score(baseline, markers, pairs, features, params, args.n_eval, args.kid_subset)
    new = score(model, markers, pairs, features, params, args.n_eval, args.kid_subset)
    report(stored, new, stored_attrs, model["attrs"], pairs)
    if args.json:
        Path(args.json).write_text(json.dumps({"stored": stored, "new": new, "new_attrs": model["attrs"],
                                               "n_eval": args.n_eval}, indent=1, default=str))


if __name__ == "__main__":
    main()
