"""genforce_plus: the paper's genforce_comp model with our additions, each label-free.

Every addition reads only what a lab has without a force label of the target: the target's
no-contact image, its rest frames (the robot's record says where the indenter was off the skin)
and the two sensors' material calibrations (TargetView).  One addition is applied in training
(TRAINED): a fine-tune of genforce_comp's weights with its labels on the translations that the
addition changes (genforce_comp's schedule, plus.rest_noise_length times as long); the others
after training, to a copy of that model (of genforce_comp where nothing is trained).  So the
ablation (stages.force.study.ablation_study) can take each one away in turn from models of
several seeds without retraining: the transfer keeps the trained weights (`plus_base`) beside
genforce_comp's.

The additions, in the order they are applied (ADDITIONS):

  rest_noise    the translations carry the target's rest noise.  A translator draws a frame the
                way the target's frames look on average: where nothing moved it draws the
                target's reference exactly, while a real frame at rest differs from it in the
                pixels that its camera noise tips over the segmentation threshold (about 0.1%
                of a GelSight frame's).  A model trained on the clean translations reads that
                noise as force, about as much as the light contact a grasp needs.  Each
                translated frame takes, in the pixels where one of the target's rest frames
                (drawn at random) differs from the target's reference, that rest frame's
                values.  Rest frames: the release frames at depth 0 of the target's
                contacts of the training indenters.  Translations that already carry as much
                noise (a translation between skins of one marker pattern is the source's own
                frames, noise and all) are left as they are, and so is a target without rest
                frames (its collection records no depth): genforce_plus then starts from
                genforce_comp's weights.
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

ADDITIONS = ("rest_noise", "mirror_shear", "shear_calibration", "punch_calibration")
TRAINED = ("rest_noise",)          # applied in training (a fine-tune of genforce_comp)
NOISE_SHARE = 0.5                  # translations whose rest frames differ from the target's reference
                                   # in at least this share of the target's rest noise carry it already


@dataclass
class TargetView:
    """What the additions read of the target, none of it a force label: its no-contact image
    (H,W), the shear-to-normal ratios of the source's and the target's calibrations
    ({"source", "target"}; None: either has none), its rest frames (K,H,W) (none: (0,H,W))
    and the punch calibrations' rescaling of the compensated labels (punch_scale; None: either
    sensor has no punch calibration)."""
    reference: np.ndarray
    shear_ratios: Mapping | None = None
    rest: np.ndarray | None = None
    punch_scale: float | None = None


def target_view(target_markers: Mapping, shear_ratios: Mapping | None = None,
                indenters: Sequence[str] | None = None, punch_scale: float | None = None) -> TargetView:
    """The TargetView of the target's own collection `target_markers`: its reference image and
    its rest frames among the contacts of `indenters` (None: all)."""
    if target_markers is None or "reference" not in target_markers:
        raise ValueError("genforce_plus needs the target's own collection (target_markers) for its reference image")
    reference = np.asarray(target_markers["reference"])
    return TargetView(reference, shear_ratios, rest_frames(target_markers, indenters, reference), punch_scale)


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


def rest_rows(art: Mapping, indenters: Sequence[str] | None = None) -> np.ndarray:
    """The rows of `art`'s rest frames: release frames at depth 0 (the robot's record: the
    indenter is off the skin) of its contacts of `indenters` (None: all); no rows where `art`
    records no `depth` or `phase`."""
    from stages.force.compensation import UNLOADING_PHASES
    from stages.force.data import contact_runs, run_rows
    if "depth" not in art or "phase" not in art:
        return np.zeros(0, int)
    rows = run_rows(contact_runs(art, indenters))
    depth, phase = np.asarray(art["depth"])[rows], np.asarray(art["phase"])[rows]
    return rows[np.isin(phase, UNLOADING_PHASES) & (depth == 0)]


def rest_frames(art: Mapping, indenters: Sequence[str] | None, reference: np.ndarray) -> np.ndarray:
    """`art`'s rest frames (K,H,W) (rest_rows); (0,H,W) of `reference`'s shape where it has none."""
    rows = rest_rows(art, indenters)
    if not rows.size:
        return np.zeros((0,) + reference.shape, reference.dtype)
    return np.stack([np.asarray(art["images"][int(r)]) for r in rows])


def noise_share(frames: np.ndarray, reference: np.ndarray) -> float:
    """The mean share of pixels in which `frames` (K,H,W) differ from `reference` (0 for none)."""
    return float(np.mean(frames != reference[None])) if len(frames) else 0.0


def rest_noise(images: np.ndarray, view: TargetView, seed) -> np.ndarray:
    """`images` (N,H,W), each taking, where a random one of view.rest differs from
    view.reference, that rest frame's values (rest_noise in the module's docstring); `seed`
    (an int or a tuple of ints) draws the rest frames."""
    if view.rest is None or not len(view.rest):
        raise ValueError("rest_noise: the target has no rest frames")
    rng = np.random.default_rng(seed)
    pick = rng.integers(0, len(view.rest), len(images))
    masks = view.rest != view.reference[None]
    out = np.array(images, copy=True)
    for k, j in enumerate(pick):
        out[k][masks[j]] = view.rest[j][masks[j]]
    return out


def rest_noise_plan(translated: Mapping, view: TargetView, indenters: Sequence[str] | None) -> dict:
    """Whether rest_noise changes these translations: {"applied", "rest_frames", "target_share",
    "translation_share"} (the rest noise's pixel shares of the target's rest frames and of the
    translations' own rest frames)."""
    rest = view.rest if view.rest is not None else np.zeros((0,) + view.reference.shape)
    own = rest_frames(translated, indenters, view.reference)
    target, trans = noise_share(rest, view.reference), noise_share(own, view.reference)
    applied = bool(len(rest) and target > 0 and trans < NOISE_SHARE * target)
    return {"applied": applied, "rest_frames": int(len(rest)), "target_share": round(target, 8),
            "translation_share": round(trans, 8)}


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
    """A copy of `model` with the after-training ones of `additions` applied in ADDITIONS order
    (a TRAINED one is in the weights already); (model, info per addition applied here)."""
    out = copy.deepcopy(model)
    info: dict = {}
    for name in [a for a in ADDITIONS if a in set(additions) and a not in TRAINED]:
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
