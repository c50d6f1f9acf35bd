"""genforce_plus: the paper's genforce_comp model with our additions, each label-free.

Every addition is applied after training, to a copy of the genforce_comp model, and reads only
what a lab has without a force label of the target: the target's no-contact image and the two
sensors' material calibrations (TargetView).  So an addition costs no retraining, and the ablation (stages.force.study.ablation_study) can take each one away in
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

Which additions a genforce_plus model carries is the params' `plus.additions`; each one kept
there has beaten the seed spread on the validation indenters
(ablation/<study>/<addition>/delta_mae_total against ablation/<study>/seed_spread/mae_total).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

ADDITIONS = ("mirror_shear", "shear_calibration")


@dataclass
class TargetView:
    """What the additions read of the target, none of it a force label: its no-contact image
    (H,W) and the shear-to-normal ratios of the source's and the target's calibrations
    ({"source", "target"}; None: either has none)."""
    reference: np.ndarray
    shear_ratios: Mapping | None = None


def target_view(target_markers: Mapping, shear_ratios: Mapping | None = None) -> TargetView:
    """The TargetView of the target's own collection `target_markers` (its reference image)."""
    if target_markers is None or "reference" not in target_markers:
        raise ValueError("genforce_plus needs the target's own collection (target_markers) for its reference image")
    return TargetView(np.asarray(target_markers["reference"]), shear_ratios)


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


def apply(model, target: TargetView, additions: Sequence[str]) -> tuple[object, dict]:
    """A copy of `model` with `additions` applied in ADDITIONS order; (model, info per addition)."""
    out = copy.deepcopy(model)
    info: dict = {}
    for name in [a for a in ADDITIONS if a in set(additions)]:
        if name == "mirror_shear":
            out.config["mirror_read"] = "auto"
            info[name] = {"mirrors": list(out.mirrors_for(target.reference))}
        elif name == "shear_calibration":
            info[name] = scale_shear(out, target.shear_ratios)
    return out.eval(), info


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
