"""genforce_plus: the paper's genforce_comp model with our additions, each label-free.

Every addition is applied after training, to a copy of the genforce_comp model, and reads only
what GenForce already has without a force label of the target: the translations and the
source's compensated labels, and the few location-paired frames of the target's own
collection on the training indenters that fine-tune M2M (images only).  So an addition costs
no retraining, and the ablation (stages.force.study.ablation_study) can take each one away in
turn from models of several seeds.

The additions, in the order they are applied (ADDITIONS):

  mirror_shear  the model reads a frame's shear as the odd part of its readings of the frame and
                of the frame's mirror images under which the target's reference looks the same
                (stages.force.model, mirror_read "auto"): the even part is error.
  paired_bn     the encoder's batch-norm statistics moved so that the target's paired frames are
                normalised as their translations are (stages.force.align: AdaBN on paired frames).
  linear_fz     Fz read as the mean of the network's reading and a linear read of how much the
                frame changes against the reference (stages.force.model.fit_linear_fz, fitted on
                the translated training frames and their compensated labels, each image
                statistic scaled by how the target's paired frames show it against their
                translations): the network's Fz cannot leave its training labels' range.
  shear_gain    Fx, Fy scaled per axis by the least-squares gain, through 0, from the model's
                shear on the target's paired frames to the compensated source labels of the
                translated frames they pair with.
  fz_gain       Fz scaled by the least-squares gain, through 0, from the model's Fz on the
                target's paired frames to its Fz on their translations (no label read).

A gain is clipped to GAIN_RANGE.  Which additions a genforce_plus model carries is the params'
`plus.additions`; each one kept there has beaten the seed spread on the validation indenters
(ablation/<study>/<addition>/delta_mae_total against ablation/<study>/seed_spread/mae_total).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from stages.force.data import paired_rows, predict_rows

ADDITIONS = ("mirror_shear", "paired_bn", "linear_fz", "shear_gain", "fz_gain")
LINEAR_FZ_WEIGHT = 0.5         # linear_fz: the plain mean of the two reads
GAIN_RANGE = (0.25, 4.0)


@dataclass
class Paired:
    """What the additions read: the location-paired frames of the translations and the target
    (rows (2,K)), the compensated source labels (K,3) of the translated ones, and the training
    contacts (runs of the translations) with their compensated labels (N,3, every row)."""
    translated: Mapping
    target: Mapping
    rows: np.ndarray
    labels: np.ndarray
    runs: list
    train_labels: np.ndarray

    @property
    def count(self) -> int:
        return int(self.rows.shape[1])


def paired_frames(translated: Mapping, target_markers: Mapping, labels: np.ndarray,
                  indenters: Sequence[str] | None, pairs: int) -> Paired:
    """The Paired the additions read: `pairs` location-paired frames of `indenters` (the
    training indenters, whose contacts are the training runs), `labels` (N,3) the translated
    rows' compensated labels."""
    from stages.force.data import contact_runs
    if target_markers is None or "images" not in target_markers:
        raise ValueError("genforce_plus needs the target's own paired frames (target_markers)")
    _, rows = paired_rows(translated, target_markers, indenters, pairs)
    labels = np.asarray(labels, np.float32)
    return Paired(translated, target_markers, rows, labels[rows[0]],
                  contact_runs(translated, indenters), labels)


def check_additions(additions: Sequence[str], name: str) -> list[str]:
    """The additions as a list in ADDITIONS order; an unknown or repeated one is an InputError."""
    from stages.common import InputError
    additions = [str(a) for a in additions]
    unknown = sorted(set(additions) - set(ADDITIONS))
    if unknown:
        raise InputError(f"{name}: plus.additions {unknown} are not among {list(ADDITIONS)}")
    if len(set(additions)) != len(additions):
        raise InputError(f"{name}: plus.additions {additions} names one twice")
    return [a for a in ADDITIONS if a in additions]


def _clip(g: float) -> float:
    return round(float(np.clip(g, *GAIN_RANGE)), 6)


def _gain(x: np.ndarray, y: np.ndarray) -> float:
    """Least-squares gain, through 0, from x to y (1 where x is all zero)."""
    den = float(np.sum(x * x))
    return float(np.sum(x * y) / den) if den > 1e-12 else 1.0


