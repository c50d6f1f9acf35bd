"""Node `control`: the paper's robot tasks (Fig. 7) in the gripper twin with a force model.

For each grasp object: close and hold the object's target force (0.6 / 0.8 / 1.2 N by
fragility) with the P controller on the model's force estimates; for each slip object: grasp,
lift, then an external pull ramps up while the slip avoider watches the estimated shear.  The
same slip episode is also run without avoidance (oracle grasp, no detector) to show what the
pull alone does (`slip_mm_passive`).

The fingers carry the model's target skin: its gel, and its image chain (gripper.SkinCamera:
the skin's look rendered in Mitsuba and segmented as its training frames were), so the model
reads the twin's frames as it reads the skin's.  The skin's own-label model runs the same
episodes: the reference the transferred model is measured against.

Metrics (episodes.py defines them): control/grasp/<object>/{force_error_N, crushed, success,
pred_error_N}; control/slip/<object>/{detected_s, slip_mm, slip_mm_passive, false_alarms,
detected, tightenings, force_error_N, crushed, success}; control/mean/{grasp,slip}/<metric>
over the objects; the same under control/supervised/ for the own-label model (without
slip_mm_passive, which does not depend on the model).
Grasp success needs no crushing and a steady-state error below `tolerance_N`, default 0.25 N:
a fragile item (0.6 N) is then held below 0.85 N and a robust one (1.2 N) above 0.95 N, so the
grasp stays in its fragility class's band (the paper's point in choosing the targets), and the
band is wider than what 10 Hz P control on a true force leaves (under 0.02 N with the oracle),
so a failure is the force model's.
"""
from __future__ import annotations

import zlib
from typing import Callable, Mapping

import numpy as np

from stages.control.controller import OraclePredictor
from stages.control.episodes import (DEFAULT_CONTROLLER, DEFAULT_PULL, DEFAULT_TWIN, grasp_metrics,
                                     merged_settings, run_episode, slip_metrics)
from stages.control.gripper import SkinCamera
from stages.control.objects import GraspObject, grasp_object
from stages.figures import contact_sheet, figure_png, png

_ARRAYS = ("time", "width_m", "force_true", "force_pred", "normal_N", "slip_mm", "load_N")
SHOTS_PER_EPISODE = 100_000    # episode k's camera shots are k * this + 1, 2, ...: its own noise


def oracle_factory(*, finger: str = "left", noise_N: float = 0.0, lag_frames: int = 0,
                   seed: int = 0) -> Callable:
    """make_predictor for run_study: the twin's own true force on one finger."""
    return lambda twin: OraclePredictor(lambda: twin.true_force(finger), noise_N=noise_N,
                                        lag_frames=lag_frames, seed=seed)


PREDICTOR = "genforce_plus"       # the transfer's model the fingers read


def control_node(*, model, model_pair, sensors: Mapping, materials: Mapping,
                 patterns: Mapping, segmentation: Mapping | None = None, backend: str = "auto",
                 supervised=None, **study) -> dict:
    """Node `control`: the fingers carry the model's target sensor, model_pair[1]: its gel
    (its sensors entry's mechanics, materials.<its material>) and its image chain (SkinCamera:
    its look rendered and segmented as its training frames were).  supervised: the sensor's
    own-label model (own[skin]), run through the same episodes as the reference a transferred
    model is measured against.  reference_seed (control.reference_seed): null for the sensor's
    own no-contact reference, or an integer camera-noise seed for a fresh take of it.  The rest
    as control_study."""
    from stages.common import InputError
    from stages.markers.render import marker_set

    ref_seed = study.get("reference_seed")
    if ref_seed is not None and (isinstance(ref_seed, bool) or not isinstance(ref_seed, int) or ref_seed < 0):
        raise InputError(f"control: reference_seed must be a non-negative integer or null, got {ref_seed!r}")
    target = str(model_pair[1])
    if target not in sensors:
        raise InputError(f"control: model_pair target {target!r} is not a sensor ({', '.join(sensors)})")
    spec = sensors[target]
    look = spec.get("look")
    if spec.get("source", "render") != "render" or look not in ("none", "gelsight"):
        raise InputError(f"control: the fingers carry sensor {target!r} (look {look!r}): the gripper "
                         "twin has flat camera pads, sensors of look gelsight or none")
    if float(spec.get("curvature_radius_mm", 0.0)) > 0:
        raise InputError(f"control: sensor {target!r} is a dome: the gripper twin's pads are flat")
    if spec.get("material") not in materials:
        raise InputError(f"control: sensor {target!r} has material {spec.get('material')!r}, not in materials")
    return control_study(model=model, supervised=supervised, model_pair=model_pair,
                         sensor=spec, material=materials[spec["material"]], skin=spec,
                         skin_name=target, markers=marker_set(patterns, spec["pattern"]),
                         segmentation=segmentation, backend=backend, **study)


