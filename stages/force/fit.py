"""The force regressor's training nodes: own[skin,seed] and transfer[source,target,seed], one
instance per regressor seed of `force.seeds`.

`config` is the regressor's config (model.DEFAULT_CONFIG keys) plus the training keys of
TRAIN_DEFAULTS.  Trained models are stored as arrays (model.to_arrays) under a group
("weights" for own; "genforce", "genforce_comp", "genforce_plus" for transfer) with
attrs["config"] (and attrs["configs"][group] where a group's config differs);
model.load_model / model.load_predictor rebuild them.

Where target labels go: own[target] (the oracle) is the only node that trains on a target's
labels.  transfer reads the target's images alone: the location-paired frames of its training
indenters, for genforce_plus (stages.force.plus); tests/stages/force/test_leakage.py poisons the
target's labels and checks that no weight of transfer changes.
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from stages.common import attrs_of, split_timing
from stages.force.data import contact_runs, read_runs, run_rows

TRAIN_DEFAULTS = {
    "seq_len": 32,                # longest training window (frames)
    "finetune_lr_factor": 0.1,    # fine-tune stage learning rate = lr * factor
    "optimizer": "sgd",           # sgd (momentum 0.9, the paper's) or adamw
    "weight_decay": 5e-4,         # the optimiser's (the paper's SGD: 5e-4)
}


def recipe(train: Mapping) -> dict:
    """The keyword arguments of stages.force.train.fit that a config's training keys set: every
    method trains with them alike."""
    return {"seq_len": int(train["seq_len"]), "optimizer": str(train["optimizer"]),
            "weight_decay": float(train["weight_decay"])}


def split_config(config: Mapping | None) -> tuple[dict, dict]:
    """User config -> (model config, training options)."""
    from stages.force.model import model_config
    config = dict(config or {})
    train = {k: config.pop(k, v) for k, v in TRAIN_DEFAULTS.items()}
    return model_config(config), train


def _checkpoint(path: str | None):
    """The node's training checkpoint (stages.force.train.Checkpoint) at the engine's path."""
    from stages.force.train import Checkpoint
    return Checkpoint(path) if path else None


def _split_timing(history: Mapping, ckpt) -> tuple[dict, dict]:
    """split_timing, plus the steps the node's fits resumed from (timing: resumed_at_step)."""
    kept, timing = split_timing(history)
    if ckpt is not None and ckpt.resumed:
        timing["resumed_at_step"] = dict(ckpt.resumed)
    return kept, timing


def train_own(markers: Mapping, config: Mapping, *, steps: int, batch_size: int, lr: float, seed: int,
              train_indenters: Sequence[str], checkpoint=None, label: str = "own", desc: str = "own"):
    """(model, history): the regressor on a skin's own images and labels of the contacts of
    `train_indenters`, with its reference set: own's training (and the learning curve's
    oracle at other lengths)."""
    from stages.force.train import fit, make_sequences
    model_cfg, train = split_config(config)
    runs = contact_runs(markers, train_indenters)
    if not runs:
        raise ValueError(f"{desc}: no contacts of train_indenters {list(train_indenters)}")
    reference = np.asarray(markers["reference"])
    force = np.asarray(markers["force"], np.float32)
    seqs = make_sequences(read_runs(markers, "images", runs), [force[a:b] for a, b in runs],
                          reference, model_cfg)
    model, history = fit(seqs, model_cfg, steps=int(steps), batch_size=int(batch_size), lr=float(lr),
                         seed=int(seed), **recipe(train), desc=desc, checkpoint=checkpoint, label=label)
    model.set_reference(reference)
    return model, history


def fit_own(*, markers: Mapping, skin: str, train_indenters: Sequence[str], config: Mapping,
            steps: int, batch_size: int, lr: float, seed: int, checkpoint: str | None = None) -> dict:
    """Node `own[skin]`: the regressor on the skin's own images and labels, trained on the
    contacts of `train_indenters`: the source-only model where the skin is a source, the oracle
    where it is a target.  Returns weights/..., attrs {config, skin, train_indenters, history}
    and figures/loss.  `checkpoint` (the engine's): the training resumes from there after an
    interruption (stages.force.train.Checkpoint)."""
    from stages.force.model import to_arrays
    from stages.force.train import loss_figure
    ckpt = _checkpoint(checkpoint)
    model, history = train_own(markers, config, steps=steps, batch_size=batch_size, lr=lr, seed=seed,
                               train_indenters=train_indenters, checkpoint=ckpt, label="own",
                               desc=f"own[{skin}]")
    _, train = split_config(config)
    kept, timing = _split_timing(history, ckpt)
    return {"weights": to_arrays(model),
            "attrs": {"config": model.config, "train": train, "skin": skin,
                      "train_indenters": list(train_indenters), "history": kept},
            "timing": timing,
            "figures": {"loss": loss_figure({skin: history}, f"own[{skin}]")}}


