"""genforce_plus: the paper's genforce_comp model with our additions, each label-free.

Every addition is applied after training, to a copy of the genforce_comp model, and reads only
what GenForce already has without a force label of the target: the translations and the
source's compensated labels, and the location-paired frames of the target's own
collection on the training indenters that fine-tune M2M (images only).  So an addition costs
no retraining, and the ablation (stages.force.study.ablation_study) can take each one away in
turn from models of several seeds.

The additions, in the order they are applied (ADDITIONS):

  mirror_shear  the model reads a frame's shear as the odd part of its readings of the frame and
                of the frame's mirror images under which the target's reference looks the same
                (stages.force.model, mirror_read "auto"): the even part is error.
  shear_calibration
                the shear read scaled by the ratio of the two sensors' shear-to-normal ratios
                in their calibrations' shear legs (stages.force.compensation.shear_ratio,
                target over source): the paper's compensation scales shear by the normal
                force's curves, and a sensor's shear stiffness against its normal stiffness
                (how deep it presses for its shear stroke, its friction) is not in them.
                Without a shear leg in both calibrations the read is left as it is.
  linear_fz     Fz read as the mean of the network's reading and a linear read of how much the
                frame changes against the reference (stages.force.model.fit_linear_fz, fitted on
                the translated training frames and their compensated labels, each image
                statistic scaled by how the target's paired frames show it against their
                translations): the network's Fz cannot leave its training labels' range.

Which additions a genforce_plus model carries is the params' `plus.additions`; each one kept
there has beaten the seed spread on the validation indenters
(ablation/<study>/<addition>/delta_mae_total against ablation/<study>/seed_spread/mae_total).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from stages.force.data import paired_rows

ADDITIONS = ("mirror_shear", "shear_calibration", "linear_fz")
LINEAR_FZ_WEIGHT = 0.5         # linear_fz: the plain mean of the two reads


@dataclass
class Paired:
    """What the additions read: the location-paired frames of the translations and the target
    (rows (2,K)), the compensated source labels (K,3) of the translated ones, and the training
    contacts (runs of the translations) with their compensated labels (N,3, every row), and
    the shear-to-normal ratios of the source's and the target's calibrations (None: none)."""
    translated: Mapping
    target: Mapping
    rows: np.ndarray
    labels: np.ndarray
    runs: list
    train_labels: np.ndarray
    shear_ratios: Mapping | None = None

    @property
    def count(self) -> int:
        return int(self.rows.shape[1])


def paired_frames(translated: Mapping, target_markers: Mapping, labels: np.ndarray,
                  indenters: Sequence[str] | None, pairs: int, shear_ratios: Mapping | None = None) -> Paired:
    """The Paired the additions read: `pairs` location-paired frames of `indenters` (the
    training indenters, whose contacts are the training runs), `labels` (N,3) the translated
    rows' compensated labels, `shear_ratios` {"source", "target"} the calibrations'
    shear-to-normal ratios (compensation.shear_ratio; None where either has none)."""
    from stages.force.data import contact_runs
    if target_markers is None or "images" not in target_markers:
        raise ValueError("genforce_plus needs the target's own paired frames (target_markers)")
    _, rows = paired_rows(translated, target_markers, indenters, pairs)
    labels = np.asarray(labels, np.float32)
    return Paired(translated, target_markers, rows, labels[rows[0]],
                  contact_runs(translated, indenters), labels, shear_ratios)


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


def apply(model, paired: Paired, additions: Sequence[str]) -> tuple[object, dict]:
    """A copy of `model` with `additions` applied in ADDITIONS order; (model, info per addition)."""
    out = copy.deepcopy(model)
    info: dict = {}
    todo = [a for a in ADDITIONS if a in set(additions)]
    if todo and paired.count < 2:
        raise ValueError(f"genforce_plus: {paired.count} location-paired frames; the additions need 2 or more")
    for name in todo:
        if name == "mirror_shear":
            out.config["mirror_read"] = "auto"
            info[name] = {"mirrors": list(out.mirrors_for(np.asarray(paired.target["reference"])))}
        elif name == "shear_calibration":
            info[name] = scale_shear(out, paired.shear_ratios)
        elif name == "linear_fz":
            info[name] = fit_linear_fz_read(out, paired, LINEAR_FZ_WEIGHT)
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


def scale_shear(model, ratios: Mapping | None) -> dict:
    """Scale `model`'s shear read by ratios["target"] / ratios["source"] (its shear axes' force
    range times that factor: the sigmoid's reading maps to that many times the force); with
    no ratios (None, or either None) the model is left as it is.  The info: the scale and the
    ratios."""
    import torch
    if not ratios or ratios.get("source") is None or ratios.get("target") is None:
        return {"scale": 1.0, "calibrated": False}
    src, tgt = float(ratios["source"]), float(ratios["target"])
    if not (src > 0 and tgt > 0 and np.isfinite(src) and np.isfinite(tgt)):
        raise ValueError(f"shear_calibration: shear-to-normal ratios {src} -> {tgt} must be positive")
    scale = tgt / src
    lo, hi = np.asarray(model.config["force_min"], float), np.asarray(model.config["force_max"], float)
    lo[:2], hi[:2] = lo[:2] * scale, hi[:2] * scale
    model.config["force_min"], model.config["force_max"] = lo.round(6).tolist(), hi.round(6).tolist()
    model.force_min.copy_(torch.tensor(model.config["force_min"], dtype=torch.float32))
    model.force_max.copy_(torch.tensor(model.config["force_max"], dtype=torch.float32))
    return {"scale": round(scale, 6), "calibrated": True, "source_ratio": round(src, 6),
            "target_ratio": round(tgt, 6)}