def skin_camera(*, skin: Mapping, markers, sensor: Mapping, size, twin: Mapping | None = None,
                segmentation: Mapping | None = None, skin_name: str = "",
                backend: str = "auto", noise_seed: int = 0,
                reference_seed: int | None = None) -> SkinCamera:
    """The skin's image chain on the twin's solver grid.  The mesh keeps the vertex spacing the
    skin's frames were rendered with (the sensor's grid, times the skin's `upsample`); the
    reference is the skin's own (the render node's seed: the markers node's reference, bit for
    bit) unless `reference_seed` names another camera-noise seed for its shot (a re-mounted
    sensor's fresh take), and the shots' camera noise has its own seed, derived from the
    render seed and noise_seed, so no shot repeats a training frame's noise."""
    from stages.sim.indenters import grid_coords
    from stages.sim.sensors import pad_grid

    grid = tuple(int(v) for v in merged_settings(DEFAULT_TWIN, twin, "twin")["grid"])
    native, spacing = pad_grid(sensor)
    twin_spacing = spacing * (native[1] - 1) / (grid[1] - 1)
    gx, gy = grid_coords(grid, twin_spacing)
    render_seed = int(skin.get("seed", zlib.crc32(skin_name.encode())))
    return SkinCamera(gx, gy, markers, spec=skin, size=size, segmentation=segmentation,
                      seed=zlib.crc32(f"control/{render_seed}/{int(noise_seed)}".encode()),
                      reference_seed=render_seed if reference_seed is None else int(reference_seed),
                      upsample=twin_spacing / spacing * float(skin.get("upsample", 1.0)),
                      backend=backend)


def control_study(*, model, objects: Mapping, grasp: list, slip: list, sensor: Mapping,
                  material: Mapping, size, duration_s: float, pull: Mapping, seed: int = 0,
                  twin: Mapping | None = None, controller: Mapping | None = None,
                  tolerance_N: float = 0.25, model_pair=None,
                  supervised=None, skin: Mapping | None = None, markers=None,
                  segmentation: Mapping | None = None, skin_name: str = "",
                  backend: str = "auto", reference_seed: int | None = None) -> dict:
    """The control study.  model_pair: the (source, target) skins of `model`, for the record.
    model: a transfer artifact (its genforce_plus model, loaded with
    stages.force.model.load_predictor); None runs the oracle (the twin's true force), the
    ceiling any model is measured against.  supervised: an
    own-label artifact (prefix "weights") run through the same episodes; its metrics are
    control/supervised/....  skin (its params), markers (its pattern), segmentation: the
    fingers' images come through the skin's image chain (skin_camera); None: drawn masks of
    twin["pattern"].  seed: the noise streams, the oracle's and the skin camera's (the model's
    predictions are deterministic).  reference_seed: the camera-noise seed of the skin camera's
    no-contact reference (None: the skin's own; skin_camera).  See run_study."""
    kw = dict(objects=objects, grasp=grasp, slip=slip, sensor=sensor, material=material, size=size,
              duration_s=duration_s, pull=pull, seed=seed, twin=twin, controller=controller,
              tolerance_N=tolerance_N)
    import contextlib
    from stages.markers.mitsuba_backend import thread_count
    # one frame at a time: extra threads only contend (Dr.Jit's here, torch's in _control_runs)
    with thread_count(1) if skin is not None else contextlib.nullcontext():
        if skin is not None:
            if markers is None:
                raise ValueError("control_study: a skin camera needs the skin's markers")
            kw["camera"] = skin_camera(skin=skin, markers=markers, sensor=sensor, size=size,
                                       twin=twin, segmentation=segmentation, skin_name=skin_name,
                                       backend=backend, noise_seed=seed, reference_seed=reference_seed)
        out = _control_runs(model, supervised, kw)
    if skin is not None:
        out["attrs"]["camera"] = {"skin": skin_name, "look": str(skin.get("look", "none")),
                                  "reference_seed": kw["camera"].reference_seed}
    else:
        out["attrs"]["camera"] = {"drawn": str(merged_settings(DEFAULT_TWIN, twin, "twin")["pattern"])}
    return out