def calibrations(given, captured: Mapping | None) -> tuple[tuple, dict]:
    """The (source, target) calibrations a transfer compensates with: each sensor's captured
    calibration (captured: sensor body -> capture_calibration artifact) where there is one, else
    the one given (its twin's calibrate artifact, whose attrs name the body; the authors'
    curves; or None); and {"source"|"target": "capture_calibration[sensor=...]"} for the
    captured ones (empty without)."""
    chosen, which = [], {}
    for end, twin in zip(("source", "target"), given):
        sensor = None if twin is None else attrs_of(twin).get("sensor")
        if captured and sensor in captured:
            chosen.append(captured[sensor])
            which[end] = f"capture_calibration[sensor={sensor}]"
        else:
            chosen.append(twin)
    return tuple(chosen), which


def compensated_labels(translated: Mapping, curves: Mapping | None) -> np.ndarray:
    """(N,3) the translations' (source's) labels compensated with `curves` ({"source", "target":
    Curves.as_dict()}, as a transfer records them): the paper's compensation.  Without curves
    (None: neither sensor has a calibration) or with equal ones, the labels as they are, and no
    depth is read."""
    from stages.force.compensation import Curves, compensate, loading_mask
    if curves is None or Curves.from_dict(curves["source"]) == Curves.from_dict(curves["target"]):
        return np.array(translated["force"], np.float32)
    return compensate(np.asarray(translated["force"], np.float32),
                      np.asarray(translated["normalised_depth"], float),
                      loading_mask(np.asarray(translated["phase"])),
                      Curves.from_dict(curves["source"]), Curves.from_dict(curves["target"]))


