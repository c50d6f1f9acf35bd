"""Node functions of the force regressor: own[skin], transfer[source,target] and the force
studies (homo, material, hetero).

Inputs are contact-sequence artifacts (or plain dicts of arrays): `images` (N,H,W) uint8,
`reference` (H,W), `force` (N,3), `normalised_depth`, `phase`, `contact_id`, `indenter_id`
and `indenters` (the names indenter_id indexes).  A contact's frames are contiguous and in
time order.  Contacts are split by indenter name: models train on `train_indenters`, studies
score on `test_indenters`.

`config` is the regressor's config (model.DEFAULT_CONFIG keys) plus the training keys of
TRAIN_DEFAULTS.  Trained models are stored as arrays (model.to_arrays) under a group
("weights" for own, "genforce" / "genforce_comp" for transfer) with attrs["config"];
model.load_model / model.load_predictor rebuild them.
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from stages.common import attrs_of, split_timing

TRAIN_DEFAULTS = {
    "seq_len": 32,                # longest training window (frames)
    "finetune_lr_factor": 0.1,    # fine-tune stage learning rate = lr * factor
    "mirror": False,              # train on each contact's mirror images too (train.mirrored)
}
METHODS = ("source_only", "genforce", "genforce_comp", "oracle")
# diagnostic row of the studies: the source's test labels compensated as transfer compensates
# its training labels, scored against the target's labels on the location-paired test frames
# (what genforce_comp would score if it reproduced its labels exactly: the compensation's own error)
LABELS = "labels_comp"
# genforce_comp over several regressor seeds (transfer's and seed[...]'s): the mean of each
# metric, and its standard deviation as sd_<metric>
SEEDS = "genforce_comp_seeds"
# the same models read as one: the metrics of their mean prediction (force.model.MeanPredictor,
# as the control study reads its ensemble), per axis weighted by how each reads the target's
# location-paired frames where the study's `ensemble` is "paired" (ensemble_weights)
ENSEMBLE = "genforce_comp_ensemble"
ENSEMBLE_MODES = ("mean", "paired")
# the transferred models (and source-only) scored on the target's contacts of the seen
# (training) indenters as well: method <method>_seen.  GenForce never sees the target's labels
# nor, past the few location-paired frames M2M's fine-tune, the splice and the alignment read,
# its images, so these frames are test data for every method but the oracle, which trained on
# them (no oracle_seen).
SEEN = "_seen"
SEEN_METHODS = ("source_only", "genforce", "genforce_comp")
_COLOURS = {"source_only": "C3", "genforce": "C0", "genforce_comp": "C2", "oracle": "0.45"}


# ---------------------------------------------------------------------------- artifacts

def _split_config(config: Mapping | None) -> tuple[dict, dict]:
    """User config -> (model config, training options)."""
    config = dict(config or {})
    train = {k: config.pop(k, v) for k, v in TRAIN_DEFAULTS.items()}
    if not isinstance(train["mirror"], bool):
        from stages.common import InputError
        raise InputError(f"force config mirror must be true or false, got {train['mirror']!r}")
    from stages.force.model import model_config
    return model_config(config), train


def indenter_names(art) -> np.ndarray:
    """The indenter name of every frame."""
    names = np.asarray(art["indenters"]).astype(str)
    return names[np.asarray(art["indenter_id"]).astype(int)]


def contact_runs(art, indenters: Sequence[str] | None = None) -> list[tuple[int, int]]:
    """(start, stop) frame ranges of the contacts pressed by `indenters` (None: all)."""
    cid = np.asarray(art["contact_id"])
    starts = np.flatnonzero(np.r_[True, cid[1:] != cid[:-1]]) if cid.size else np.zeros(0, int)
    if len(np.unique(cid)) != starts.size:
        raise ValueError("contact_runs: a contact's frames are not contiguous")
    stops = np.r_[starts[1:], cid.size].astype(int)
    runs = list(zip(starts.tolist(), stops.tolist()))
    if indenters is None:
        return runs
    known = set(np.asarray(art["indenters"]).astype(str))
    unknown = sorted(set(indenters) - known)
    if unknown:
        raise KeyError(f"indenter(s) {unknown} are not in the artifact's indenters {sorted(known)}")
    names = indenter_names(art)
    keep = set(indenters)
    return [(a, b) for a, b in runs if names[a] in keep]


def whole_contacts(art, rows) -> np.ndarray:
    """The rows, in order, of every whole contact of `art` that one of `rows` falls in."""
    runs = contact_runs(art)
    starts = np.array([a for a, _ in runs])
    which = np.unique(np.searchsorted(starts, np.asarray(rows, int), side="right") - 1)
    return np.concatenate([np.arange(*runs[i]) for i in which])


def _read_runs(art, key: str, runs) -> list[np.ndarray]:
    return [np.asarray(art[key][a:b]) for a, b in runs]


def splice_paired(images: list[np.ndarray], runs, translated: Mapping, target_markers: Mapping | None,
                  indenters: Sequence[str] | None, pairs: int, name: str) -> tuple[list[np.ndarray], int]:
    """The translated contacts' images (`images`, one array per run of `runs`) with the frames
    that are location-paired with the target's own collection replaced by the target's frames:
    `pairs` of them (0: all) among the paired frames of `indenters`, the frames M2M's fine-tune
    and the alignment read (paired_table).  A paired frame shows the target at the same
    location, depth and phase as the source's frame it replaces, so it keeps that frame's label;
    the regressor then sees some of the target's own images among the translations, labelled by
    the source.  Returns (images, frames spliced)."""
    from stages.m2m.data import take_rows
    if target_markers is None or "images" not in target_markers:
        raise ValueError(f"{name}: splice needs the target's own frames (target_markers)")
    _, rows = _paired_rows(translated, target_markers, indenters, pairs)
    real = take_rows(target_markers["images"], rows[1])
    if real.shape[1:] != images[0].shape[1:]:
        raise ValueError(f"{name}: the target's frames are {real.shape[1:]}, the translations "
                         f"{images[0].shape[1:]}")
    out = [np.array(im) for im in images]
    starts = np.array([a for a, _ in runs])
    stops = np.array([b for _, b in runs])
    done = 0
    for row, frame in zip(rows[0].tolist(), real):
        i = int(np.searchsorted(starts, row, side="right")) - 1
        if i < 0 or row >= stops[i]:
            continue                     # a paired frame outside the training contacts
        out[i][row - starts[i]] = frame
        done += 1
    return out, done


def _paired_rows(translated: Mapping, target_markers: Mapping, indenters: Sequence[str] | None,
                 pairs: int) -> tuple[np.ndarray, np.ndarray]:
    """paired_table of the translations and the target's own collection: `pairs` location-paired
    frames (0: all) of `indenters` (None: every indenter of the translations), as M2M's
    fine-tune pairs them.  Returns (frames, rows (2,K): translated, target)."""
    from stages.m2m.data import indenter_names as indenters_of
    from stages.m2m.data import paired_table
    if indenters is None:
        indenters = indenters_of(translated)
    return paired_table({"translated": translated, "target": target_markers},
                        ["translated", "target"], indenters, int(pairs))


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


# ---------------------------------------------------------------------------- training nodes

def fit_own(*, markers: Mapping, skin: str, train_indenters: Sequence[str], config: Mapping,
            steps: int, batch_size: int, lr: float, seed: int, skin_spec: Mapping | None = None,
            linear_fz: Mapping | None = None, checkpoint: str | None = None) -> dict:
    """Node `own[skin]`: the regressor on the skin's own images and labels.

    Trained on the contacts of `train_indenters` (source-only model when the skin is a source,
    the oracle when it is a target).  `linear_fz` and `skin_spec` (the skin's): its Fz read
    as fit_transfer's models read a target of the same look, the linear read fitted
    on the skin's own frames and labels (attrs linear_fz).  Returns weights/..., attrs
    {config, skin, train_indenters, history} and figures/loss.  `checkpoint` (the engine's): the training
    resumes from there after an interruption (stages.force.train.Checkpoint).
    """
    from stages.force.model import to_arrays
    from stages.force.train import fit, loss_figure, make_sequences
    model_cfg, train = _split_config(config)
    weight = linear_fz_weight(linear_fz, skin_spec, f"own[{skin}]")
    runs = contact_runs(markers, train_indenters)
    if not runs:
        raise ValueError(f"fit_own[{skin}]: no contacts of train_indenters {list(train_indenters)}")
    reference = np.asarray(markers["reference"])
    force = np.asarray(markers["force"], np.float32)
    seqs = make_sequences(_read_runs(markers, "images", runs), [force[a:b] for a, b in runs],
                          reference, model_cfg)
    ckpt = _checkpoint(checkpoint)
    model, history = fit(seqs, model_cfg, steps=int(steps), batch_size=int(batch_size), lr=float(lr),
                         seed=int(seed), seq_len=int(train["seq_len"]), mirror=train["mirror"],
                         desc=f"own[{skin}]", checkpoint=ckpt, label="own")
    model.set_reference(reference)
    linear = ({"linear_fz": fit_linear_fz_read(model, markers, runs, force, None, train_indenters, 0, weight)}
              if weight else {})
    kept, timing = _split_timing(history, ckpt)
    return {"weights": to_arrays(model),
            "attrs": {"config": model.config, "train": train, "skin": skin,
                      "train_indenters": list(train_indenters), "history": kept, **linear},
            "timing": timing,
            "figures": {"loss": loss_figure({skin: history}, f"own[{skin}]")}}


def fit_transfer(*, translated: Mapping, source_calibration: Mapping, target_calibration: Mapping,
                 source: str, target: str, config: Mapping, steps: int, batch_size: int, lr: float,
                 seed: int, finetune_steps: int, train_indenters: Sequence[str] | None = None,
                 compensation: str = "normal", compensation_depth: str = "shared",
                 target_markers: Mapping | None = None, indenters: Mapping | None = None,
                 source_spec: Mapping | None = None, target_spec: Mapping | None = None,
                 align: str = "none", align_pairs: int = 0, splice: str = "none",
                 readout: str = "none", captured_calibrations: Mapping | None = None,
                 linear_fz: Mapping | None = None, fz_readout: str = "none",
                 checkpoint: str | None = None) -> dict:
    """Node `transfer[source,target]`: regressors on the source's sequences translated into the
    target's style (images; reference = the target's), trained with the source's labels
    (genforce) and with the labels compensated to the target's material (genforce_comp).

    The material prior of each sensor is its `calibrate` artifact (`source_calibration`,
    `target_calibration`: the twin's), or its `capture_calibration` where
    `captured_calibrations` (sensor -> artifact) holds one (attrs calibration: which).

    Both follow the same two-stage schedule from the same seed and differ only in their labels:
    stage 1 trains `steps` steps at `lr` on all translated training contacts (contacts of
    `train_indenters`; None: all of them); stage 2 fine-tunes stage 1's weights for
    `finetune_steps` at lr * finetune_lr_factor on the same contacts and labels (the paper's
    lr 0.1 then 1e-3; 0 skips it).  When the two calibrations give the same curves (same
    material) the compensation is the identity and genforce_comp is genforce's weights, not
    retrained (attrs compensation_identity true).  `compensation` is the mode of
    stages.force.compensation: "normal" (the paper's), "axes" (shear gains too) or "contact"
    ("axes" labels; the target's own frames' shear, which `readout` reads, from its sticking
    contact where it presses deeper, its sliding one where shallower: contact_labels, with the
    `indenters` meshes).
    `readout` ("none", "shear"): after training (and the alignment), genforce_comp's shear output
    is scaled by shear_readout's gains: how it reads the target's own frames on the
    `align_pairs` location-paired frames against the shear they carry (_readout_labels); stored
    as readout_frame, readout_shear and attrs shear_readout, which the seeds read.  Where the
    compensation is the identity genforce_comp is genforce, and so is scaled too.
    `compensation_depth`: "shared" evaluates both curves at the source's normalised depth;
    "paired" evaluates the target's at the target's own normalised depth of the paired frame,
    k times the source's (compensation.depth_ratio, from the normalised depths of the source's
    and `target_markers`' collections; no target label is read).  `align` ("none", "encoder",
    "all"): both models' batch norm is then aligned to the target's own frames on
    `align_pairs` location-paired frames of `train_indenters` (align_models; images only).
    `splice` ("none", "replace", "mix"): those same paired frames of the target replace the
    translations they are paired with in the training sequences (splice_paired), keeping the
    source's labels; "mix" trains on each contact as translated and as spliced
    (_training_images).
    `linear_fz` (a skin's look, `target_spec["look"]` -> weight): both models read
    Fz partly as a linear read of the image's statistics (fit_linear_fz_read; attrs linear_fz),
    weighted so; a look it does not name, weight 0, reads the network's Fz alone.
    `fz_readout` ("none", "up"): after the rest, genforce_comp's Fz is scaled by fz_readout's
    gain, how it reads the target's own frames against the translations at the `align_pairs`
    location-paired frames, where it reads them lower (attrs fz_readout; the seeds fit their
    own).  `checkpoint` (the
    engine's): an interrupted node re-runs none of its finished fits and resumes the one it
    was in (stages.force.train.Checkpoint).
    """
    from stages.force.compensation import (compensate, curves_figure, curves_from_calibration,
                                           label_scale, loading_mask, shear_ratio)
    from stages.force.model import to_arrays
    from stages.force.train import ContactSequence, fit_two_stage, loss_figure, make_sequences
    name = f"transfer[{source}->{target}]"
    _check_align(align, target_markers, name)
    weight = linear_fz_weight(linear_fz, target_spec, name)
    _check_fz_readout(fz_readout, target_markers, name)
    (source_calibration, target_calibration), calibration_from = _calibrations(
        (source_calibration, target_calibration), (source_spec, target_spec), captured_calibrations)
    model_cfg, train = _split_config(config)
    src_curves = curves_from_calibration(source_calibration)
    tgt_curves = curves_from_calibration(target_calibration)
    runs = contact_runs(translated, train_indenters)
    if not runs:
        raise ValueError(f"fit_transfer[{source}->{target}]: no translated contacts to train on")
    reference = np.asarray(translated["reference"])
    force = np.asarray(translated["force"], np.float32)
    depth = np.asarray(translated["normalised_depth"], float)
    loading = loading_mask(np.asarray(translated["phase"]))
    k = _depth_ratio(compensation_depth, depth, target_markers, f"fit_transfer[{source}->{target}]")
    identity = src_curves == tgt_curves and k == 1.0
    comp = compensate(force, depth, loading, src_curves, tgt_curves, mode=compensation, depth_ratio=k)
    read_on, readout_info = _readout_labels(readout, compensation, translated, target_calibration,
                                            comp, k, indenters, target_markers, train_indenters,
                                            align_pairs, name)
    images, seq_runs, spliced = _training_images(translated, runs, target_markers, train_indenters,
                                                 align_pairs, splice, name)
    seqs = make_sequences(images, [force[a:b] for a, b in seq_runs], reference, model_cfg)
    kwargs = dict(steps=int(steps), finetune_steps=int(finetune_steps), batch_size=int(batch_size),
                  lr=float(lr), seed=int(seed), seq_len=int(train["seq_len"]),
                  finetune_lr_factor=float(train["finetune_lr_factor"]), mirror=train["mirror"])
    ckpt = _checkpoint(checkpoint)
    genforce, hist = fit_two_stage(seqs, model_cfg, desc=f"{name} genforce", checkpoint=ckpt,
                                   label="genforce", **kwargs)
    genforce.set_reference(reference)
    histories = {"genforce": hist}
    models = {"genforce": genforce, "genforce_comp": genforce}
    if not identity:
        comp_seqs = [ContactSequence(s.inputs, comp[a:b]) for s, (a, b) in zip(seqs, seq_runs)]
        genforce_comp, histories["genforce_comp"] = fit_two_stage(
            comp_seqs, model_cfg, desc=f"{name} genforce_comp", checkpoint=ckpt,
            label="genforce_comp", **kwargs)
        genforce_comp.set_reference(reference)
        models["genforce_comp"] = genforce_comp
    models, aligned = align_models(models, translated, target_markers, train_indenters, align_pairs,
                                   align, name)
    linear_info = {}
    if weight:
        labels = {"genforce": force} if identity else {"genforce": force, "genforce_comp": comp}
        for m, f in labels.items():
            linear_info[m] = fit_linear_fz_read(models[m], translated, runs, f, target_markers,
                                                train_indenters, align_pairs, weight)
    extra = {}
    if read_on is not None:
        frames, rows, shear = read_on
        readout_info["gain"] = list(shear_readout(models["genforce_comp"], target_markers, rows[1], shear))
        scale_shear(models["genforce_comp"], readout_info["gain"])
        extra = {"readout_frame": frames, "readout_shear": shear}
    fz_info = {}
    if fz_readout != "none":
        fz_info = _apply_fz_readout(models["genforce_comp"], translated, target_markers,
                                    train_indenters, align_pairs, fz_readout)
    weights = to_arrays(models["genforce"])
    weights_comp = to_arrays(models["genforce_comp"])
    if identity:
        models.pop("genforce_comp")
    rows = np.concatenate([np.arange(a, b) for a, b in runs])
    scale = (np.ones(rows.size) if identity else
             label_scale(depth[rows], loading[rows], src_curves, tgt_curves, depth_ratio=k))
    kept, timing = _split_timing(histories, ckpt)
    figures = {"loss": loss_figure(histories, name),
               "compensation": curves_figure({source: (source_calibration, src_curves),
                                              target: (target_calibration, tgt_curves)},
                                             f"compensation {source} -> {target}")}
    return {"genforce": weights, "genforce_comp": weights_comp, **extra,
            "attrs": {"config": genforce.config, "train": train, "source": source, "target": target,
                      "compensation_identity": bool(identity), "compensation": compensation,
                      **({"calibration": calibration_from} if calibration_from else {}),
                      **({"shear_readout": readout_info} if readout_info else {}),
                      **({"fz_readout": fz_info} if fz_info else {}),
                      "compensation_depth": compensation_depth, "depth_ratio": k, "align": aligned,
                      "spliced": spliced, **({"linear_fz": linear_info} if linear_info else {}),
                      "shear_ratio": shear_ratio(src_curves, tgt_curves, compensation, k),
                      "force_range": {m: {"min": mdl.config["force_min"], "max": mdl.config["force_max"]}
                                      for m, mdl in models.items()},
                      "curves": {"source": src_curves.as_dict(), "target": tgt_curves.as_dict()},
                      "label_scale": {"mean": float(scale.mean()), "min": float(scale.min()),
                                      "max": float(scale.max())},
                      "train_indenters": None if train_indenters is None else list(train_indenters),
                      "history": kept},
            "timing": timing,
            "figures": figures}


def _calibrations(twins, specs, captured: Mapping | None) -> tuple[tuple, dict]:
    """The (source, target) calibrations a transfer compensates with: each sensor's captured
    calibration (captured: sensor -> capture_calibration artifact) where there is one, else its
    twin's calibrate artifact; and {"source"|"target": "capture_calibration[sensor=...]"} for
    the captured ones (empty without)."""
    chosen, which = [], {}
    for end, twin, spec in zip(("source", "target"), twins, specs):
        sensor = None if spec is None else spec.get("sensor")
        if captured and sensor in captured:
            chosen.append(captured[sensor])
            which[end] = f"capture_calibration[sensor={sensor}]"
        else:
            chosen.append(twin)
    return tuple(chosen), which


def _readout_labels(readout, mode, translated, target_calibration, comp, k, indenters, target_markers,
                    train_indenters, pairs, name):
    """readout "shear": ((frames, rows (2,K): translated rows, target rows, shear (K,2)), attrs)
    on the `pairs` location-paired frames of `train_indenters` (_paired_rows), the shear being
    the labels the target's own frames there carry: contact_labels in compensation mode
    "contact" (None where it gives none), else `comp`'s; readout "none": (None, {})."""
    from stages.common import InputError
    if readout not in READOUT_MODES:
        raise InputError(f"{name}: readout {readout!r} is not one of {READOUT_MODES}")
    if readout == "none":
        return None, {}
    if target_markers is None or "images" not in target_markers:
        raise ValueError(f"{name}: readout 'shear' needs the target's own frames (target_markers)")
    frames, rows = _paired_rows(translated, target_markers, train_indenters, pairs)
    if mode == "contact":
        shear, info = contact_labels(translated, target_calibration, comp, k, indenters=indenters,
                                     rows=rows[0], name=name)
    else:
        shear, info = np.asarray(comp, np.float32)[rows[0], :2], {"labels": "compensated"}
    info["pairs"] = int(len(frames))
    if shear is None:
        return None, info
    return (frames, rows, shear), info


DEPTH_MODES = ("shared", "paired")
SPLICE_MODES = ("none", "replace", "mix")


def _training_images(translated, runs, target_markers, indenters, pairs, splice, name):
    """(images per training sequence, the run each is of, frames spliced): the translated
    contacts, with the target's paired frames spliced in (splice_paired) per `splice`: "none",
    "replace" (every contact as spliced) or "mix" (every contact twice, as translated and as
    spliced, so that a draw sees either with even odds)."""
    from stages.common import InputError
    if splice not in SPLICE_MODES:
        raise InputError(f"{name}: splice {splice!r} is not one of {SPLICE_MODES}")
    images = _read_runs(translated, "images", runs)
    if splice == "none":
        return images, list(runs), 0
    spliced, done = splice_paired(images, runs, translated, target_markers, indenters, pairs, name)
    if splice == "replace":
        return spliced, list(runs), done
    return images + spliced, list(runs) * 2, done


def fit_transfer_seed(*, transfer: Mapping, translated: Mapping, seed: int, config: Mapping,
                      steps: int, batch_size: int, lr: float, finetune_steps: int,
                      train_indenters: Sequence[str] | None = None, model_pair=None,
                      source: str = "", target: str = "", target_markers: Mapping | None = None,
                      align: str = "none", align_pairs: int = 0, splice: str = "none",
                      checkpoint: str | None = None) -> dict:
    """Nodes `transfer_seed[seed]` and `hetero_seed[source,target,seed]`: `transfer`'s
    genforce_comp model trained again from another seed: on `translated`'s contacts of
    `train_indenters` (transfer_seed: the transfer's own translation; hetero_seed: the pair
    translated by M2M fine-tuned from the same seed, m2m_seed), with the same labels
    (compensated with the curves, mode and depth ratio stored in `transfer`'s attrs,
    recorded_compensation) and the same two-stage schedule; a linear Fz read where the
    transfer has one, with its weight, fitted on `translated` (attrs linear_fz).  Models of
    several seeds differ only by chance: their mean is a steadier force reading than any one
    of them (the control study's ensemble; model_pair: transfer's (source, target), which the
    graph's templates read), and their spread is the chance in a study's figure (hetero; source,
    target: the fan-out's values, which transfer's attrs hold too).  Returns genforce_comp
    weights and attrs {config, source, target, seed, history, align, spliced, and shear_readout
    where transfer's has one: this model's own gains against transfer's stored readout_shear
    on the same frames; fz_readout likewise, this model's own gain; linear_fz, this model's own
    read}.  `align`, `align_pairs`, `splice`, `target_markers` and `checkpoint`: as
    fit_transfer's."""
    from stages.force.model import to_arrays
    from stages.force.train import fit_two_stage, make_sequences
    info = attrs_of(transfer)
    name = f"transfer[{info['source']}->{info['target']}] seed {seed}"
    _check_align(align, target_markers, name)
    model_cfg, train = _split_config(config)
    runs = contact_runs(translated, train_indenters)
    if not runs:
        raise ValueError(f"{name}: no translated contacts to train on")
    reference = np.asarray(translated["reference"])
    force = recorded_compensation(translated, info)
    images, seq_runs, spliced = _training_images(translated, runs, target_markers, train_indenters,
                                                 align_pairs, splice, name)
    seqs = make_sequences(images, [force[a:b] for a, b in seq_runs], reference, model_cfg)
    ckpt = _checkpoint(checkpoint)
    model, history = fit_two_stage(seqs, model_cfg, steps=int(steps), finetune_steps=int(finetune_steps),
                                   batch_size=int(batch_size), lr=float(lr), seed=int(seed),
                                   seq_len=int(train["seq_len"]),
                                   finetune_lr_factor=float(train["finetune_lr_factor"]),
                                   mirror=train["mirror"], desc=name,
                                   checkpoint=ckpt, label="seed")
    model.set_reference(reference)
    models, aligned = align_models({"genforce_comp": model}, translated, target_markers, train_indenters,
                                   align_pairs, align, name)
    linear = info.get("linear_fz") or {}
    linear = linear.get("genforce_comp", linear.get("genforce"))
    if linear:                           # the transfer's read, fitted again on this node's translation
        linear_read = fit_linear_fz_read(models["genforce_comp"], translated, runs, force, target_markers,
                                         train_indenters, align_pairs, float(linear["weight"]))
    readout = {}
    if "readout_shear" in transfer:
        frames, rows = _paired_rows(translated, target_markers, train_indenters, align_pairs)
        if not np.array_equal(frames, np.asarray(transfer["readout_frame"])):
            raise ValueError(f"{name}: the transfer's shear read-out frames are not this node's paired "
                             "frames (another translation, indenters or align_pairs?)")
        gains = shear_readout(models["genforce_comp"], target_markers, rows[1],
                              np.asarray(transfer["readout_shear"], np.float32))
        scale_shear(models["genforce_comp"], gains)
        readout = {"shear_readout": {"gain": list(gains), "pairs": int(len(frames))}}
    if info.get("fz_readout"):
        readout["fz_readout"] = _apply_fz_readout(models["genforce_comp"], translated, target_markers,
                                                  train_indenters, align_pairs, info["fz_readout"]["mode"])
    kept, timing = _split_timing(history, ckpt)
    return {"genforce_comp": to_arrays(models["genforce_comp"]),
            "attrs": {"config": model.config, "train": train, "source": info["source"],
                      "target": info["target"], "seed": int(seed), "history": kept, "align": aligned,
                      "spliced": spliced, **readout,
                      **({"linear_fz": linear_read} if linear else {})},
            "timing": timing}


# two collections whose deepest presses differ by more than this fraction of the deeper one
# press an indenter into differently shaped contacts (compensation "contact": contact_labels)
CONTACT_DEPTH_TOLERANCE = 0.1
READOUT_GAIN_RANGE = (0.25, 4.0)
READOUT_MODES = ("none", "shear")
FZ_READOUT_MODES = ("none", "up")


def _pad_spec(attrs: Mapping) -> dict:
    """The contact geometry of a calibrated sensor from its calibrate artifact's attrs: pad,
    curvature and solver spacing, on an odd grid covering the pad (its centre a cell centre)."""
    spacing = float(attrs["spacing_mm"])
    pad = [float(v) for v in attrs["pad_mm"]]
    grid = [int(np.ceil(p / spacing)) // 2 * 2 + 1 for p in (pad[1], pad[0])]
    return {"grid": grid, "spacing_mm": spacing, "pad_mm": pad,
            "curvature_radius_mm": float(attrs["curvature_radius_mm"])}


def contact_areas(indenters: Mapping, names, indenter_id, contact_id, touchdown, depth,
                  spec: Mapping) -> np.ndarray:
    """(N,) mm^2: the rigid indenter's overlap with the undeformed pad of `spec` (_pad_spec) at
    each frame's depth, the indenter's tip over its contact's touchdown point (N,2) mm: the
    cells whose surface gap to the indenter is below the depth."""
    from stages.sim.indenters import mesh_from_artifact
    from stages.sim.sensors import contact_height, surface_gap
    gap, cell = surface_gap(spec), float(spec["spacing_mm"]) ** 2
    names = np.asarray(names).astype(str)
    contact_id, indenter_id = np.asarray(contact_id), np.asarray(indenter_id)
    depth, touchdown = np.asarray(depth, float), np.asarray(touchdown, float)
    meshes, out = {}, np.zeros(depth.size)
    for c in np.unique(contact_id):
        rows = np.flatnonzero(contact_id == c)
        name = str(names[indenter_id[rows[0]]])
        if name not in meshes:
            meshes[name] = mesh_from_artifact(indenters, name)
        height = contact_height(meshes[name], spec, touchdown[rows[0]], gap)
        levels = np.sort(height[np.isfinite(height)].ravel())
        out[rows] = np.searchsorted(levels, depth[rows], side="left") * cell
    return out


def contact_labels(translated: Mapping, target_calibration: Mapping, comp: np.ndarray, k: float, *,
                   indenters: Mapping | None, rows: np.ndarray, name: str) -> tuple[np.ndarray | None, dict]:
    """Compensation mode "contact": the shear (K,2) the target's own frames at the translated
    frames `rows` carry, and attrs saying which (`labels`):

      "contact"      the target's collection presses deeper than the source's by more than
                     CONTACT_DEPTH_TOLERANCE of its depth: its sticking-contact shear
                     (compensation.contact_shear; TacTip from the flat pads, R2 0.97);
      "compensated"  the two press as deep: `comp`'s shear (the source's, compensated);
      "slip"         the target presses shallower: its pad slides under a contact that sticks
                     on the source, and what it slid out under the shear leg it is sheared
                     back by on the way home (compensation.slip_shear, walked over the whole
                     contacts of `rows`; TacTip to the flat pads R2 0.86-0.88 on the training
                     indenters' paired frames, the same per-frame law 0.76);
      "none"         the target presses shallower and its calibration records no friction
                     mu: None.

    The target's depth at a frame is k times the source's normalised depth times the target
    calibration's max_depth_mm, its contact the indenter's overlap with the target's pad there
    (contact_areas, the `indenters` meshes), its stiffness the calibration's shear leg
    (shear_stiffness, at the calibration indenter's contact), capped at the calibration's
    friction mu (none recorded: no cap) times the compensated |Fz| (`comp`'s).  The deeper
    target's contact sticks over most of its face (slip only at its rim), which one slip for
    the whole contact overstates (slip_shear there: R2 0.96 -> 0.94 from GelSight), so it is
    read frame by frame."""
    from stages.force.compensation import contact_shear, shear_stiffness, slip_shear
    attrs = attrs_of(target_calibration)
    if "max_depth_mm" not in attrs:
        raise ValueError(f"{name}: compensation 'contact' needs the target calibration's attrs "
                         "['max_depth_mm']")
    depth = np.asarray(translated["normalised_depth"], float)
    source_deepest = float(np.max(np.asarray(translated["depth"], float)))
    target_deepest = float(k * np.max(depth) * float(attrs["max_depth_mm"]))
    info = {"source_depth_mm": round(source_deepest, 6), "target_depth_mm": round(target_deepest, 6)}
    rows = np.asarray(rows, int)
    shallower = source_deepest > (1.0 + CONTACT_DEPTH_TOLERANCE) * target_deepest
    mu = attrs.get("mu")
    if shallower and mu is None:
        return None, {"labels": "none", **info}
    if not shallower and target_deepest <= (1.0 + CONTACT_DEPTH_TOLERANCE) * source_deepest:
        return np.asarray(comp, np.float32)[rows, :2], {"labels": "compensated", **info}
    missing = [key for key in ("spacing_mm", "pad_mm", "curvature_radius_mm", "indenter") if key not in attrs]
    if missing:
        raise ValueError(f"{name}: compensation 'contact' needs the target calibration's attrs {missing}")
    if indenters is None:
        raise ValueError(f"{name}: compensation 'contact' needs the indenters' meshes")
    spec = _pad_spec(attrs)
    cal_depth = np.asarray(target_calibration["depth"], float)
    punch = contact_areas(indenters, [attrs["indenter"]], [0], [0], [(0.0, 0.0)],
                          [float(cal_depth.max())], spec)[0]
    read = whole_contacts(translated, rows) if shallower else rows   # the slip runs from their start
    shift = np.asarray(translated["shift"], float)[read]
    touchdown = np.asarray(translated["position"], float)[read, :2] - shift
    contact_id = np.asarray(translated["contact_id"])[read]
    area = contact_areas(indenters, translated["indenters"], np.asarray(translated["indenter_id"])[read],
                         contact_id, touchdown, k * depth[read] * float(attrs["max_depth_mm"]), spec)
    stiffness = shear_stiffness(target_calibration)
    normal = np.asarray(comp)[read, 2]
    if shallower:
        shear = slip_shear(shift, area, normal, contact_id, stiffness=stiffness, punch_area=punch,
                           mu=float(mu))[np.searchsorted(read, rows)]
    else:
        shear = contact_shear(shift, area, normal, stiffness=stiffness, punch_area=punch,
                              mu=None if mu is None else float(mu))
    info.update(labels="slip" if shallower else "contact", stiffness_n_per_mm=round(stiffness, 6),
                punch_area_mm2=round(float(punch), 6), mu=None if mu is None else float(mu))
    return shear.astype(np.float32), info


def _target_predictions(model, target_markers: Mapping, rows: np.ndarray) -> np.ndarray:
    """(K,3) the model's forces at the target's own frames `rows`, each read in its whole contact
    (the GRU's state from the contact's first frame, as the studies and a control loop read)."""
    from stages.force.model import predict_contacts
    read = whole_contacts(target_markers, rows)
    cid = np.asarray(target_markers["contact_id"])
    pred = predict_contacts(model, np.asarray(target_markers["images"][read.tolist()]), cid[read],
                            np.asarray(target_markers["reference"]))
    return pred[np.searchsorted(read, np.asarray(rows, int))]


def linear_fz_weight(linear_fz: Mapping | None, target_spec: Mapping | None, name: str) -> float:
    """The weight of the linear Fz read for a target: `linear_fz` (a skin's look -> weight in
    [0, 1]) at the target skin's `look` (stages.markers.unify.LOOKS: "taxel", the uSkins, whose
    marker images are drawn from taxel signals; "tactip", whose pins the press pushes aside);
    0 where it names none.  A key that is no look is a one-line InputError."""
    from stages.common import InputError
    from stages.markers.unify import LOOKS
    if not linear_fz:
        return 0.0
    if not isinstance(linear_fz, Mapping):
        raise InputError(f"{name}: linear_fz must map a skin's look to a weight, got {linear_fz!r}")
    unknown = sorted(str(k) for k in linear_fz if k not in LOOKS)
    if unknown:
        raise InputError(f"{name}: linear_fz names {unknown}, which are not looks {list(LOOKS)}")
    look = str((target_spec or {}).get("look", ""))
    weight = linear_fz.get(look, 0.0)
    if isinstance(weight, bool) or not isinstance(weight, (int, float)) or not 0.0 <= float(weight) <= 1.0:
        raise InputError(f"{name}: linear_fz[{look!r}] must be a number in [0, 1], got {weight!r}")
    return float(weight)


def fit_linear_fz_read(model, translated: Mapping, runs, force: np.ndarray, target_markers: Mapping | None,
                       indenters, pairs: int, weight: float) -> dict:
    """Give `model` a linear Fz read (stages.force.model.fit_linear_fz) weighted `weight`: fitted on the
    translated frames of `runs` and their labels `force` (N,3; the rows of `translated`), each
    statistic scaled by how the target's own frames show it against the translations at the
    location-paired frames (_paired_rows: `pairs` of them, as the alignment reads; none without
    `target_markers`).  The network's Fz is bounded by its training labels' range (the
    sigmoid); the linear read is not, and where the marker image is drawn from taxel signals
    (a uSkin dot's area grows with its taxel's normal count), or on TacTip, whose press pushes
    aside the pins it covers, the image's change is nearly linear in the normal force.
    Returns the fit's info, with weight."""
    from stages.force.model import fit_linear_fz, image_statistics, prepare
    from stages.m2m.data import take_rows
    cfg = model.config
    reference = np.asarray(translated["reference"])
    rows = np.concatenate([np.arange(a, b) for a, b in runs])
    stats = np.concatenate([image_statistics(prepare(im, reference, cfg), cfg["input_mode"]).numpy()
                            for im in _read_runs(translated, "images", runs)])
    paired = {}
    if target_markers is not None and "images" in target_markers:
        _, prow = _paired_rows(translated, target_markers, indenters, pairs)
        if prow.shape[1]:
            paired = {"translated": image_statistics(prepare(take_rows(translated["images"], prow[0]),
                                                             reference, cfg), cfg["input_mode"]).numpy(),
                      "target": image_statistics(prepare(take_rows(target_markers["images"], prow[1]),
                                                         np.asarray(target_markers["reference"]), cfg),
                                                 cfg["input_mode"]).numpy()}
    coef, intercept, info = fit_linear_fz(stats, np.asarray(force)[rows, 2], **paired)
    model.set_linear_fz(coef, intercept, weight)
    return {**info, "coef": coef.tolist(), "intercept": intercept, "weight": float(weight),
            "pairs": int(len(paired.get("target", ())))}


def shear_readout(model, target_markers: Mapping, rows: np.ndarray, shear: np.ndarray) -> tuple[float, float]:
    """(gx, gy): per shear axis, the least-squares gain, through 0, from `model`'s shear on the
    target's own frames `rows` (_target_predictions) to `shear` (K,2) there, clipped to
    READOUT_GAIN_RANGE (1 where the model reads no shear).  A model that reads the target's
    shear at half its size gets gain 2."""
    pred = _target_predictions(model, target_markers, rows)[:, :2].astype(float)
    shear = np.asarray(shear, float)
    if shear.shape != pred.shape:
        raise ValueError(f"shear_readout: {shear.shape[0]} shear labels for {pred.shape[0]} frames")
    gains = []
    for a in (0, 1):
        den = float(np.sum(pred[:, a] ** 2))
        g = float(np.sum(shear[:, a] * pred[:, a]) / den) if den > 1e-12 else 1.0
        gains.append(round(float(np.clip(g, *READOUT_GAIN_RANGE)), 6))
    return gains[0], gains[1]


def ensemble_weights(models: Sequence, transfer: Mapping, translated: Mapping, target_markers: Mapping,
                     indenters: Sequence[str], pairs: int) -> np.ndarray:
    """(M,3) per-axis weights of the ensemble members `models` of one transfer (its genforce_comp
    and its seeds' models), each axis's summing to 1: each member's inverse mean squared error on
    the target's own frames at the `pairs` location-paired frames of `indenters` (the frames the
    read-outs read, _paired_rows of the transfer's translation `translated`), each read in its
    whole contact.  Fx, Fy are scored against the transfer's read-out labels (readout_shear,
    the shear those frames carry; equal weights where it has none), Fz against the compensated
    label of the translated frame each pairs with (recorded_compensation): the source's labels,
    no target label is read.  A member whose translation drew the pair worse reads those frames
    worse, and the test frames too."""
    if not len(models):
        raise ValueError("ensemble_weights: no models")
    frames, rows = _paired_rows(translated, target_markers, indenters, pairs)
    shear = None
    if "readout_shear" in transfer:
        if not np.array_equal(frames, np.asarray(transfer["readout_frame"])):
            raise ValueError("ensemble_weights: the transfer's read-out frames are not the paired frames "
                             f"of indenters {list(indenters)} ({pairs} pairs)")
        shear = np.asarray(transfer["readout_shear"], float)
    fz = recorded_compensation(translated, attrs_of(transfer), rows[0])[:, 2].astype(float)
    err = np.ones((len(models), 3))
    for k, model in enumerate(models):
        pred = _target_predictions(model, target_markers, rows[1]).astype(float)
        if shear is not None:
            err[k, :2] = np.mean((pred[:, :2] - shear) ** 2, axis=0)
        err[k, 2] = np.mean((pred[:, 2] - fz) ** 2)
    w = 1.0 / np.maximum(err, 1e-12)
    return w / w.sum(axis=0)


def _check_fz_readout(mode, target_markers, name: str) -> None:
    """A one-line InputError for an fz_readout mode not in FZ_READOUT_MODES, before training;
    a ValueError where it needs the target's frames and has none."""
    from stages.common import InputError
    if mode not in FZ_READOUT_MODES:
        raise InputError(f"{name}: fz_readout {mode!r} is not one of {FZ_READOUT_MODES}")
    if mode != "none" and (target_markers is None or "images" not in target_markers):
        raise ValueError(f"{name}: fz_readout {mode!r} needs the target's own frames (target_markers)")


def _apply_fz_readout(model, translated, target_markers, indenters, pairs: int, mode: str) -> dict:
    """fz_readout's gain on the `pairs` location-paired frames of `indenters`, applied to
    `model` (scale_fz); returns attrs {mode, gain, raw, pairs}."""
    _, rows = _paired_rows(translated, target_markers, indenters, pairs)
    gain, raw = fz_readout(model, translated, target_markers, rows) if rows.shape[1] else (1.0, 1.0)
    scale_fz(model, gain)
    return {"mode": mode, "gain": gain, "raw": raw, "pairs": int(rows.shape[1])}


def fz_readout(model, translated: Mapping, target_markers: Mapping, rows: np.ndarray) -> tuple[float, float]:
    """(gain, raw): raw is the least-squares gain, through 0, from `model`'s Fz on the target's
    own frames `rows[1]` to its Fz on the translations they are paired with, `rows[0]`
    (_target_predictions of each, in its whole contact; no label is read): a model that reads the
    target's frames at 0.8 of the translations at the same locations gets raw 1.25.  gain is
    raw clipped to [1, READOUT_GAIN_RANGE[1]]: the read-out only raises the normal force, as
    every model reads its unseen contacts low (README, "Fz read-out")."""
    on_target = _target_predictions(model, target_markers, rows[1])[:, 2].astype(float)
    on_translated = _target_predictions(model, translated, rows[0])[:, 2].astype(float)
    den = float(np.sum(on_target ** 2))
    raw = float(np.sum(on_target * on_translated) / den) if den > 1e-12 else 1.0
    return round(float(np.clip(raw, 1.0, READOUT_GAIN_RANGE[1])), 6), round(raw, 6)


def scale_fz(model, gain: float) -> None:
    """Scale `model`'s normal force (Fz) by `gain` in place, through its force range as
    scale_shear scales the shear (the linear Fz read, where on, is not scaled)."""
    _scale_range(model, (1.0, 1.0, float(gain)))


def scale_shear(model, gains) -> None:
    """Scale `model`'s shear output (Fx, Fy) by `gains` in place: its force range (force_min,
    force_max buffers and config), which its sigmoid output spans, so every reader of the
    stored model (studies, control, streaming) reads the scaled force."""
    _scale_range(model, (float(gains[0]), float(gains[1]), 1.0))


def _scale_range(model, gains) -> None:
    """Scale `model`'s force range (buffers and config) per axis by `gains` (3,)."""
    import torch
    g = torch.tensor([float(v) for v in gains], dtype=model.force_min.dtype,
                     device=model.force_min.device)
    with torch.no_grad():
        model.force_min.mul_(g)
        model.force_max.mul_(g)
    model.config["force_min"] = [round(float(v), 6) for v in model.force_min.cpu().tolist()]
    model.config["force_max"] = [round(float(v), 6) for v in model.force_max.cpu().tolist()]


def _depth_ratio(mode: str, source_depth, target_markers, name: str) -> float:
    """k of compensation_depth `mode`: 1 for "shared", the collections' ratio for "paired"."""
    from stages.force.compensation import depth_ratio
    if mode not in DEPTH_MODES:
        raise ValueError(f"{name}: compensation_depth {mode!r} is not one of {DEPTH_MODES}")
    if mode == "shared":
        return 1.0
    if target_markers is None or "normalised_depth" not in target_markers:
        raise ValueError(f"{name}: compensation_depth 'paired' needs the target's collection "
                         "(target_markers with normalised_depth)")
    return depth_ratio(source_depth, np.asarray(target_markers["normalised_depth"]))


ALIGN_MODES = ("none", "encoder", "all")


def _check_align(layers: str, target_markers: Mapping | None, name: str) -> None:
    """Before any training: an align mode the node cannot use is the user's error."""
    from stages.common import InputError
    if layers not in ALIGN_MODES:
        raise InputError(f"{name}: align {layers!r} is not one of {ALIGN_MODES}")
    if layers != "none" and (target_markers is None or "images" not in target_markers):
        raise ValueError(f"{name}: align {layers!r} needs the target's own frames (target_markers)")


def align_models(models: Mapping, translated: Mapping, target_markers: Mapping | None,
                 indenters: Sequence[str] | None, pairs: int, layers: str, name: str) -> tuple[dict, dict]:
    """`models` (name -> ForceRegressor trained on `translated`) with their batch norm aligned
    to the target's own frames (stages.force.align) on `pairs` location-paired frames of
    `indenters` (0: all): the target's frames from `target_markers` beside the translations of
    the source's frames at the same locations, as M2M's fine-tune pairs them; no label is read.
    Returns (models, attrs); layers "none" returns them as they are.  One model object under
    two names is aligned once."""
    from stages.force.align import align_batchnorm
    from stages.m2m.data import take_rows
    _check_align(layers, target_markers, name)
    if layers == "none":
        return dict(models), {"layers": "none"}
    frames, rows = _paired_rows(translated, target_markers, indenters, pairs)
    fake = take_rows(translated["images"], rows[0])
    real = take_rows(target_markers["images"], rows[1])
    reference = np.asarray(translated["reference"])    # the target's, which the models keep
    done: dict[int, object] = {}
    out = {}
    for key, model in models.items():
        if id(model) not in done:
            done[id(model)] = align_batchnorm(model, fake, real, reference, layers=layers)
        out[key] = done[id(model)]
    return out, {"layers": layers, "pairs": int(len(frames))}


# ---------------------------------------------------------------------------- study node

def _test_set(art, test_indenters):
    runs = contact_runs(art, test_indenters)
    if not runs:
        raise ValueError(f"no test contacts of indenters {list(test_indenters)}")
    rows = np.concatenate([np.arange(a, b) for a, b in runs])
    return {"images": np.concatenate(_read_runs(art, "images", runs)),
            "contact_id": np.asarray(art["contact_id"])[rows],
            "frame": np.asarray(art["frame"])[rows] if "frame" in art else None,
            "force": np.asarray(art["force"], np.float32)[rows],
            "reference": np.asarray(art["reference"])}


def compensated_test_labels(source_art, transfer_art, test_indenters, target_frames):
    """(N,3) the source's test-contact labels compensated with transfer_art's recorded curves,
    mode and depth ratio, in the order of the target's test frames; None when the frames are
    not location-paired (no `frame` labels, or they differ) or the transfer records no curves."""
    attrs = attrs_of(transfer_art)
    if target_frames is None or "frame" not in source_art or "curves" not in attrs:
        return None
    rows = np.concatenate([np.arange(a, b) for a, b in contact_runs(source_art, test_indenters)])
    if not np.array_equal(np.asarray(source_art["frame"])[rows], target_frames):
        return None
    return recorded_compensation(source_art, attrs, rows)


def recorded_compensation(labelled: Mapping, attrs: Mapping, rows=None) -> np.ndarray:
    """(N,3) `labelled`'s force labels (its `rows`; None: all of them) compensated as a transfer
    compensated its training labels: with the curves, mode and depth ratio its `attrs` record
    (compensation.compensate, which returns them unchanged, bit for bit, where those make the
    identity).  What fit_transfer_seed trains on and compensated_test_labels scores."""
    from stages.force.compensation import Curves, compensate, loading_mask

    def take(key, dtype=None):
        a = np.asarray(labelled[key], dtype)
        return a if rows is None else a[rows]
    curves = attrs["curves"]
    return compensate(take("force", np.float32), take("normalised_depth", float),
                      loading_mask(take("phase")), Curves.from_dict(curves["source"]),
                      Curves.from_dict(curves["target"]), mode=attrs.get("compensation", "normal"),
                      depth_ratio=float(attrs.get("depth_ratio", 1.0)))


def force_study(*, study: str, pairs: Sequence[Sequence[str]], own: Mapping[str, Mapping],
                transfer: Mapping[str, Mapping], markers: Mapping[str, Mapping],
                test_indenters: Sequence[str], trace_frames: int = 1000,
                seeds: Mapping[str, Mapping] | None = None,
                seen_indenters: Sequence[str] = (), translated: Mapping[str, Mapping] | None = None,
                ensemble: str = "mean", ensemble_pairs: int = 0) -> dict:
    """Node `homo` / `material` / `hetero` (force part): four methods per source -> target pair,
    all scored on the target's test contacts (`test_indenters`) against the target's labels:

      source_only    own[source] on the target's images
      genforce       transfer[source=,target=] genforce model
      genforce_comp  transfer[source=,target=] genforce_comp model (compensated labels)
      oracle         own[target] (trained on the target's own labels)

    Every model sees the target's images with the target's reference.  Metrics
    `<study>/<source>_<target>/<method>/<metric>` and `<study>/mean/<method>/<metric>`, plus
    the diagnostic method `labels_comp` (LABELS: compensated_test_labels scored the same way)
    where the source's test frames are location-paired with the target's, and, for the pairs
    that `seeds` (fit_transfer_seed artifacts keyed "source=..,target=..,seed=..") has models
    of, the method SEEDS: genforce_comp's metrics averaged over transfer's model and those,
    with sd_<metric> their standard deviation, and the method ENSEMBLE: the metrics of the
    mean of those models' predictions (means over pairs in `<study>/mean/` when every pair
    has them).  `ensemble` "mean" reads the members with equal weights; "paired" weighs them per
    axis by how each reads the target's location-paired frames of `seen_indenters`
    (`ensemble_pairs` of them, the read-outs' frames; ensemble_weights, which needs the pair's
    translation in `translated`: "source=..,target=.." -> translate artifact), attrs
    ensemble_weights ("source_target" -> (members, 3) weights, the transfer's model first).
    With `seen_indenters` (the training indenters), source_only, genforce and
    genforce_comp are also scored on the target's contacts of those: methods `<method>_seen`
    (SEEN; the paper's seen / unseen split), figure seen_unseen.  Arrays mae/<method> (pairs,
    4: fx, fy, fz, total), r2/<method> (pairs, 3), pairs ("source_target"), sources, targets,
    trace/*; figures radar (MAE), r2_hist, trace, violin.
    """
    from stages.common import InputError, torch_threads
    if ensemble not in ENSEMBLE_MODES:
        raise InputError(f"force_study[{study}]: ensemble {ensemble!r} is not one of {ENSEMBLE_MODES}")
    if ensemble == "paired" and seeds and not seen_indenters:
        raise ValueError(f"force_study[{study}]: ensemble 'paired' weighs the members on paired frames "
                         "of the training indenters, and seen_indenters names none")
    with torch_threads():
        return _force_study(study, pairs, own, transfer, markers, test_indenters, trace_frames,
                            seeds or {}, list(seen_indenters or ()), translated or {}, ensemble,
                            int(ensemble_pairs))


def _seed_models(seeds: Mapping[str, Mapping], source: str, target: str) -> list[Mapping]:
    """The artifacts of `seeds` trained for source -> target, in seed order."""
    found = []
    for key, art in seeds.items():
        fields = dict(part.split("=", 1) for part in key.split(","))
        if fields.get("source") == source and fields.get("target") == target:
            found.append((int(fields.get("seed", attrs_of(art).get("seed", 0))), art))
    return [art for _, art in sorted(found, key=lambda x: x[0])]


def _force_study(study, pairs, own, transfer, markers, test_indenters, trace_frames, seeds,
                 seen_indenters, translated, ensemble, ensemble_pairs) -> dict:
    from stages.common import torch_device
    from stages.force.metrics import METRICS, force_metrics
    from stages.force.model import load_model, predict_contacts
    dev = torch_device()

    def load(art, prefix):                # batch prediction runs where training does
        return load_model(art, prefix, device=dev)

    def predict(model, data):
        return predict_contacts(model, data["images"], data["contact_id"], data["reference"])

    pairs = [(str(s), str(t)) for s, t in pairs]
    if not pairs:
        raise ValueError(f"force_study[{study}]: no pairs")
    for s, t in pairs:
        for name, table, key in (("own", own, s), ("own", own, t), ("markers", markers, t),
                                 ("transfer", transfer, f"source={s},target={t}")):
            if key not in table:
                raise KeyError(f"force_study[{study}]: {name} has no {key!r} (pair {s} -> {t})")
    overlap = sorted(set(map(str, seen_indenters)) & set(map(str, test_indenters)))
    if overlap:
        raise ValueError(f"force_study[{study}]: indenters {overlap} are both seen and test indenters")
    tests, seen_sets, oracle_pred, metrics, weights = {}, {}, {}, {}, {}
    per_pair: list[dict] = []
    for s, t in pairs:
        if t not in tests:
            tests[t] = _test_set(markers[t], test_indenters)
        test = tests[t]
        tr = transfer[f"source={s},target={t}"]
        if t not in oracle_pred:
            oracle_pred[t] = predict(load(own[t], "weights"), test)
        identical = bool(attrs_of(tr).get("compensation_identity", False))
        models = {"source_only": load(own[s], "weights"), "genforce": load(tr, "genforce")}
        models["genforce_comp"] = models["genforce"] if identical else load(tr, "genforce_comp")
        preds = {m: predict(models[m], test) for m in ("source_only", "genforce")}
        preds["genforce_comp"] = preds["genforce"] if identical else predict(models["genforce_comp"], test)
        preds["oracle"] = oracle_pred[t]
        scores = {m: force_metrics(preds[m], test["force"]) for m in METHODS}
        for m in METHODS:
            for k, v in scores[m].items():
                metrics[f"{study}/{s}_{t}/{m}/{k}"] = v
        members = _seed_models(seeds, s, t)
        if members:
            member_models = [models["genforce_comp"]] + [load(m, "genforce_comp") for m in members]
            member_preds = [preds["genforce_comp"]] + [predict(m, test) for m in member_models[1:]]
            runs = [scores["genforce_comp"]] + [force_metrics(p, test["force"]) for p in member_preds[1:]]
            for k in runs[0]:
                values = [r[k] for r in runs]
                metrics[f"{study}/{s}_{t}/{SEEDS}/{k}"] = float(np.mean(values))
                metrics[f"{study}/{s}_{t}/{SEEDS}/sd_{k}"] = float(np.std(values, ddof=1))
            mean = np.mean(member_preds, axis=0)
            if ensemble == "paired":
                pair = f"source={s},target={t}"
                if pair not in translated:
                    raise KeyError(f"force_study[{study}]: ensemble 'paired' needs translated[{pair!r}]")
                w = ensemble_weights(member_models, tr, translated[pair], markers[t], seen_indenters,
                                     ensemble_pairs)
                weights[f"{s}_{t}"] = np.round(w, 6).tolist()
                mean = np.einsum("ka,kna->na", w, np.asarray(member_preds, float)).astype(np.float32)
            for k, v in force_metrics(mean, test["force"]).items():
                metrics[f"{study}/{s}_{t}/{ENSEMBLE}/{k}"] = v
        if seen_indenters:
            if t not in seen_sets:
                seen_sets[t] = _test_set(markers[t], seen_indenters)
            seen = seen_sets[t]
            seen_preds = {m: predict(models[m], seen) for m in ("source_only", "genforce")}
            seen_preds["genforce_comp"] = (seen_preds["genforce"] if identical
                                           else predict(models["genforce_comp"], seen))
            for m in SEEN_METHODS:
                for k, v in force_metrics(seen_preds[m], seen["force"]).items():
                    metrics[f"{study}/{s}_{t}/{m}{SEEN}/{k}"] = v
        labels = (compensated_test_labels(markers[s], tr, test_indenters, test["frame"])
                  if s in markers else None)
        if labels is not None:
            for k, v in force_metrics(labels, test["force"]).items():
                metrics[f"{study}/{s}_{t}/{LABELS}/{k}"] = v
        per_pair.append({"source": s, "target": t, "scores": scores,
                         "errors": {m: preds[m] - test["force"] for m in METHODS}, "preds": preds})
    for m in METHODS:
        for k in METRICS:
            metrics[f"{study}/mean/{m}/{k}"] = float(np.mean([p["scores"][m][k] for p in per_pair]))
    for method, names in ((LABELS, METRICS), (SEEDS, [*METRICS, *(f"sd_{k}" for k in METRICS)]),
                          (ENSEMBLE, METRICS),
                          *((f"{m}{SEEN}", METRICS) for m in SEEN_METHODS)):
        for k in names:
            have = [metrics[f"{study}/{s}_{t}/{method}/{k}"] for s, t in pairs
                    if f"{study}/{s}_{t}/{method}/{k}" in metrics]
            if len(have) == len(pairs):
                metrics[f"{study}/mean/{method}/{k}"] = float(np.mean(have))

    mae = {m: np.array([[p["scores"][m][k] for k in ("mae_fx", "mae_fy", "mae_fz", "mae_total")]
                        for p in per_pair]) for m in METHODS}
    r2 = {m: np.array([[p["scores"][m][k] for k in ("r2_fx", "r2_fy", "r2_fz")] for p in per_pair])
          for m in METHODS}
    labels = [f"{p['source']}_{p['target']}" for p in per_pair]
    # representative pair: the median genforce_comp total MAE
    rep = per_pair[int(np.argsort(mae["genforce_comp"][:, 3])[(len(per_pair) - 1) // 2])]
    n = min(int(trace_frames), len(tests[rep["target"]]["force"]))
    trace = {"true": tests[rep["target"]]["force"][:n],
             **{m: rep["preds"][m][:n].astype(np.float32) for m in ("source_only", "genforce_comp")}}
    figures = {"radar": _radar_png(mae, labels, study),
               "r2_hist": _r2_hist_png(r2, study),
               "trace": _trace_png(trace, f"{study}: {rep['source']} -> {rep['target']}"),
               "violin": _violin_png(per_pair, study)}
    if seen_indenters:
        figures["seen_unseen"] = _seen_unseen_png(metrics, study)
    return {"mae": mae, "r2": r2, "pairs": labels, "sources": [p["source"] for p in per_pair],
            "targets": [p["target"] for p in per_pair], "trace": trace, "figures": figures,
            "metrics": metrics,
            "attrs": {"study": study, "test_indenters": list(test_indenters),
                      "seen_indenters": list(seen_indenters),
                      "seen_frames": {t: int(len(v["force"])) for t, v in seen_sets.items()},
                      "trace_pair": [rep["source"], rep["target"]],
                      **({"ensemble_weights": weights} if weights else {}),
                      "test_frames": {t: int(len(v["force"])) for t, v in tests.items()}}}


# ---------------------------------------------------------------------------- figures

def _figure(**kw):
    from matplotlib.figure import Figure
    return Figure(**kw)


def _png(fig):
    from stages.figures import figure_png
    fig.tight_layout()
    return figure_png(fig)


def _radar_png(mae: Mapping[str, np.ndarray], labels: list[str], study: str):
    """One panel per force component: a radar whose spokes are the pairs, one polygon per
    method (grouped bars instead when there are fewer than 3 pairs: a radar needs 3 spokes)."""
    fig = _figure(figsize=(11, 3.4))
    radar = len(labels) >= 3
    angles = np.linspace(0, 2 * np.pi, len(labels), endpoint=False)
    closed = np.r_[angles, angles[:1]]
    width = 0.8 / len(mae)
    for k, comp in enumerate(("Fx", "Fy", "Fz", "Ft (mean)")):
        ax = fig.add_subplot(1, 4, k + 1, projection="polar" if radar else None)
        for j, (m, values) in enumerate(mae.items()):
            v = values[:, k]
            if radar:
                ax.plot(closed, np.r_[v, v[:1]], color=_COLOURS[m], lw=1.2, label=m)
                ax.fill(closed, np.r_[v, v[:1]], color=_COLOURS[m], alpha=0.08)
            else:
                ax.bar(np.arange(len(labels)) + (j - (len(mae) - 1) / 2) * width, v, width,
                       color=_COLOURS[m], label=m)
        ax.set_xticks(angles if radar else np.arange(len(labels)))
        ax.set_xticklabels(labels, fontsize=5 if radar else 7)
        ax.tick_params(axis="y", labelsize=6)
        if radar:            # a few radial labels: at an angle, more of them overprint each other
            from matplotlib.ticker import MaxNLocator
            ax.yaxis.set_major_locator(MaxNLocator(3))
        ax.set_title(f"MAE {comp} (N)", fontsize=9)
    fig.suptitle(study, fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    fig.legend(*fig.axes[0].get_legend_handles_labels(), loc="upper left", ncol=4, fontsize=7,
               frameon=False)
    from stages.figures import figure_png
    return figure_png(fig)


def _r2_hist_png(r2: Mapping[str, np.ndarray], study: str):
    """R2 over pairs and axes, source-only vs GenForce + compensation (R2 < -1 drawn at -1)."""
    fig = _figure(figsize=(4.5, 3.2))
    ax = fig.add_subplot()
    bins = np.linspace(-1.0, 1.0, 21)
    for m in ("source_only", "genforce_comp"):
        ax.hist(np.clip(r2[m].ravel(), -1.0, 1.0), bins=bins, color=_COLOURS[m], alpha=0.55, label=m)
    ax.set(xlabel="R$^2$ (all pairs and axes; below -1 at -1)", ylabel="count", title=study)
    ax.legend(fontsize=8)
    return _png(fig)


def _trace_png(trace: Mapping[str, np.ndarray], title: str):
    fig = _figure(figsize=(8, 5.5))
    for k, comp in enumerate(("Fx", "Fy", "Fz")):
        ax = fig.add_subplot(3, 1, k + 1)
        ax.plot(trace["true"][:, k], color="k", lw=1.2, label="true")
        for m in ("source_only", "genforce_comp"):
            ax.plot(trace[m][:, k], color=_COLOURS[m], lw=0.9, label=m)
        ax.set_ylabel(f"{comp} (N)")
        if k == 0:
            ax.set_title(title, fontsize=9)
            ax.legend(fontsize=7, ncol=3)
    fig.axes[-1].set_xlabel("test frame")
    return _png(fig)


def _seen_unseen_png(metrics: Mapping[str, float], study: str):
    """Mean MAE over the pairs per axis and method, on the seen and the unseen indenters."""
    fig = _figure(figsize=(9, 3.0))
    width = 0.8 / len(SEEN_METHODS)
    for k, comp in enumerate(("fx", "fy", "fz", "total")):
        ax = fig.add_subplot(1, 4, k + 1)
        for j, m in enumerate(SEEN_METHODS):
            v = [metrics[f"{study}/mean/{m}{SEEN}/mae_{comp}"], metrics[f"{study}/mean/{m}/mae_{comp}"]]
            ax.bar(np.arange(2) + (j - (len(SEEN_METHODS) - 1) / 2) * width, v, width,
                   color=_COLOURS[m], label=m)
        ax.set_xticks(np.arange(2))
        ax.set_xticklabels(["seen", "unseen"], fontsize=8)
        ax.tick_params(axis="y", labelsize=7)
        ax.set_title(f"MAE {'Ft (mean)' if comp == 'total' else 'F' + comp[1]} (N)", fontsize=9)
    fig.suptitle(f"{study}: seen vs unseen indenters (mean over pairs)", fontsize=9)
    fig.tight_layout(rect=(0, 0.08, 1, 0.95))
    fig.legend(*fig.axes[0].get_legend_handles_labels(), loc="lower center", ncol=3, fontsize=7,
               frameon=False)
    from stages.figures import figure_png
    return figure_png(fig)


def _violin_png(per_pair: list[dict], study: str):
    """Prediction error per method and axis, pooled over pairs."""
    fig = _figure(figsize=(9, 3.2))
    for k, comp in enumerate(("Fx", "Fy", "Fz")):
        ax = fig.add_subplot(1, 3, k + 1)
        data = [np.concatenate([p["errors"][m][:, k] for p in per_pair]) for m in METHODS]
        parts = ax.violinplot(data, showmedians=True, showextrema=False)
        for body, m in zip(parts["bodies"], METHODS):
            body.set_facecolor(_COLOURS[m])
            body.set_alpha(0.6)
        parts["cmedians"].set_color("k")
        ax.axhline(0.0, color="0.5", lw=0.6)
        ax.set_xticks(np.arange(1, len(METHODS) + 1))
        ax.set_xticklabels(METHODS, rotation=30, fontsize=7)
        ax.set_ylabel(f"{comp} error (N)")
    fig.suptitle(f"{study}: prediction error", fontsize=9)
    return _png(fig)
