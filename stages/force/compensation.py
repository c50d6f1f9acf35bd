"""Material compensation of force labels (paper, Methods and Supp. Text 9).

A sensor's calibration indentation gives the normal force against normalised depth while
loading and while unloading.  Each branch is fitted with a 2nd-degree polynomial of the
normal-force magnitude |Fz|,

    |Fz|(d) = a d^2 + b d        (d = normalised depth)

with no constant term: there is no force at zero depth, and the ratio of two such polynomials
stays finite as d -> 0, where it tends to the ratio of the curves' slopes b_t / b_s.  So the
label scale

    r(d) = P_target(d) / P_source(d) = (a_t d + b_t) / (a_s d + b_s)

is computed in this divided form at every depth and small depths need no special case.
:func:`fit_curves` refuses a curve that is not positive on (0, 1]; ``eps`` guards the secant
slope a d + b past the calibrated range (d > 1), where a fitted curve may bend down to zero:
both slopes are clamped to at least eps.

Shear: the paper scales all three axes by the normal-force ratio (mode "normal"), which holds
while the sensors' shear-to-normal force ratios agree (one elastomer family: GelSight r6 and
r18 differ by 10%).  Across sensor kinds they do not (the TacTip twin's dome shears at about a
third of GelSight's ratio), so mode "axes" also scales Fx, Fy by the ratio of the two sensors'
shear gains: a calibration with a shear leg at d_max (calibration_trajectory shear_mm) gives
gain = sum |F_xy| / sum |F_z| over its shear-out frames, and shear labels are scaled by
r(d) * gain_target / gain_source, divided by the depth ratio k below where the two sensors'
collections reach different normalised depths (shear_ratio: a sticking shear's force does not
grow with depth, the punch's normal force does, so a gain read deeper is smaller).  Without a
shear leg on both sides "axes" is "normal".

Contact (mode "contact"): "axes" labels for the translations, and a second set for the
target's own frames at the same locations, which a transfer's shear read-out is calibrated
against (stages.force.nodes.shear_readout, `force.readout`).  Where the target's collection
presses deeper than the source's (TacTip's dome 4.5 mm, the flat pads 1 mm) the source's shear
says little about the target's: a GelSight or uSkin pad slides under most presses (|F_xy| /
|F_z| at its friction coefficient, 0.55-0.60) while TacTip's deep contact sticks, and sticks
harder under a rounded face than a flat one (Mindlin: a sticking contact of radius a sheared
by delta carries 8 G* a delta, while its normal force is 2 a E* d under a punch, 4/3 a E* d
under a sphere and a E* d under a cone).  The target's own sticking contact
(:func:`contact_shear`) gives its shear instead: the calibration's shear leg gives the
stiffness per mm of shift at the punch's contact (:func:`shear_stiffness`), scaled by the
paired frame's contact radius over the punch's, sqrt(area / punch area), from the indenter's
geometry pressed to the target's depth (stages.force.nodes.contact_labels), and capped at the
target's friction times its compensated normal force (sliding).  On the twins that is
TacTip's shear at R2 0.97/0.97 (Fx/Fy, unseen indenters; "axes" 0.61/0.63) from GelSight and
0.97/0.98 from uSkin.  Those labels do not train the regressor: a translated frame keeps much
of the source's deformation, and the label it needs is the force under the deformation it
shows, which "axes" gives (every translated frame labelled by the contact model: GelSight ->
TacTip R2 0.78/0.73/0.85 -> 0.77/0.56/0.80).  Where the two press as deep the target's frames
carry the "axes" labels.  Where the target presses shallower (TacTip -> a flat pad) its pad
slides under much of a contact that sticks on the source (|F_xy| / |F_z| at its friction on a
quarter of the paired frames), and what slid out under the shear leg is sheared back when the
indenter returns, which the per-frame law reads as no shear (R2 0.76, "axes" 0.32-0.46): the
same law walked through each contact with its slip remembered (:func:`slip_shear`) labels
those frames at R2 0.87-0.88 (TacTip to GelSight and to the uSkin, training indenters).

Depth: each curve is a function of its own sensor's normalised depth (depth / the sensor's
calibration d_max).  A location-paired frame presses every sensor to the same fraction of its
collection depth, which is the same normalised depth only when each sensor's d_max is its
collection depth (the paper's heterogeneous calibrations: 1 mm GelSight and uSkin, 4.5 mm
TacTip).  Where they differ (the twins' GelSight is calibrated to the material study's 1.4 mm
but collected to 1 mm, so its frames reach normalised depth 0.714 while uSkin's and TacTip's
reach 1), ``depth_ratio`` k maps the source's normalised depth d to the target's, k d, with
k = the target collection's deepest normalised depth / the source's (:func:`depth_ratio`), and

    r(d) = P_target(k d) / P_source(d) = k (a_t k d + b_t) / (a_s d + b_s).

k = 1 (sensors of one depth range, every homogeneous and material pair) is the formula above
exactly.

Calibration indenter: the curves are only a material prior if the indenter's contact does
not change shape with depth.  A flat punch's does not (F = 2 a E* d on a half-space,
Sneddon; the pad's thickness only stiffens the slope), so every sensor's punch curve is near
linear and their ratio is the skins' stiffness ratio.  The paper's prism and cone make
contacts that grow with depth, and grow differently on TacTip's dome pressed 4.5 mm than on a
flat pad pressed 1 mm (the twins' prism curves bend a/b = 0.22 on uSkin, 3.2 on TacTip),
which puts the prism's own shape into every label.  The default calibration is therefore the
4 mm flat punch `calib_punch` (params.yaml, calibration_trajectory.indenter).

Which curve a frame uses: phase 0 (press) loading; phases 1 and 2 (shear out and back, at
constant depth right after pressing) loading too, since the elastomer has not been unloaded
(the simulation twin uses the loading stiffness there); phase 3 (release) unloading.  A
calibration's own shear leg is left out of its curves.

The authors' released curves (stages.capture.authors_calibration) are polynomials of any
degree, np.poly1d's coefficients as their files hold them, and need not pass through the
origin: for those r(d) = P_target(k d) / P_source(d) as it stands (their loaders' ratio), and
1 where either curve is not positive (a fitted curve's small negative constant near d = 0
would otherwise flip or blow up the labels).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

PHASES = (0, 1, 2, 3)          # press, shear out, shear back, release
UNLOADING_PHASES = (3,)
MODES = ("normal", "axes", "contact")


@dataclass(frozen=True)
class Curves:
    """One sensor's calibration: polynomial coefficients, highest power first (np.polyval
    order), of |Fz| against normalised depth for each branch ((a, b, 0) when fitted here; any
    degree from the authors' files), and the shear gain (|F_xy| / |F_z| on the shear leg; None
    without one)."""
    loading: tuple[float, float, float]
    unloading: tuple[float, float, float]
    shear_gain: float | None = None

    def as_dict(self) -> dict:
        return {"loading": list(self.loading), "unloading": list(self.unloading),
                "shear_gain": self.shear_gain}

    @classmethod
    def from_dict(cls, d: Mapping) -> "Curves":
        gain = d.get("shear_gain")
        return cls(tuple(float(v) for v in d["loading"]), tuple(float(v) for v in d["unloading"]),
                   None if gain is None else float(gain))


def _fit_branch(d: np.ndarray, f: np.ndarray, name: str) -> tuple[float, float, float]:
    if d.size < 2 or np.ptp(d) <= 0:
        raise ValueError(f"fit_curves: the {name} branch needs at least 2 distinct depths, "
                         f"got {d.size} frames")
    a, b = np.linalg.lstsq(np.c_[d * d, d], f, rcond=None)[0]
    if not (b > 0 and a + b > 0):       # a d + b > 0 on (0, 1]: P(d) > 0 there
        raise ValueError(f"fit_curves: the {name} curve is not positive on (0, 1] "
                         f"(a={a:.4g}, b={b:.4g}): no usable calibration")
    return (float(a), float(b), 0.0)


def _branches(loading, phase=None) -> tuple[np.ndarray, np.ndarray]:
    """(press, release) masks of a calibration's frames: loading frames minus any shear leg
    (phases 1-2, when `phase` is given), and the unloading frames."""
    loading = np.asarray(loading, bool)
    press = loading if phase is None else loading & (np.asarray(phase) == 0)
    return press, ~loading


def fit_curves(normalised_depth, force, loading, phase=None) -> Curves:
    """Fit the loading and unloading curves of a calibration (calibrate artifact arrays:
    normalised_depth (N,), force (N,3) N, loading (N,) bool, and phase (N,) if it has a shear
    leg: phases 1-2 then give the shear gain and stay out of the curves)."""
    d = np.asarray(normalised_depth, float)
    force = np.asarray(force, float)
    loading = np.asarray(loading, bool)
    if force.shape != (d.size, 3) or loading.shape != d.shape:
        raise ValueError(f"fit_curves: normalised_depth {d.shape}, force {force.shape}, loading "
                         f"{loading.shape} must be (N,), (N,3), (N,)")
    if phase is not None and np.shape(phase) != d.shape:
        raise ValueError(f"fit_curves: phase {np.shape(phase)} and normalised_depth {d.shape} differ")
    f = np.abs(force[:, 2])
    press, release = _branches(loading, phase)
    gain = None
    if phase is not None:
        out = np.asarray(phase) == 1
        if out.any():
            normal = f[out].sum()
            if not normal > 0:
                raise ValueError("fit_curves: the shear leg has no normal force: no shear gain")
            gain = float(np.hypot(force[out, 0], force[out, 1]).sum() / normal)
    return Curves(_fit_branch(d[press], f[press], "loading"),
                  _fit_branch(d[release], f[release], "unloading"), gain)


def curves_from_calibration(calibration: Mapping) -> Curves:
    """Curves of a calibrate[sensor] artifact, a capture_calibration[sensor] one or a dict with
    the same arrays: normalised_depth, force, and loading or phase (loading_mask of it; a
    captured calibration records the phase only).  An authors_calibration[sensor] artifact
    holds its curves' coefficients (loading_coefficients, unloading_coefficients): those."""
    if "loading_coefficients" in calibration:
        return Curves(tuple(float(v) for v in np.asarray(calibration["loading_coefficients"]).ravel()),
                      tuple(float(v) for v in np.asarray(calibration["unloading_coefficients"]).ravel()))
    loading, phase = _calibration_phases(calibration)
    return fit_curves(np.asarray(calibration["normalised_depth"]), np.asarray(calibration["force"]),
                      loading, phase)


