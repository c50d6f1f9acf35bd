"""Grasp and slip episodes of the gripper twin under the paper's controllers, and their metrics.

A grasp episode: the gripper opens at the object's width + approach_mm, the predictor reads
`warmup_s` of open-gripper frames (a force model's GRU starts from zero state and reads a few
frames high: A-II's models 0.65 N at the first frame, settled after ~5), is tared for `tare_s`
(the paper subtracts a baseline against its model's zero shift), then the
GraspController closes and holds the target force for `grasp_s`.  A slip episode continues
(paper: grasp, lift, slip check at the top): the object's weight comes on over `lift_s` (+y,
down in the marker image), the P loop stops after `settle_s` and the SlipAvoider monitors for
`pull.monitor_s` seconds, during which an external pull ramps up from `pull.start_s`
(rate_N_s up to max_N, direction_deg in the left pad's frame: 90 = +y, along gravity).

Slip onset is the counterfactual moment the load first exceeds the friction capacity the grasp
had when the pull began (2 mu F): the time the object would start sliding if nothing reacted.
It does not depend on the controller, so detection before it (anticipation, negative delay)
and after it are measured on the same clock.
"""
from __future__ import annotations

import inspect
from typing import Callable, Mapping

import numpy as np

from stages.control.controller import GraspController, SlipAvoider
from stages.control.gripper import GelTable, GripperTwin, SkinCamera
from stages.control.objects import GraspObject
from stages.markers.patterns import gelsight_pattern

# Twin and episode settings (params `control.twin` may override any of them).
DEFAULT_TWIN = {
    "grid": [33, 33],          # solver grid on the sensor's pad (coarse: ~0.8 mm cells)
    "pattern": "A-II",         # GelSight marker layout of drawn masks (a skin camera brings its own)
    "finger": "left",          # the finger whose sensor feeds the controllers
    "rate_hz": 20.0,           # sensor frame rate (= the slip check's rate)
    "finger_N_mm": 4.0,        # mount + finger stiffness, each side
    "damping_N_s_m": 30.0,     # viscous friction of the sliding interface
    "approach_mm": 3.0,        # initial opening beyond the object's width
    "warmup_s": 0.5,           # open-gripper frames read, not tared: a model's GRU settles
    "tare_s": 0.25,            # open-gripper frames averaged into the force baseline
    "lift_s": 0.5,             # the object's weight comes on over this time
    "settle_s": 0.5,           # P control continues this long after the lift
}
# The paper's controller settings (params `control.controller` may override them).
DEFAULT_CONTROLLER = {
    "kp": 0.0004, "grasp_rate_hz": 10.0, "close_speed": 0.005, "contact_N": 0.1,
    "slip_rate_hz": 20.0, "window_s": 0.5, "threshold_N": 0.3, "samples": 3,
    "tighten_m": 0.001, "tighten_speed": 0.015,
}
DEFAULT_PULL = {"start_s": 1.0, "rate_N_s": 8.0, "max_N": 1.5, "direction_deg": 90.0, "monitor_s": 10.0}
STEADY_S = 1.0                 # steady state = the last second of the grasp phase
STOPPED_MM = 0.05              # slip stopped: less than this over the last second


def merged_settings(defaults: Mapping, given: Mapping | None, what: str) -> dict:
    unknown = sorted(set(given or {}) - set(defaults))
    if unknown:
        raise KeyError(f"unknown {what} setting(s) {unknown} (known: {sorted(defaults)})")
    return {**defaults, **(given or {})}


def pull_force(pull: Mapping, t_start: float) -> Callable[[float], np.ndarray]:
    """t -> pull force (2,) N: 0 before t_start, then rate_N_s * (t - t_start) up to max_N."""
    angle = np.deg2rad(float(pull["direction_deg"]))
    unit = np.array([np.cos(angle), np.sin(angle)])
    rate, cap = float(pull["rate_N_s"]), float(pull["max_N"])
    return lambda t: unit * float(np.clip(rate * (t - t_start), 0.0, cap))


def weight_force(obj: GraspObject, t_lift: float, lift_s: float) -> Callable[[float], np.ndarray]:
    """t -> the object's weight (2,) N along +y, ramping in linearly over lift_s from t_lift."""
    return lambda t: np.array([0.0, obj.weight_N * float(np.clip((t - t_lift) / max(lift_s, 1e-9), 0, 1))])


def total_force(*forces: Callable[[float], np.ndarray]) -> Callable[[float], np.ndarray]:
    """t -> the sum of several time profiles of force."""
    return lambda t: sum(f(t) for f in forces)


def _reset(predictor, reference) -> None:
    """Reset a predictor, handing it the sensor's no-contact image if it takes one."""
    try:
        takes = "reference" in inspect.signature(predictor.reset).parameters
    except (TypeError, ValueError):
        takes = False
    if takes:
        predictor.reset(reference=reference)
    else:
        predictor.reset()


