"""Material compensation of force labels, as the paper states it (Methods, Supp. Text 9).

A sensor's calibration indentation gives the normal force against normalised depth while
loading and while unloading.  Each branch is fitted with a 2nd-degree polynomial of the
normal-force magnitude |Fz|, and a source label at normalised depth d is rescaled by

    r(d) = P_target(d) / P_source(d)

with the loading curves in loading phases and the unloading curves in unloading phases.  All
three axes are scaled by r, as the authors' loader multiplies each ft.csv row by its ratio
(force/com/com_hetero/data_loader.py), and both curves are read at the source's normalised
depth, the depth of the frame the label belongs to.

The twins' curves are fitted through the origin, |Fz|(d) = a d^2 + b d: no force at zero
depth, and the ratio of two such curves stays finite as d -> 0, where it tends to b_t / b_s; it
is then computed in the divided form (a_t d + b_t) / (a_s d + b_s).  Curves with a constant
term (the authors' released coefficient files are plain np.poly1d coefficients) are divided
as they are, where the source's curve is above eps; elsewhere a label keeps its value.

Which curve a frame uses: phase 0 (press) loading; phases 1 and 2 (shear out and back, at
constant depth right after pressing) loading too, since the elastomer has not been unloaded;
phase 3 (release) unloading.  A calibration's curves are fitted on its press and release
frames; its shear leg (phases 1 and 2, where the calibration has one) gives the sensor's
shear-to-normal ratio (:func:`shear_ratio`), which the paper's compensation does not read
(genforce_plus's `shear_calibration` does, stages.force.plus).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

PHASES = (0, 1, 2, 3)          # press, shear out, shear back, release
UNLOADING_PHASES = (3,)
EPS = 1e-6


@dataclass(frozen=True)
class Curves:
    """One sensor's calibration: polynomial coefficients, highest power first (np.polyval
    order), of |Fz| against normalised depth, for the loading and the unloading branch."""
    loading: tuple[float, ...]
    unloading: tuple[float, ...]

    def as_dict(self) -> dict:
        return {"loading": list(self.loading), "unloading": list(self.unloading)}

    @classmethod
    def from_dict(cls, d: Mapping) -> "Curves":
        return cls(tuple(float(v) for v in d["loading"]), tuple(float(v) for v in d["unloading"]))


def _fit_branch(d: np.ndarray, f: np.ndarray, name: str) -> tuple[float, float, float]:
    if d.size < 2 or np.ptp(d) <= 0:
        raise ValueError(f"fit_curves: the {name} branch needs at least 2 distinct depths, "
                         f"got {d.size} frames")
    a, b = np.linalg.lstsq(np.c_[d * d, d], f, rcond=None)[0]
    if not (b > 0 and a + b > 0):       # a d + b > 0 on (0, 1]: P(d) > 0 there
        raise ValueError(f"fit_curves: the {name} curve is not positive on (0, 1] "
                         f"(a={a:.4g}, b={b:.4g}): no usable calibration")
    return (float(a), float(b), 0.0)


def fit_curves(normalised_depth, force, loading) -> Curves:
    """Fit the loading and unloading curves of a calibration: normalised_depth (N,), force
    (N,3) N, loading (N,) bool."""
    d = np.asarray(normalised_depth, float)
    force = np.asarray(force, float)
    loading = np.asarray(loading, bool)
    if force.shape != (d.size, 3) or loading.shape != d.shape:
        raise ValueError(f"fit_curves: normalised_depth {d.shape}, force {force.shape}, loading "
                         f"{loading.shape} must be (N,), (N,3), (N,)")
    f = np.abs(force[:, 2])
    return Curves(_fit_branch(d[loading], f[loading], "loading"),
                  _fit_branch(d[~loading], f[~loading], "unloading"))


def curves_from_calibration(calibration: Mapping) -> Curves:
    """Curves of a calibration: a calibrate[sensor] or capture_calibration[sensor] artifact, or a
    dict with the same arrays (normalised_depth, force, and loading or phase), or one that holds
    the curves' coefficients (an authors_calibration[sensor] artifact: loading_coefficients,
    unloading_coefficients, read from the authors' files)."""
    if "loading_coefficients" in calibration and "unloading_coefficients" in calibration:
        return Curves(tuple(float(v) for v in np.asarray(calibration["loading_coefficients"]).ravel()),
                      tuple(float(v) for v in np.asarray(calibration["unloading_coefficients"]).ravel()))
    missing = [k for k in ("normalised_depth", "force") if k not in calibration]
    if "loading" not in calibration and "phase" not in calibration:
        missing.append("loading or phase")
    if missing:
        raise ValueError(f"calibration: no {', '.join(missing)} (a calibrate or capture_calibration artifact?)")
    depth, force = np.asarray(calibration["normalised_depth"]), np.asarray(calibration["force"])
    if "phase" in calibration:          # press and release: a shear leg is not on the curve
        phase = np.asarray(calibration["phase"])
        loading_mask(phase)
        keep = np.isin(phase, (0,) + UNLOADING_PHASES)
        return fit_curves(depth[keep], force[keep], phase[keep] == 0)
    return fit_curves(depth, force, np.asarray(calibration["loading"]))