def scale_axes(model, gains) -> None:
    """Scale `model`'s output per axis by `gains` (3,) in place: its force range (force_min,
    force_max buffers and config), which its sigmoid output spans, so every reader of the stored
    model (studies, control, streaming) reads the scaled force."""
    import torch
    g = torch.tensor([float(v) for v in gains], dtype=model.force_min.dtype, device=model.force_min.device)
    with torch.no_grad():
        model.force_min.mul_(g)
        model.force_max.mul_(g)
    lo, hi = model.force_min.cpu().tolist(), model.force_max.cpu().tolist()
    model.config["force_min"] = [round(float(min(a, b)), 6) for a, b in zip(lo, hi)]
    model.config["force_max"] = [round(float(max(a, b)), 6) for a, b in zip(lo, hi)]


def apply(model, paired: Paired, additions: Sequence[str]) -> tuple[object, dict]:
    """A copy of `model` with `additions` applied in ADDITIONS order; (model, info per addition)."""
    from stages.force.align import align_batchnorm
    from stages.m2m.data import take_rows
    out = copy.deepcopy(model)
    info: dict = {}
    todo = [a for a in ADDITIONS if a in set(additions)]
    if todo and paired.count < 2:
        raise ValueError(f"genforce_plus: {paired.count} location-paired frames; the additions need 2 or more")
    for name in todo:
        if name == "mirror_shear":
            out.config["mirror_read"] = "auto"
            info[name] = {"mirrors": list(out.mirrors_for(np.asarray(paired.target["reference"])))}
        elif name == "paired_bn":
            fake = take_rows(paired.translated["images"], paired.rows[0])
            real = take_rows(paired.target["images"], paired.rows[1])
            out = align_batchnorm(out, fake, real, np.asarray(paired.translated["reference"]))
            info[name] = {"pairs": paired.count}
        elif name == "linear_fz":
            info[name] = fit_linear_fz_read(out, paired, LINEAR_FZ_WEIGHT)
        elif name == "shear_gain":
            pred = predict_rows(out, paired.target, paired.rows[1])[:, :2].astype(float)
            gains = [_clip(_gain(pred[:, a], paired.labels[:, a].astype(float))) for a in (0, 1)]
            scale_axes(out, (gains[0], gains[1], 1.0))
            info[name] = {"gain": gains, "pairs": paired.count}
        elif name == "fz_gain":
            on_target = predict_rows(out, paired.target, paired.rows[1])[:, 2].astype(float)
            on_translated = predict_rows(out, paired.translated, paired.rows[0])[:, 2].astype(float)
            raw = _gain(on_target, on_translated)
            scale_axes(out, (1.0, 1.0, _clip(raw)))
            info[name] = {"gain": _clip(raw), "raw": round(raw, 6), "pairs": paired.count}
    return out.eval(), info


def fit_linear_fz_read(model, paired: Paired, weight: float) -> dict:
    """Give `model` a linear Fz read weighted `weight` (stages.force.model.fit_linear_fz): fitted
    on the translated training frames and their compensated labels, each image statistic
    scaled by how the target's paired frames show it against their translations."""
    from stages.force.data import read_runs, run_rows
    from stages.force.model import fit_linear_fz, image_statistics, prepare
    from stages.m2m.data import take_rows
    cfg = model.config
    reference = np.asarray(paired.translated["reference"])

    def stats(images, ref):
        return image_statistics(prepare(images, ref, cfg), cfg["input_mode"]).numpy()
    train = np.concatenate([stats(im, reference) for im in read_runs(paired.translated, "images", paired.runs)])
    fake = stats(take_rows(paired.translated["images"], paired.rows[0]), reference)
    real = stats(take_rows(paired.target["images"], paired.rows[1]), np.asarray(paired.target["reference"]))
    coef, intercept, info = fit_linear_fz(train, paired.train_labels[run_rows(paired.runs), 2],
                                          translated=fake, target=real)
    model.set_linear_fz(coef, intercept, weight)
    return {**info, "coef": [round(float(c), 6) for c in coef], "intercept": round(intercept, 6),
            "weight": float(weight), "pairs": paired.count}