def make_twin(obj: GraspObject, *, sensor: Mapping, material: Mapping, size, twin: Mapping,
              load=None, table: GelTable | None = None, camera: SkinCamera | None = None,
              first_shot: int = 0) -> GripperTwin:
    """The episode's gripper twin; with a camera (the skin's image chain) its pattern is the
    camera's, else the GelSight twin named by twin["pattern"] with drawn masks."""
    markers = None if camera is not None else \
        gelsight_pattern(str(twin["pattern"]).removeprefix("gelsight-"))
    return GripperTwin(obj, sensor=sensor, material=material, pattern=markers,
                       size=size, grid=twin["grid"], approach_mm=twin["approach_mm"],
                       finger_N_mm=twin["finger_N_mm"], damping_N_s_m=twin["damping_N_s_m"],
                       load=load, table=table, camera=camera, first_shot=first_shot)


def run_episode(obj: GraspObject, make_predictor: Callable, *, sensor: Mapping, material: Mapping,
                size=(128, 128), grasp_s: float = 4.0, pull: Mapping | None = None,
                twin: Mapping | None = None, controller: Mapping | None = None,
                table: GelTable | None = None, camera: SkinCamera | None = None,
                first_shot: int = 0) -> dict:
    """One episode (a slip episode when `pull` is given).  make_predictor(twin) -> predictor.
    camera: the sensors' image chain (gripper.SkinCamera; None: drawn masks), its shots
    numbered from first_shot + 1.

    Returns per-frame arrays time (s), width_m, force_true / force_pred (N, 3) N (left pad;
    pred after taring), normal_N (the twin's normal force), slip_mm (N, 2), load_N (N, 2),
    plus events (name -> times: contact, detected), marks (phase start times), onset (slip
    episodes), crushed / dropped / max_normal_N, the last frame's marker image, the object and
    its gel table (reusable by the next episode of the same object).
    """
    tw = merged_settings(DEFAULT_TWIN, twin, "twin")
    ctl = merged_settings(DEFAULT_CONTROLLER, controller, "controller")
    pull = None if pull is None else merged_settings(DEFAULT_PULL, pull, "pull")
    dt = 1.0 / float(tw["rate_hz"])
    t_tare = float(tw["warmup_s"])
    t_close = t_tare + float(tw["tare_s"])
    t_lift = t_close + float(grasp_s)
    marks = {"close": t_close, "end_grasp": t_lift, "end": t_lift}
    load = None                                # grasp episodes: the object rests on the table
    if pull is not None:
        marks["monitor"] = t_lift + float(tw["lift_s"]) + float(tw["settle_s"])
        marks["pull"] = marks["monitor"] + float(pull["start_s"])
        marks["end"] = marks["monitor"] + float(pull["monitor_s"])
        load = total_force(weight_force(obj, t_lift, float(tw["lift_s"])),
                           pull_force(pull, marks["pull"]))
    gripper = make_twin(obj, sensor=sensor, material=material, size=size, twin=tw, load=load,
                        table=table, camera=camera, first_shot=first_shot)
    predictor = make_predictor(gripper)
    _reset(predictor, gripper.reference)
    grasp = GraspController(obj.target_N, kp=ctl["kp"], rate_hz=ctl["grasp_rate_hz"],
                            close_speed=ctl["close_speed"], contact_N=ctl["contact_N"])
    avoider = SlipAvoider(rate_hz=ctl["slip_rate_hz"], window_s=ctl["window_s"],
                          threshold_N=ctl["threshold_N"], samples=int(ctl["samples"]),
                          tighten_m=ctl["tighten_m"], speed=ctl["tighten_speed"])
    n = int(round(marks["end"] / dt)) + 1
    rec = {"time": np.arange(n) * dt, "width_m": np.zeros(n), "force_true": np.zeros((n, 3)),
           "force_pred": np.zeros((n, 3)), "normal_N": np.zeros(n), "slip_mm": np.zeros((n, 2)),
           "load_N": np.zeros((n, 2))}
    events = {"contact": [], "detected": []}
    tare, baseline, normal_at_pull = [], np.zeros(3), None
    finger = tw["finger"]
    for k, t in enumerate(rec["time"]):
        images = gripper.read_sensors()
        raw = np.asarray(predictor.step(images[finger]), float)
        if t < t_close - 1e-9:
            if t >= t_tare - 1e-9:
                tare.append(raw)
        elif grasp.phase == "idle":
            baseline = np.mean(tare, axis=0) if tare else np.zeros(3)
            grasp.start(t, gripper)
        force = raw - baseline
        rec["width_m"][k] = gripper.width()
        rec["force_true"][k] = gripper.true_force(finger)
        rec["force_pred"][k] = force
        rec["normal_N"][k] = gripper.normal_N
        rec["slip_mm"][k] = gripper.slip_mm
        rec["load_N"][k] = 0.0 if load is None else load(t)
        if pull is not None and not avoider.active and t >= marks["monitor"] - 1e-9:
            grasp.hold(gripper)
            avoider.start(t)
        if pull is not None and normal_at_pull is None and t >= marks["pull"] - 1e-9:
            normal_at_pull = gripper.normal_N
        if grasp.update(t, force, gripper) == "contact":
            events["contact"].append(t)
        if avoider.update(t, force, gripper):
            events["detected"].append(t)
        gripper.step(dt)
    out = {**rec, "events": {k: np.asarray(v, float) for k, v in events.items()}, "marks": marks,
           "baseline_N": baseline, "crushed": gripper.crushed, "dropped": gripper.dropped,
           "max_normal_N": gripper.max_normal_N, "object": obj, "table": gripper.table,
           "image": np.asarray(images[finger]), "reference": gripper.reference}
    if pull is not None:
        out["onset"] = slip_onset(load, marks["pull"], marks["end"], obj, normal_at_pull or 0.0)
    return out