def shear_ratio(calibration: Mapping | None) -> float | None:
    """A calibration's shear-to-normal ratio: |(Fx, Fy)| / |Fz| at the far end of its shear leg
    (the phase-1 frames at the largest shift), the mean over them; None for a calibration
    without a shear leg (the authors' coefficient files, a calibration captured without one)
    or whose leg reads no shear (an F/T channel that did not measure it)."""
    if calibration is None or not all(k in calibration for k in ("phase", "shift", "force")):
        return None
    phase, shift = np.asarray(calibration["phase"]), np.asarray(calibration["shift"], float)
    force = np.asarray(calibration["force"], float)
    reach = np.hypot(shift[:, 0], shift[:, 1])
    leg = phase == 1
    if not leg.any() or reach[leg].max() <= 0:
        return None
    far = leg & np.isclose(reach, reach[leg].max())
    normal = np.abs(force[far, 2])
    if np.any(normal <= EPS):
        raise ValueError("shear_ratio: the calibration's shear leg has no normal force")
    ratio = float(np.mean(np.hypot(force[far, 0], force[far, 1]) / normal))
    return ratio if ratio > EPS else None


def loading_mask(phase) -> np.ndarray:
    """True for frames on the loading curve (press and shear phases), False for release."""
    phase = np.asarray(phase)
    bad = ~np.isin(phase, PHASES)
    if bad.any():
        raise ValueError(f"loading_mask: phase values {np.unique(phase[bad]).tolist()} are not in {PHASES}")
    return ~np.isin(phase, UNLOADING_PHASES)


def _through_origin(c: tuple[float, ...]) -> bool:
    return len(c) >= 2 and c[-1] == 0.0


def label_scale(normalised_depth, loading, source: Curves, target: Curves, eps: float = EPS) -> np.ndarray:
    """r(d) = P_target(d) / P_source(d) per frame, on the loading or unloading branch."""
    d = np.maximum(np.asarray(normalised_depth, float), 0.0)
    loading = np.asarray(loading, bool)
    if d.shape != loading.shape:
        raise ValueError(f"label_scale: normalised_depth {d.shape} and loading {loading.shape} differ")
    out = np.ones(d.shape)
    for mask, s, t in ((loading, source.loading, target.loading),
                       (~loading, source.unloading, target.unloading)):
        x = d[mask]
        if _through_origin(s) and _through_origin(t):
            # P(d) / d: the slope form, finite at d = 0; clamped where a curve bends down past d = 1
            num = np.maximum(np.polyval(t[:-1], x), eps)
            den = np.maximum(np.polyval(s[:-1], x), eps)
            out[mask] = num / den
        else:
            num, den = np.polyval(t, x), np.polyval(s, x)
            ok = den > eps
            out[mask] = np.where(ok, num / np.where(ok, den, 1.0), 1.0)
    return out


def compensate(force, normalised_depth, loading, source: Curves, target: Curves, eps: float = EPS) -> np.ndarray:
    """Source labels (N,3) rescaled to the target's material: every axis times r(d).
    Identical source and target curves return the labels unchanged, bit for bit."""
    force = np.asarray(force)
    if force.ndim != 2 or force.shape[1] != 3:
        raise ValueError(f"compensate: force must be (N,3), got {force.shape}")
    if source == target:
        return force.copy()
    scale = label_scale(normalised_depth, loading, source, target, eps)
    if scale.shape != force.shape[:1]:
        raise ValueError(f"compensate: {force.shape[0]} forces but {scale.shape[0]} depths")
    return (force * scale[:, None]).astype(force.dtype)


def curves_figure(calibrations: Mapping[str, tuple[Mapping, Curves]], title: str):
    """PNG bytes: calibration points (where the calibration has them) and fitted curves,
    loading solid and unloading dashed, for each named sensor: name -> (calibration, Curves)."""
    from matplotlib.figure import Figure

    from stages.figures import figure_png
    fig = Figure(figsize=(4.8, 3.6))
    ax = fig.add_subplot()
    grid = np.linspace(0.0, 1.0, 50)
    for k, (name, (cal, curves)) in enumerate(calibrations.items()):
        colour = f"C{k}"
        if "normalised_depth" in cal and "force" in cal:
            d, f = np.asarray(cal["normalised_depth"]), np.abs(np.asarray(cal["force"])[:, 2])
            load = (np.asarray(cal["loading"], bool) if "loading" in cal
                    else loading_mask(np.asarray(cal["phase"])))
            ax.plot(d[load], f[load], ".", color=colour, ms=3, alpha=0.6)
            ax.plot(d[~load], f[~load], "x", color=colour, ms=3, alpha=0.6)
        ax.plot(grid, np.polyval(curves.loading, grid), "-", color=colour, label=f"{name} loading")
        ax.plot(grid, np.polyval(curves.unloading, grid), "--", color=colour, label=f"{name} unloading")
    ax.set(xlabel="normalised depth", ylabel="|Fz| (N)", title=title)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return figure_png(fig)