def _calibration_phases(calibration: Mapping) -> tuple[np.ndarray, np.ndarray | None]:
    """(loading (N,) bool, phase (N,) or None) of a calibration (curves_from_calibration)."""
    missing = [k for k in ("normalised_depth", "force") if k not in calibration]
    if "loading" not in calibration and "phase" not in calibration:
        missing.append("loading or phase")
    if missing:
        raise ValueError(f"calibration: no {', '.join(missing)} (a calibrate or capture_calibration artifact?)")
    phase = np.asarray(calibration["phase"]) if "phase" in calibration else None
    loading = np.asarray(calibration["loading"]) if "loading" in calibration else loading_mask(phase)
    return loading, phase


def loading_mask(phase) -> np.ndarray:
    """True for frames on the loading curve (press and shear phases), False for release."""
    phase = np.asarray(phase)
    bad = ~np.isin(phase, PHASES)
    if bad.any():
        raise ValueError(f"loading_mask: phase values {np.unique(phase[bad]).tolist()} are not in {PHASES}")
    return ~np.isin(phase, UNLOADING_PHASES)


def depth_ratio(source_depth, target_depth) -> float:
    """k: the target's normalised depth per unit of the source's at a location-paired frame,
    from the two collections' normalised depths (N,): the ratio of their deepest frames, the
    protocol's common depth 1."""
    deepest = []
    for name, d in (("source", source_depth), ("target", target_depth)):
        d = np.asarray(d, float)
        top = float(np.max(d)) if d.size else float("nan")
        if not (np.isfinite(top) and top > 0):
            raise ValueError(f"depth_ratio: the {name} collection's normalised depth has no positive "
                             f"maximum (got {top})")
        deepest.append(top)
    return deepest[1] / deepest[0]


