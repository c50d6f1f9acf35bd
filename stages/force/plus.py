"""genforce_plus: the paper's genforce_comp model with our additions, each label-free.

Every addition reads only what a lab has without a force label of the target: the target's
no-contact image and the two sensors' material calibrations (TargetView).  Each is applied
after training, to a copy of genforce_comp's model, so the ablation
(stages.force.study.ablation_study) can take each one away in turn from models of several
seeds without retraining.

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
  punch_calibration
                the whole read rescaled from the compensation of the calibration prism to that
                of a flat punch (params plus.punch_indenter; node calibrate_punch: the same
                indentations, to the same depths): the least-squares factor that takes the
                source's training labels compensated with the prism's curves to the same labels
                compensated with the punch's (punch_scale).  One indenter's curves fix the
                ratio of two sensors' forces at every normalised depth, but where the sensors
                press to different depths (TacTip 4.5 mm against GelSight's 1 mm) that ratio
                depends on how the indenter's contact grows with depth: a knife edge's contact
                grows with it on TacTip's dome, a flat face's does not, and most training
                indenters press with a flat face.  Without punch calibrations of both sensors
                (the authors' sets, a captured calibration) the read is left as it is.

Which additions a genforce_plus model carries is the params' `plus.additions`; each one kept
there has beaten the seed spread on the validation indenters
(ablation/<study>/<addition>/delta_mae_total or delta_mae_fz_light against the seed spread).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

ADDITIONS = ("mirror_shear", "shear_calibration", "punch_calibration")


@dataclass
class TargetView:
    """What the additions read of the target, none of it a force label: its no-contact image
    (H,W), the shear-to-normal ratios of the source's and the target's calibrations
    ({"source", "target"}; None: either has none) and the punch calibrations' rescaling of the
    compensated labels (punch_scale; None: either sensor has no punch calibration)."""
    reference: np.ndarray
    shear_ratios: Mapping | None = None
    punch_scale: float | None = None


def target_view(target_markers: Mapping, shear_ratios: Mapping | None = None,
                punch_scale: float | None = None) -> TargetView:
    """The TargetView of the target's own collection `target_markers`: its reference image."""
    if target_markers is None or "reference" not in target_markers:
        raise ValueError("genforce_plus needs the target's own collection (target_markers) for its reference image")
    reference = np.asarray(target_markers["reference"])
    return TargetView(reference, shear_ratios, punch_scale)


def punch_scale(force, normalised_depth, loading, prism: Mapping, punch: Mapping) -> float:
    """The least-squares k with k * (labels compensated with the prism's curves) closest to the
    labels compensated with the punch's: `force` (N,3) the source's training labels at
    `normalised_depth` (N,) on the `loading` (N,) branch; prism and punch: {"source",
    "target": Curves}.  1.0 for labels that carry no force."""
    from stages.force.compensation import label_scale
    force = np.asarray(force, float)
    by = {name: force * label_scale(normalised_depth, loading, curves["source"], curves["target"])[:, None]
          for name, curves in (("prism", prism), ("punch", punch))}
    norm = float(np.sum(by["prism"] ** 2))
    return float(np.sum(by["prism"] * by["punch"]) / norm) if norm > 0 else 1.0


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
    """A copy of `model` with `additions` applied in ADDITIONS order; (model, info per
    addition)."""
    out = copy.deepcopy(model)
    info: dict = {}
    for name in [a for a in ADDITIONS if a in set(additions)]:
        if name == "mirror_shear":
            out.config["mirror_read"] = "auto"
            info[name] = {"mirrors": list(out.mirrors_for(target.reference))}
        elif name == "shear_calibration":
            info[name] = scale_shear(out, target.shear_ratios)
        elif name == "punch_calibration":
            info[name] = scale_read(out, target.punch_scale)
    return out.eval(), info


def _scale_range(model, scale) -> None:
    """Multiply `model`'s force range (force_min, force_max; N) by `scale` (3,) per axis."""
    import torch
    lo = np.asarray(model.config["force_min"], float) * scale
    hi = np.asarray(model.config["force_max"], float) * scale
    model.config["force_min"], model.config["force_max"] = lo.round(6).tolist(), hi.round(6).tolist()
    model.force_min.copy_(torch.tensor(model.config["force_min"], dtype=torch.float32))
    model.force_max.copy_(torch.tensor(model.config["force_max"], dtype=torch.float32))


def scale_read(model, scale: float | None) -> dict:
    """Scale `model`'s whole read (its three axes' force range) by `scale` (punch_scale); with
    None the model is left as it is.  The info: the scale."""
    if scale is None:
        return {"scale": 1.0, "calibrated": False}
    scale = float(scale)
    if not (scale > 0 and np.isfinite(scale)):
        raise ValueError(f"punch_calibration: scale {scale} must be positive")
    _scale_range(model, np.full(3, scale))
    return {"scale": round(scale, 6), "calibrated": True}


def scale_shear(model, ratios: Mapping | None) -> dict:
    """Scale `model`'s shear read by ratios["target"] / ratios["source"] (its shear axes' force
    range times that factor: the sigmoid's reading maps to that many times the force); with
    no ratios (None, or either None) the model is left as it is.  The info: the scale and the
    ratios."""
    if not ratios or ratios.get("source") is None or ratios.get("target") is None:
        return {"scale": 1.0, "calibrated": False}
    src, tgt = float(ratios["source"]), float(ratios["target"])
    if not (src > 0 and tgt > 0 and np.isfinite(src) and np.isfinite(tgt)):
        raise ValueError(f"shear_calibration: shear-to-normal ratios {src} -> {tgt} must be positive")
    scale = tgt / src
    _scale_range(model, np.array([scale, scale, 1.0]))
    return {"scale": round(scale, 6), "calibrated": True, "source_ratio": round(src, 6),
            "target_ratio": round(tgt, 6)}