def _control_runs(model, supervised, kw: dict) -> dict:
    """The study's runs: the model's (the oracle's when None), then the supervised model's on
    the same episodes (the gel tables reused, no figures, no passive slip runs)."""
    kw = {**kw, "tables": {}}
    threads = None
    if model is not None or supervised is not None:
        import torch
        from stages.force.model import load_predictor
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
    try:
        if model is None:
            finger = merged_settings(DEFAULT_TWIN, kw["twin"], "twin")["finger"]
            out = run_study(oracle_factory(finger=finger, seed=kw["seed"]), **kw)
            out["attrs"]["predictor"] = "oracle"
        else:
            predictor = load_predictor(model, prefix=PREDICTOR)
            out = run_study(lambda gripper: predictor, **kw)
            out["attrs"]["predictor"] = PREDICTOR
        if supervised is not None:
            own = load_predictor(supervised, prefix="weights")
            ref = run_study(lambda gripper: own, passive=False, plots=False,
                            prefix="control/supervised", **kw)
            out["metrics"].update(ref["metrics"])
    finally:
        if threads is not None:
            torch.set_num_threads(threads)
    out["attrs"]["supervised"] = supervised is not None
    return out


def run_study(make_predictor: Callable, *, objects: Mapping, grasp: list, slip: list,
              sensor: Mapping, material: Mapping, size, duration_s: float, pull: Mapping,
              seed: int = 0, twin: Mapping | None = None, controller: Mapping | None = None,
              tolerance_N: float = 0.25, camera: SkinCamera | None = None, passive: bool = True,
              prefix: str = "control", plots: bool = True, tables: dict | None = None) -> dict:
    """All episodes with predictors from make_predictor(gripper twin) -> predictor.

    objects: catalogue name -> entry (objects.py); grasp / slip: names to run; sensor /
    material: the sensor twin's catalogue entry and elastomer; size: marker image (H, W);
    duration_s: the grasp phase; pull: slip-phase settings (episodes.DEFAULT_PULL keys);
    twin / controller: overrides of episodes.DEFAULT_TWIN / DEFAULT_CONTROLLER; camera: the
    fingers' image chain (gripper.SkinCamera; None: drawn masks); passive: also run each slip
    episode without avoidance (the oracle, which reads no image: drawn masks) for
    slip_mm_passive; prefix: of the metric names; plots: draw the figures; tables: object name
    -> gel table, filled and reused (one dict shared by studies of the same twin).
    Returns grasp/<object>/... and slip/<object>/... per-frame arrays, figures, metrics, attrs.
    """
    from tqdm import tqdm

    unknown = [n for n in list(grasp) + list(slip) if n not in objects]
    if unknown:
        raise KeyError(f"control objects {unknown} are not in the catalogue ({', '.join(objects)})")
    tw = merged_settings(DEFAULT_TWIN, twin, "twin")
    ctl = merged_settings(DEFAULT_CONTROLLER, controller, "controller")
    pl = merged_settings(DEFAULT_PULL, pull, "pull")
    size = tuple(int(v) for v in size)
    common = {"sensor": sensor, "material": material, "size": size, "grasp_s": float(duration_s),
              "twin": tw, "controller": ctl}
    tables = {} if tables is None else tables
    out, metrics, figures, marks = {"grasp": {}, "slip": {}}, {}, {}, {}
    steady_images = []
    runs = [("grasp", n) for n in grasp] + [("slip", n) for n in slip]
    for k, (kind, name) in enumerate(tqdm(runs, desc="control", unit="episode", disable=None,
                                          leave=False)):
        obj = grasp_object(name, objects[name])
        ep = run_episode(obj, make_predictor, pull=pl if kind == "slip" else None,
                         table=tables.get(name), camera=camera, first_shot=SHOTS_PER_EPISODE * k,
                         **common)
        tables[name] = ep["table"]
        key = f"{prefix}/{kind}/{name}"
        if kind == "grasp":
            found = grasp_metrics(ep, tolerance_N)
            if plots:
                figures[f"grasp_{name}"] = _trace_png(ep, f"grasp {name}: target {obj.target_N} N")
                diff = 128 + (ep["image"].astype(np.int16) - ep["reference"]) // 2
                steady_images += [ep["image"], diff.astype(np.uint8)]
        else:
            found = slip_metrics(ep, float(ctl["window_s"]), tolerance_N)
            free = None
            if passive:
                free = run_episode(obj, oracle_factory(finger=tw["finger"], seed=seed), pull=pl,
                                   table=tables[name],
                                   **{**common, "controller": {**ctl, "threshold_N": np.inf}})
                found["slip_mm_passive"] = slip_metrics(free, float(ctl["window_s"]))["slip_mm"]
            if plots:
                figures[f"slip_{name}"] = _trace_png(ep, f"slip {name}: pull {pl['rate_N_s']} N/s "
                                                         f"to {pl['max_N']} N", passive=free)
        metrics.update({f"{key}/{k}": float(v) for k, v in found.items()})
        out[kind][name] = _arrays(ep)
        marks[f"{kind}/{name}"] = {k: float(v) for k, v in ep["marks"].items()}
        if ep.get("onset") is not None:
            marks[f"{kind}/{name}"]["onset"] = float(ep["onset"])
    metrics.update(_means(metrics, grasp, slip, prefix))
    if steady_images:
        # each grasp object's last marker image and its change from the reference (grey 0)
        figures["images"] = png(contact_sheet(steady_images, cols=min(len(steady_images), 6)))
    out = {k: v for k, v in out.items() if v}
    out["figures"] = figures
    out["metrics"] = metrics
    out["attrs"] = {"units": "s, m (width), N (force: left pad frame, Fz < 0 pressing), mm (slip)",
                    "targets_N": {n: grasp_object(n, objects[n]).target_N for n in dict.fromkeys(
                        list(grasp) + list(slip))},
                    "tolerance_N": float(tolerance_N), "image_size": list(size),
                    "twin": {k: (list(v) if isinstance(v, (list, tuple)) else v) for k, v in tw.items()},
                    "controller": {k: float(v) for k, v in ctl.items()},
                    "pull": {k: float(v) for k, v in pl.items()}, "marks_s": marks}
    return out