def label_scale(normalised_depth, loading, source: Curves, target: Curves, eps: float = 1e-6,
                depth_ratio: float = 1.0) -> np.ndarray:
    """r(d) = P_target(k d) / P_source(d) per frame (k = depth_ratio), in the divided (slope)
    form; see the module."""
    d = np.maximum(np.asarray(normalised_depth, float), 0.0)
    loading = np.asarray(loading, bool)
    if d.shape != loading.shape:
        raise ValueError(f"label_scale: normalised_depth {d.shape} and loading {loading.shape} differ")
    k = float(depth_ratio)
    if not (np.isfinite(k) and k > 0):
        raise ValueError(f"label_scale: depth_ratio must be a positive number, got {depth_ratio!r}")

    if all(c.loading[-1] == 0 and c.unloading[-1] == 0 for c in (source, target)):
        def slope(c: Curves, x):                            # P(x) / x: through the origin
            return np.maximum(np.where(loading, np.polyval(c.loading[:-1], x),
                                       np.polyval(c.unloading[:-1], x)), eps)

        return k * slope(target, k * d) / slope(source, d)     # k = 1: exact, x * 1.0 == x

    def value(c: Curves, x):
        return np.where(loading, np.polyval(c.loading, x), np.polyval(c.unloading, x))

    top, bottom = value(target, k * d), value(source, d)
    ok = (top > eps) & (bottom > eps)
    return np.where(ok, top / np.where(ok, bottom, 1.0), 1.0)


