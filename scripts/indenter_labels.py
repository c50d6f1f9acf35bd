"""Would labels compensated per indenter shape help a transfer?  (README, hetero study.)

    python scripts/indenter_labels.py [--store artifacts] [--pair tactip:gelsight-A-II ...] [--train]

The transfer compensates its training labels with one calibration per sensor, a flat punch's
(`calibration_trajectory.indenter`).  This script calibrates both sensors of each pair with
every training indenter as well (`calibrate[sensor]` under `-p
calibration_trajectory.indenter=<name>`: one press each, run here if the store lacks it) and
compensates each training contact with its own indenter's curves.  It prints the R2 of the
source's labels against the target's own force at the location-paired frames of the
training indenters: uncompensated, with the punch (what `transfer` trains on) and per
indenter; and, per indenter, how large the translated contacts are against the target's own
at the same frames (changed pixels), which says whose deformation a translation draws.  With --train it also trains genforce_comp both ways (the transfer's config, steps
and seed) and scores the models on the target's unseen and seen indenters as the study does;
the punch model reproduces the study's genforce_comp.

A curved indenter's calibration curve can be convex with a slightly negative linear term,
which stages.force.compensation.fit_curves refuses; those are fitted with non-negative
coefficients instead (the force of a sphere grows as d^1.5, of a cone as d^2).
"""
import argparse
import functools
import subprocess
import sys
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

from pipeline.artifact import Artifact  # noqa: E402
from stages.common import attrs_of  # noqa: E402
from stages.force.compensation import (Curves, _branches, compensate, curves_from_calibration,  # noqa: E402
                                       loading_mask)
from stages.force.nodes import contact_runs, indenter_names  # noqa: E402
from store_lookup import artifact_path  # noqa: E402

TOOL = "indenter_labels"


def _nonnegative_curves(cal) -> Curves:
    """fit_curves' polynomials a d^2 + b d with a, b >= 0 (b at least 1% of a), shear gain kept."""
    from scipy.optimize import nnls
    d = np.asarray(cal["normalised_depth"], float)
    force = np.asarray(cal["force"], float)
    f = np.abs(force[:, 2])
    phase = np.asarray(cal["phase"])
    press, release = _branches(np.asarray(cal["loading"]), phase)

    def fit(m):
        a, b = nnls(np.c_[d[m] ** 2, d[m]], f[m])[0]
        return (float(a), float(max(b, 0.01 * a)), 0.0)
    out = phase == 1
    gain = float(np.hypot(force[out, 0], force[out, 1]).sum() / f[out].sum()) if out.any() else None
    return Curves(fit(press), fit(release), gain)


@functools.lru_cache(maxsize=None)
def shape_curves(store: str, sensor: str, indenter: str) -> Curves:
    instance, param = f"calibrate[sensor={sensor}]", f"calibration_trajectory.indenter={indenter}"
    run = subprocess.run([sys.executable, "-m", "pipeline", "run", instance, "--store", store, "-p", param],
                         cwd=REPO, capture_output=True, text=True)
    if run.returncode:
        sys.exit(f"{TOOL}: {instance} with {param}: {run.stderr.strip() or run.stdout.strip()}")
    cal = Artifact(artifact_path(store, instance, TOOL, (param,)))
    try:
        return curves_from_calibration(cal)
    except ValueError as err:
        if "curve is not positive" not in str(err):
            raise
        print(f"{TOOL}: {sensor} pressed by {indenter}: {err}; fitted with non-negative terms",
              file=sys.stderr)
        return _nonnegative_curves(cal)


def restore_refs(store: str, sensors) -> None:
    """`pipeline run` under -p leaves the store's refs of calibration_trajectory and calibrate
    at the last indenter's artifacts: run them once more as params.yaml has them (cached)."""
    targets = ["calibration_trajectory", *(f"calibrate[sensor={s}]" for s in sorted(sensors))]
    run = subprocess.run([sys.executable, "-m", "pipeline", "run", *targets, "--store", store],
                         cwd=REPO, capture_output=True, text=True)
    if run.returncode:
        sys.exit(f"{TOOL}: restoring the refs of {targets}: {run.stderr.strip() or run.stdout.strip()}")


def r2_axes(true, pred) -> str:
    from sklearn.metrics import r2_score
    return "/".join(f"{r2_score(true[:, k], pred[:, k]):.2f}" for k in range(3))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--store", default="artifacts")
    ap.add_argument("--pair", action="append", help="source:target skins (default: TacTip and GelSight A-II, both ways)")
    ap.add_argument("--train", action="store_true", help="train genforce_comp with both labellings and score it")
    args = ap.parse_args()
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    train_ind, test_ind = params["splits"]["train_indenters"], params["splits"]["test_indenters"]
    pairs = [p.split(":") for p in (args.pair or ["tactip:gelsight-A-II", "gelsight-A-II:tactip"])]
    get = lambda inst: Artifact(artifact_path(args.store, inst, TOOL))  # noqa: E731
    try:
        for source, target in pairs:
            pair(args, params, get, source, target, train_ind, test_ind)
    finally:
        restore_refs(args.store, {params["skins"][skin]["sensor"] for p in pairs for skin in p})