def _arrays(ep: Mapping) -> dict:
    arrays = {k: np.asarray(ep[k], np.float32 if k.startswith("force") else np.float64)
              for k in _ARRAYS}
    arrays["events"] = {k: np.asarray(v, np.float64) for k, v in ep["events"].items()}
    return arrays


def _means(metrics: Mapping, grasp, slip, prefix: str = "control") -> dict:
    out = {}
    for kind, names, keys in (("grasp", grasp, ("force_error_N", "success", "crushed", "pred_error_N")),
                              ("slip", slip, ("detected_s", "slip_mm", "slip_mm_passive", "success"))):
        for key in keys:
            values = [metrics[f"{prefix}/{kind}/{n}/{key}"] for n in names
                      if f"{prefix}/{kind}/{n}/{key}" in metrics]
            if values:
                out[f"{prefix}/mean/{kind}/{key}"] = float(np.mean(values))
    return out


def _trace_png(ep: Mapping, title: str, passive: Mapping | None = None) -> np.ndarray:
    """Force and width traces: true vs predicted normal force with the target; for slip runs
    also the shear along the pull and the slip (with the no-avoidance run dashed)."""
    from matplotlib.figure import Figure

    obj: GraspObject = ep["object"]
    t, marks = ep["time"], ep["marks"]
    rows = 3 if passive is not None else 2
    fig = Figure(figsize=(7, 2.2 * rows))
    axes = fig.subplots(rows, 1, sharex=True)
    ax = axes[0]
    ax.plot(t, -ep["force_true"][:, 2], color="k", lw=1.2, label="true")
    ax.plot(t, -ep["force_pred"][:, 2], color="C0", lw=0.9, label="predicted")
    ax.axhline(obj.target_N, color="C2", ls="--", lw=0.8, label="target")
    if ep["max_normal_N"] > obj.crush_N:
        ax.axhline(obj.crush_N, color="C3", ls=":", lw=0.8, label="crush")
    ax.set(ylabel="normal force (N)", title=title)
    ax.legend(loc="lower right", fontsize=7, ncol=4)
    if passive is not None:
        ax = axes[1]
        for k, (label, colour) in enumerate((("Fx", "C1"), ("Fy", "C4"))):
            ax.plot(t, ep["force_true"][:, k], color=colour, lw=1.2, label=f"{label} true")
            ax.plot(t, ep["force_pred"][:, k], color=colour, lw=0.8, ls="--", label=f"{label} pred")
        ax.set(ylabel="shear (N)")
        ax.legend(loc="upper left", fontsize=7, ncol=4)
    ax = axes[-1]
    ax.plot(t, ep["width_m"] * 1e3, color="C7", lw=1.0)
    ax.set(ylabel="width (mm)", xlabel="time (s)")
    if passive is not None:
        slip = ax.twinx()
        slip.plot(t, np.hypot(*ep["slip_mm"].T), color="C3", lw=1.2, label="slip")
        slip.plot(passive["time"], np.hypot(*passive["slip_mm"].T), color="C3", lw=0.8, ls=":",
                  label="slip, no avoidance")
        slip.set_ylabel("slip (mm)")
        slip.legend(loc="center right", fontsize=7)
    for a in axes:
        for time in ep["events"]["contact"]:
            a.axvline(time, color="C2", lw=0.6, ls=":")
        for time in ep["events"]["detected"]:
            a.axvline(time, color="C3", lw=0.8)
        for key in ("monitor", "pull"):
            if key in marks:
                a.axvline(marks[key], color="0.5", lw=0.6, ls="--")
        if ep.get("onset") is not None:
            a.axvline(ep["onset"], color="C3", lw=0.6, ls="--")
    fig.tight_layout()
    return figure_png(fig)