def shear_ratio(source: Curves, target: Curves, mode: str, depth_ratio: float = 1.0) -> float:
    """The extra factor on Fx, Fy: gain_target / gain_source / depth_ratio in modes "axes" and
    "contact" when both calibrations have a shear leg, else 1 (the paper's "normal" mode).  Each gain is
    measured at its calibration's d_max; a paired frame at the source's normalised depth d
    meets the target at depth_ratio * d, and a shear that sticks keeps its force while the
    flat punch's normal force grows with depth (Mindlin against Sneddon), so a gain read at
    normalised depth x is gain / x and the ratio at the collection is the gains' ratio over
    depth_ratio (1 for sensors of one depth range)."""
    if mode not in MODES:
        raise ValueError(f"compensation mode {mode!r} is not one of {MODES}")
    if mode == "normal" or source.shear_gain is None or target.shear_gain is None:
        return 1.0
    if not (source.shear_gain > 0 and target.shear_gain > 0):
        raise ValueError(f"shear gains {source.shear_gain} / {target.shear_gain} must be positive")
    if not depth_ratio > 0:
        raise ValueError(f"depth_ratio {depth_ratio} must be positive")
    return target.shear_gain / source.shear_gain / float(depth_ratio)


def shear_stiffness(calibration: Mapping) -> float:
    """k (N per mm of shift): the least-squares slope of the shear force against the shift over
    a calibration's shear-out frames (phase 1), signed as the twin's force is."""
    if "phase" not in calibration or "shift" not in calibration:
        raise ValueError("shear_stiffness: the calibration has no shear leg (phase and shift): "
                         "compensation 'contact' needs calibration_trajectory.shear_mm > 0")
    out = np.asarray(calibration["phase"]) == 1
    shift = np.asarray(calibration["shift"], float)[out]
    force = np.asarray(calibration["force"], float)[out, :2]
    moved = float(np.sum(shift * shift))
    if not moved > 0:
        raise ValueError("shear_stiffness: the calibration's shear leg does not move (no shear-out "
                         "frames with a shift): compensation 'contact' needs calibration_trajectory.shear_mm > 0")
    k = float(np.sum(force * shift) / moved)
    if not (np.isfinite(k) and k != 0):
        raise ValueError(f"shear_stiffness: the shear leg carries no shear force (k = {k})")
    return k


def contact_shear(shift, area, normal, *, stiffness: float, punch_area: float,
                  mu: float | None = None) -> np.ndarray:
    """(N,2) the target's sticking shear force at each frame: stiffness * sqrt(area /
    punch_area) * shift (Mindlin: the force is proportional to the contact radius, which the
    calibration measured at the punch's area), scaled down to mu * |normal| where it would
    exceed it (sliding; mu None: no cap).  shift (N,2) mm, area (N,) mm^2, normal (N,) N."""
    shift = np.asarray(shift, float)
    area = np.asarray(area, float)
    normal = np.asarray(normal, float)
    if shift.ndim != 2 or shift.shape[1] != 2 or area.shape != shift.shape[:1] or normal.shape != area.shape:
        raise ValueError(f"contact_shear: shift {shift.shape}, area {area.shape} and normal "
                         f"{normal.shape} must be (N,2), (N,), (N,)")
    if not (np.isfinite(punch_area) and punch_area > 0):
        raise ValueError(f"contact_shear: the calibration contact's area must be positive, got {punch_area}")
    if np.any(area < 0):
        raise ValueError("contact_shear: contact areas must be >= 0")
    shear = float(stiffness) * np.sqrt(area / float(punch_area))[:, None] * shift
    if mu is not None:
        if not (np.isfinite(mu) and mu > 0):
            raise ValueError(f"contact_shear: friction coefficient mu must be positive, got {mu}")
        size = np.hypot(shear[:, 0], shear[:, 1])
        cap = float(mu) * np.abs(normal)
        shear *= np.where(size > cap, cap / np.maximum(size, 1e-300), 1.0)[:, None]
    return shear