def slip_onset(load: Callable, t_from: float, t_to: float, obj: GraspObject, normal_N: float,
               resolution_s: float = 1e-3) -> float | None:
    """First time in [t_from, t_to] the load exceeds the friction capacity 2 mu normal_N."""
    times = np.arange(t_from, t_to + resolution_s / 2, resolution_s)
    over = np.flatnonzero([np.hypot(*load(t)) > 2 * obj.mu * normal_N for t in times])
    return float(times[over[0]]) if over.size else None


def grasp_metrics(ep: Mapping, tolerance_N: float) -> dict:
    """force_error_N (|steady true normal - target|, mean over the last second), crushed,
    success (error < tolerance and not crushed), pred_error_N (mean |predicted - true| normal
    force over the frames in contact)."""
    obj, t = ep["object"], ep["time"]
    steady = t >= ep["marks"]["end_grasp"] - STEADY_S - 1e-9
    steady &= t <= ep["marks"]["end_grasp"] + 1e-9
    true_n, pred_n = -ep["force_true"][:, 2], -ep["force_pred"][:, 2]
    error = abs(float(true_n[steady].mean()) - obj.target_N)
    touching = true_n > 0.05
    pred_error = float(np.abs(pred_n - true_n)[touching].mean()) if touching.any() else 0.0
    return {"force_error_N": error, "crushed": float(ep["crushed"]),
            "success": float(error < tolerance_N and not ep["crushed"]), "pred_error_N": pred_error}


def slip_metrics(ep: Mapping, window_s: float = 0.5, tolerance_N: float = 0.25) -> dict:
    """detected_s (first detection after the pull began - slip onset; censored at the episode's
    end when nothing is detected; absent when the pull never exceeds friction), slip_mm (object
    displacement during monitoring), false_alarms (detections before the pull), tightenings,
    force_error_N and crushed of the grasp (as grasp_metrics), and success: the grasp held its
    target within the tolerance uncrushed, no false alarm, and, with an onset, detection within
    window_s of it and the slip stopped (< 0.05 mm over the last second, object kept); without
    one, nothing detected and nothing slipped.  (Squeezing far past the target also keeps a
    pull from slipping the object: that is a failed grasp, not a slip avoided.)"""
    t, marks, slip = ep["time"], ep["marks"], ep["slip_mm"]
    detections = ep["events"]["detected"]
    false_alarms = int((detections < marks["pull"] - 1e-9).sum())
    after = detections[detections >= marks["pull"] - 1e-9]
    mon = int(np.searchsorted(t, marks["monitor"] - 1e-9))
    total = float(np.hypot(*(slip[-1] - slip[mon])))
    last = int(np.searchsorted(t, t[-1] - STEADY_S - 1e-9))
    stopped = float(np.hypot(*(slip[-1] - slip[last]))) < STOPPED_MM and not ep["dropped"]
    grasp = grasp_metrics(ep, tolerance_N)
    out = {"slip_mm": total, "false_alarms": float(false_alarms), "crushed": float(ep["crushed"]),
           "detected": float(after.size > 0), "tightenings": float(detections.size),
           "force_error_N": grasp["force_error_N"]}
    onset = ep["onset"]
    if onset is None:
        ok = after.size == 0 and total < STOPPED_MM
    else:
        delay = float(after[0] - onset) if after.size else float(t[-1] - onset)
        out["detected_s"] = delay
        ok = after.size > 0 and delay <= window_s and stopped
    out["success"] = float(ok and false_alarms == 0 and grasp["success"] == 1.0)
    return out