def pair(args, params, get, source, target, train_ind, test_ind) -> None:
    """Print one pair's label R2 (and with --train its models' scores)."""
    tf, tr = get(f"transfer[source={source},target={target}]"), get(f"translate[source={source},target={target}]")
    ms, mt = get(f"markers[skin={source}]"), get(f"markers[skin={target}]")
    info = attrs_of(tf)
    mode, k = info["compensation"], float(info["depth_ratio"])
    punch = {side: Curves.from_dict(v) for side, v in info["curves"].items()}
    sensors = {side: params["skins"][skin]["sensor"] for side, skin in (("source", source), ("target", target))}
    shapes = {i: {side: shape_curves(args.store, sensors[side], i) for side in sensors} for i in train_ind}

    def labels(art, rows=None):
        """(uncompensated, punch, per-indenter) labels of an artifact's rows."""
        rows = np.arange(len(np.asarray(art["force"]))) if rows is None else rows
        force = np.asarray(art["force"], np.float32)[rows]
        depth = np.asarray(art["normalised_depth"], float)[rows]
        load = loading_mask(np.asarray(art["phase"])[rows])
        names = indenter_names(art)[rows]
        per = np.zeros_like(force)
        for i, c in shapes.items():
            m = names == i
            per[m] = compensate(force[m], depth[m], load[m], c["source"], c["target"], mode=mode, depth_ratio=k)
        return force, compensate(force, depth, load, punch["source"], punch["target"], mode=mode,
                                 depth_ratio=k), per

    rows_s = np.concatenate([np.arange(a, b) for a, b in contact_runs(ms, train_ind)])
    rows_t = np.concatenate([np.arange(a, b) for a, b in contact_runs(mt, train_ind)])
    if not np.array_equal(np.asarray(ms["frame"])[rows_s], np.asarray(mt["frame"])[rows_t]):
        sys.exit(f"{TOOL}: {source} and {target} training frames are not location-paired")
    truth = np.asarray(mt["force"], float)[rows_t]
    raw, by_punch, by_shape = labels(ms, rows_s)
    print(f"{source} -> {target} (mode {mode}, depth ratio {k:.2f}): label R2 Fx/Fy/Fz on the "
          f"training indenters: none {r2_axes(truth, raw)}, punch {r2_axes(truth, by_punch)}, "
          f"per indenter {r2_axes(truth, by_shape)}", flush=True)
    print("  changed pixels a frame on deep presses (phase 0, normalised depth > 0.7), translated"
          " / the target's own at the paired frames: "
          + ", ".join(f"{i} {r:.2f}" for i, r in contact_sizes(tr, mt, train_ind).items()), flush=True)
    if args.train:
        train_model(params, tr, mt, labels(tr)[1:], train_ind, test_ind)


def contact_sizes(translated, target_markers, indenters) -> dict:
    """Per indenter: the mean count of pixels a translated frame changes from its reference
    over the count the target's own location-paired frame changes, on deep presses."""
    def rows_of(art):
        return np.concatenate([np.arange(a, b) for a, b in contact_runs(art, indenters)])
    rs, rt = rows_of(translated), rows_of(target_markers)
    if not np.array_equal(np.asarray(translated["frame"])[rs], np.asarray(target_markers["frame"])[rt]):
        sys.exit(f"{TOOL}: the translations' frames are not the target's")
    deep = (np.asarray(translated["phase"])[rs] == 0) & (np.asarray(translated["normalised_depth"])[rs] > 0.7)
    names = indenter_names(translated)[rs][deep]

    def changed(art, rows):
        ref = np.asarray(art["reference"])
        return np.array([(np.asarray(art["images"][r]) != ref).sum() for r in rows], float)
    mine, theirs = changed(translated, rs[deep]), changed(target_markers, rt[deep])
    return {i: mine[names == i].mean() / max(theirs[names == i].mean(), 1.0)
            for i in indenters if (names == i).any()}


def train_model(params, translated, target_markers, label_sets, train_ind, test_ind) -> None:
    from stages.force.metrics import force_metrics
    from stages.force.model import predict_contacts
    from stages.force.nodes import _split_config, _test_set, _training_images, align_models
    from stages.force.train import fit_two_stage, make_sequences
    fc = params["force"]
    model_cfg, train = _split_config(fc["config"])
    runs = contact_runs(translated, train_ind)
    pairs = int(params["m2m"]["finetune"]["pairs_per_skin"])
    images, seq_runs, _ = _training_images(translated, runs, target_markers, train_ind, pairs,
                                           fc["splice"], TOOL)                 # spliced as transfer's
    sets = {"unseen": _test_set(target_markers, test_ind), "seen": _test_set(target_markers, train_ind)}
    for name, comp in zip(("punch", "per indenter"), label_sets):
        seqs = make_sequences(images, [comp[a:b] for a, b in seq_runs], np.asarray(translated["reference"]),
                              model_cfg)
        model, _ = fit_two_stage(seqs, model_cfg, steps=int(fc["steps"]), finetune_steps=int(fc["finetune_steps"]),
                                 batch_size=int(fc["batch_size"]), lr=float(fc["lr"]), seed=int(fc["seed"]),
                                 seq_len=int(train["seq_len"]),
                                 finetune_lr_factor=float(train["finetune_lr_factor"]), desc=name)
        model = align_models({name: model}, translated, target_markers, train_ind, pairs,   # as transfer does
                             fc["align"], name)[0][name]
        scores = []
        for split, data in sets.items():
            m = force_metrics(predict_contacts(model, data["images"], data["contact_id"], data["reference"]),
                              data["force"])
            scores.append(f"{split} R2 {m['r2_fx']:.2f}/{m['r2_fy']:.2f}/{m['r2_fz']:.2f} MAE {m['mae_total']:.2f} N")
        print(f"  genforce_comp on {name} labels: " + ", ".join(scores), flush=True)


if __name__ == "__main__":
    main()