def slip_shear(shift, area, normal, contact_id, *, stiffness: float, punch_area: float,
               mu: float) -> np.ndarray:
    """(N,2) the target's shear force at each frame of whole contacts (rows in time order, each
    contact's frames contiguous, contact_id (N,)) when its contact slides and remembers where it
    slid: from rest at a contact's first frame, each frame adds the sticking stiffness
    (contact_shear's, stiffness * sqrt(area / punch_area)) times the shift's step, and a force
    beyond mu * |normal| is scaled back onto that limit (Coulomb; the slip it stands for is kept).
    A pad that slid out under the shear leg is sheared the other way when the indenter comes
    back: at the start point again it carries -(what it slid) times the stiffness, where
    contact_shear, which reads each frame alone, gives 0.  The twin's solver carries each pad
    point's slip from frame to frame (stages.sim.contact.solve_sequence), which this follows
    with one slip for the whole contact.  shift (N,2) mm, area (N,) mm^2, normal (N,) N."""
    shift = np.asarray(shift, float)
    area = np.asarray(area, float)
    normal = np.asarray(normal, float)
    contact_id = np.asarray(contact_id)
    if (shift.ndim != 2 or shift.shape[1] != 2 or area.shape != shift.shape[:1] or normal.shape != area.shape
            or contact_id.shape != area.shape):
        raise ValueError(f"slip_shear: shift {shift.shape}, area {area.shape}, normal {normal.shape} and "
                         f"contact_id {contact_id.shape} must be (N,2), (N,), (N,), (N,)")
    if not (np.isfinite(mu) and mu > 0):
        raise ValueError(f"slip_shear: friction coefficient mu must be positive, got {mu}")
    starts = np.r_[True, contact_id[1:] != contact_id[:-1]] if contact_id.size else np.zeros(0, bool)
    if np.unique(contact_id).size != int(starts.sum()):
        raise ValueError("slip_shear: a contact's frames are not contiguous")
    step = np.where(starts[:, None], shift, np.diff(shift, axis=0, prepend=shift[:1]))
    stick = contact_shear(step, area, normal, stiffness=stiffness, punch_area=punch_area)
    cap = float(mu) * np.abs(normal)
    out = np.zeros_like(shift)
    force = np.zeros(2)
    for i in range(len(shift)):
        force = stick[i] if starts[i] else force + stick[i]    # a contact starts from rest at shift 0
        size = float(np.hypot(force[0], force[1]))
        if size > cap[i]:
            force = force * (cap[i] / size)
        out[i] = force
    return out


def compensate(force, normalised_depth, loading, source: Curves, target: Curves,
               eps: float = 1e-6, *, mode: str = "normal", depth_ratio: float = 1.0) -> np.ndarray:
    """Source labels rescaled to the target's material: Fz * r per frame, Fx and Fy * r times
    shear_ratio (mode "axes", at depth_ratio; "normal" scales them by r like Fz, the paper's);
    r evaluates the target's curve at depth_ratio times the source's normalised depth.

    Identical source and target curves at depth_ratio 1 return the labels unchanged (bit for bit).
    """
    force = np.asarray(force)
    if force.ndim != 2 or force.shape[1] != 3:
        raise ValueError(f"compensate: force must be (N,3), got {force.shape}")
    shear = shear_ratio(source, target, mode, depth_ratio)
    if source == target and depth_ratio == 1.0:
        return force.copy()
    scale = label_scale(normalised_depth, loading, source, target, eps, depth_ratio)
    if scale.shape != force.shape[:1]:
        raise ValueError(f"compensate: {force.shape[0]} forces but {scale.shape[0]} depths")
    return (force * scale[:, None] * np.array([shear, shear, 1.0])).astype(force.dtype)


def curves_figure(calibrations: Mapping[str, tuple[Mapping, Curves]], title: str):
    """PNG bytes: calibration points and fitted curves, loading solid and unloading dashed,
    for each named sensor: name -> (calibration arrays, Curves)."""
    from matplotlib.figure import Figure

    from stages.figures import figure_png
    fig = Figure(figsize=(4.8, 3.6))
    ax = fig.add_subplot()
    grid = np.linspace(0.0, 1.0, 50)
    for k, (name, (cal, curves)) in enumerate(calibrations.items()):
        colour = f"C{k}"
        if "normalised_depth" in cal:                   # the authors' curves come without points
            d, f = np.asarray(cal["normalised_depth"]), np.abs(np.asarray(cal["force"])[:, 2])
            load, unload = _branches(*_calibration_phases(cal))
            ax.plot(d[load], f[load], ".", color=colour, ms=3, alpha=0.6)
            ax.plot(d[unload], f[unload], "x", color=colour, ms=3, alpha=0.6)
        ax.plot(grid, np.polyval(curves.loading, grid), "-", color=colour, label=f"{name} loading")
        ax.plot(grid, np.polyval(curves.unloading, grid), "--", color=colour, label=f"{name} unloading")
    ax.set(xlabel="normalised depth", ylabel="|Fz| (N)", title=title)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return figure_png(fig)