def fit_transfer(*, translated: Mapping, source: str, target: str, config: Mapping, steps: int,
                 batch_size: int, lr: float, seed: int, finetune_steps: int,
                 source_calibration: Mapping | None = None, target_calibration: Mapping | None = None,
                 train_indenters: Sequence[str] | None = None,
                 target_markers: Mapping | None = None, additions: Sequence[str] = (),
                 source_punch: Mapping | None = None,
                 target_punch: Mapping | None = None,
                 captured_calibrations: Mapping | None = None, checkpoint: str | None = None) -> dict:
    """Node `transfer[source,target]`: regressors on the source's sequences translated into the
    target's style (images; reference = the target's):

      genforce       trained with the source's labels;
      genforce_comp  trained with the labels compensated to the target's material (the paper's
                     compensation, stages.force.compensation);
      genforce_plus  genforce_comp with `additions` (stages.force.plus), which read the
                     target's reference image (`target_markers`) and the calibrations:
                     applied to a copy of genforce_comp's model, nothing retrained.
                     punch_calibration reads the two sensors' flat-punch
                     calibrations (`source_punch`, `target_punch`: calibrate_punch artifacts), where
                     both are given and neither prism calibration was captured (attrs punch_scale).

    The material prior of each sensor is its `calibrate` artifact (the twin's), or its
    `capture_calibration` where `captured_calibrations` (sensor body -> artifact) holds one
    (attrs calibration: which), or its `authors_calibration` (the authors' curves).  Where
    neither sensor has one (the authors' homo set: one gel) there is nothing to compensate:
    attrs curves None, and the translations need no normalised_depth.  Both fits follow the
    same two-stage schedule from the same seed and differ only in their labels: `steps` at
    `lr` on the translated contacts of
    `train_indenters` (None: all), then `finetune_steps` at lr * finetune_lr_factor (0 skips
    it).  Where the two calibrations give the same curves the compensation is the identity and
    genforce_comp is genforce's weights, not retrained (attrs compensation_identity).
    `checkpoint` (the engine's): an interrupted node re-runs none of its finished fits and
    resumes the one it was in."""
    from stages.force import plus
    from stages.force.compensation import (curves_figure, curves_from_calibration, label_scale, loading_mask,
                                           shear_ratio)
    from stages.force.model import prepare, to_arrays
    from stages.force.train import ContactSequence, fit_two_stage, loss_figure, make_sequences
    name = f"transfer[{source}->{target}]"
    additions = plus.check_additions(additions, name)
    (source_calibration, target_calibration), calibration_from = calibrations(
        (source_calibration, target_calibration), captured_calibrations)
    if (source_calibration is None) != (target_calibration is None):
        from stages.common import InputError
        missing = source if source_calibration is None else target
        raise InputError(f"{name}: {missing} has no material calibration but the other sensor has: "
                         "compensation needs both (or neither)")
    model_cfg, train = split_config(config)
    calibrated = source_calibration is not None
    src_curves = curves_from_calibration(source_calibration) if calibrated else None
    tgt_curves = curves_from_calibration(target_calibration) if calibrated else None
    curves = {"source": src_curves.as_dict(), "target": tgt_curves.as_dict()} if calibrated else None
    runs = contact_runs(translated, train_indenters)
    if not runs:
        raise ValueError(f"{name}: no translated contacts to train on")
    comp = compensated_labels(translated, curves)
    ratios = {"source": shear_ratio(source_calibration), "target": shear_ratio(target_calibration)}
    ratios = ratios if None not in ratios.values() else None
    reference = np.asarray(translated["reference"])
    force = np.asarray(translated["force"], np.float32)
    rows = run_rows(runs)
    identity = src_curves == tgt_curves
    if not identity:      # the training frames' depths and branches (no depth read without curves)
        depth = np.asarray(translated["normalised_depth"], float)[rows]
        loading = loading_mask(np.asarray(translated["phase"])[rows])
    punch = None
    if calibrated and source_punch is not None and target_punch is not None and not calibration_from:
        punch = 1.0 if identity else plus.punch_scale(
            force[rows], depth, loading, {"source": src_curves, "target": tgt_curves},
            {"source": curves_from_calibration(source_punch), "target": curves_from_calibration(target_punch)})
    view = plus.target_view(target_markers, ratios, punch) if additions else None
    images = read_runs(translated, "images", runs)
    seqs = make_sequences(images, [force[a:b] for a, b in runs],
                          reference, model_cfg)
    kwargs = dict(steps=int(steps), finetune_steps=int(finetune_steps), batch_size=int(batch_size),
                  lr=float(lr), seed=int(seed), **recipe(train),
                  finetune_lr_factor=float(train["finetune_lr_factor"]))
    ckpt = _checkpoint(checkpoint)
    genforce, hist = fit_two_stage(seqs, model_cfg, desc=f"{name} genforce", checkpoint=ckpt,
                                   label="genforce", **kwargs)
    genforce.set_reference(reference)
    histories = {"genforce": hist}
    genforce_comp = genforce
    if not identity:
        comp_seqs = [ContactSequence(s.inputs, comp[a:b]) for s, (a, b) in zip(seqs, runs)]
        genforce_comp, histories["genforce_comp"] = fit_two_stage(
            comp_seqs, model_cfg, desc=f"{name} genforce_comp", checkpoint=ckpt,
            label="genforce_comp", **kwargs)
        genforce_comp.set_reference(reference)
    genforce_plus, plus_info = (plus.apply(genforce_comp, view, additions) if additions
                                else (genforce_comp, {}))
    scale = np.ones(rows.size) if identity else label_scale(depth, loading, src_curves, tgt_curves)
    kept, timing = _split_timing(histories, ckpt)
    figures = {"loss": loss_figure(histories, name)}
    if calibrated:
        figures["compensation"] = curves_figure({source: (source_calibration, src_curves),
                                                 target: (target_calibration, tgt_curves)},
                                                f"compensation {source} -> {target}")
    return {"genforce": to_arrays(genforce), "genforce_comp": to_arrays(genforce_comp),
            "genforce_plus": to_arrays(genforce_plus),
            "attrs": {"config": genforce.config,
                      "configs": {"genforce_comp": genforce_comp.config,
                                  "genforce_plus": genforce_plus.config},
                      "train": train, "source": source, "target": target,
                      "compensation_identity": bool(identity), "curves": curves, "shear_ratios": ratios,
                      "punch_scale": punch,
                      **({"calibration": calibration_from} if calibration_from else {}),
                      "plus": {"additions": additions, **plus_info},
                      "label_scale": {"mean": float(scale.mean()), "min": float(scale.min()),
                                      "max": float(scale.max())},
                      "train_indenters": None if train_indenters is None else list(train_indenters),
                      "history": kept},
            "timing": timing,
            "figures": figures}
