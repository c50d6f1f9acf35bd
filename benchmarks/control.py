"""Control-loop latency per step of the gripper twin (stages.control).

Run: python benchmarks/control.py [--quick]   (about a minute on a 2-core CPU; --quick: the
episodes plum 96 px, wood_block 128 px and plum 128 px through the skin camera)

One sensor frame of the loop is: twin physics (finger kinematics, series normal chain, slip, in
5 ms substeps), contact solve (a pressed solve and, with shear, a sheared one, only when the
contact state changed), marker image rendering (the left finger: drawn masks, or with "skin" the
skin camera the control node uses, a Mitsuba render of the GelSight look plus its segmentation),
force prediction, and the two controllers.  Each episode grasps the object at its target force,
then its weight comes on and a pull ramps up (8 N/s to 1.5 N) while the slip avoider watches:
grasp, hold and slip frames alike.  The controllers act on the twin's true force, so every
episode follows the same trajectory whatever the predictor; the predictor still runs on every
image and is timed.  The predictor is a tiny untrained ForceRegressor (stages.force.model,
default config) when that module imports, else the oracle.  Columns: mean ms per frame over
the frames where the stage ran (solve, render: frames whose contact changed), how many frames
ran it, and the whole frame's mean and 95th percentile against the 50 ms a 20 Hz loop allows.
"""
import argparse
import contextlib
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np                                                     # noqa: E402

from benchmarks.summary import record                                  # noqa: E402
from stages.control.controller import GraspController, OraclePredictor, SlipAvoider  # noqa: E402
from stages.control.episodes import pull_force, weight_force          # noqa: E402
from stages.control.gripper import GripperTwin                         # noqa: E402
from stages.control.objects import DEFAULT_OBJECTS, grasp_object       # noqa: E402
from stages.markers.mitsuba_backend import thread_count                 # noqa: E402
from stages.markers.patterns import gelsight_pattern                   # noqa: E402

SENSOR = {"pad_mm": [25.0, 25.0], "thickness_mm": 4.0, "grid": [65, 65], "spacing_mm": 0.390625}
MATERIAL = {"E": 5.2e5, "nu": 0.45}
RATE_HZ = 20.0
GRASP_S, HOLD_S, SLIP_S = 2.5, 1.0, 2.0
STAGES = ("physics", "solve", "render", "predict", "control")


def make_predictor(reference):
    """A tiny untrained force model if stages.force.model is there, else None (oracle)."""
    try:
        import torch
        from stages.force.model import ForceRegressor, StreamingPredictor
    except ImportError:
        return None, "oracle (stages.force.model not importable)"
    torch.manual_seed(0)
    torch.set_num_threads(1)            # batch-1 inference of a small net: threads only contend
    model = ForceRegressor()
    model.set_reference(reference)
    return StreamingPredictor(model), f"untrained ForceRegressor, input {model.config['input_size']} px, " \
                                      f"{torch.get_num_threads()} torch thread(s)"


def skin_camera(grid, size):
    """The control node's image chain for a GelSight skin (default LEDs, noise 3) on the grid."""
    from stages.control.nodes import skin_camera as make
    sensor = {**SENSOR, "curvature_radius_mm": 0.0}
    return make(skin={"look": "gelsight", "noise": 3.0}, markers=gelsight_pattern("A-II"),
                sensor=sensor, size=size, twin={"grid": list(grid)}, skin_name="gelsight-A-II")


def episode(name, grid, size, predictor_cache, camera=None):
    obj = grasp_object(name, DEFAULT_OBJECTS[name])
    t_lift = GRASP_S
    weight = weight_force(obj, t_lift, 0.5)
    pull = pull_force({"rate_N_s": 8.0, "max_N": 1.5, "direction_deg": 90.0}, t_lift + HOLD_S)
    twin = GripperTwin(obj, sensor=SENSOR, material=MATERIAL, pattern=gelsight_pattern("A-II"),
                       size=size, grid=grid, load=lambda t: weight(t) + pull(t), camera=camera)
    key = (size, camera is not None)            # the predictor's reference: drawn or shot
    if key not in predictor_cache:
        predictor_cache[key] = make_predictor(twin.reference)
    predictor, label = predictor_cache[key]
    oracle = OraclePredictor(lambda: twin.true_force("left"))
    if predictor is None:
        predictor = oracle
    predictor.reset()
    grasp, avoider = GraspController(obj.target_N), SlipAvoider()
    grasp.start(0.0, twin)
    dt, n = 1.0 / RATE_HZ, int((GRASP_S + HOLD_S + SLIP_S) * RATE_HZ)
    times = {s: [] for s in STAGES}
    frame_ms = []
    for k in range(n):
        t = k * dt
        t0 = time.perf_counter()
        changed = twin._frame is None
        force = twin.true_force("left")                    # the contact solve, if any
        t1 = time.perf_counter()
        image = twin.read_sensors()["left"]
        t2 = time.perf_counter()
        predictor.step(image)
        t3 = time.perf_counter()
        if t >= t_lift + 0.5 and not avoider.active:
            grasp.hold(twin)
            avoider.start(t)
        grasp.update(t, force, twin)
        avoider.update(t, force, twin)
        t4 = time.perf_counter()
        twin.step(dt)
        t5 = time.perf_counter()
        if changed:
            times["solve"].append(t1 - t0)
            times["render"].append(t2 - t1)
        times["predict"].append(t3 - t2)
        times["control"].append(t4 - t3)
        times["physics"].append(t5 - t4)
        frame_ms.append(1e3 * (t5 - t0))
    return times, np.asarray(frame_ms), label, n


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="two of the four episodes")
    args = ap.parse_args()
    print(f"control-loop latency per step: {RATE_HZ:.0f} Hz frames, grasp {GRASP_S} s + hold "
          f"{HOLD_S} s + pull {SLIP_S} s, {os.cpu_count()} CPU(s)")
    cache = {}
    head = (f"{'object':>11} {'grid':>6} {'image':>7} {'images':>7} "
            + " ".join(f"{s + ' ms':>10}" for s in STAGES)
            + f" {'frames':>11} {'frame ms':>9} {'p95 ms':>7} {'of 50 ms':>8}")
    rows = []
    episodes = [("plum", (33, 33), (96, 96), False), ("plum", (33, 33), (128, 128), False),
                ("plum", (65, 65), (128, 128), False), ("wood_block", (33, 33), (128, 128), False),
                ("plum", (33, 33), (128, 128), True)]
    for name, grid, size, skin in (episodes[::3] + episodes[4:] if args.quick else episodes):
        camera = skin_camera(grid, size) if skin else None
        with thread_count(1) if skin else contextlib.nullcontext():    # as the control node
            times, frame_ms, label, n = episode(name, grid, size, cache, camera)
        cells = " ".join(f"{1e3 * np.mean(times[s]) if times[s] else 0.0:>10.2f}" for s in STAGES)
        images = "skin" if skin else "drawn"
        rows.append(f"{name:>11} {grid[0]:>3}^2 {size[0]:>4}px {images:>7} {cells} "
                    f"{len(times['solve']):>4} of {n:<4} {frame_ms.mean():>9.1f} "
                    f"{np.percentile(frame_ms, 95):>7.1f} {frame_ms.mean() / 50.0:>8.0%}")
        case = f"{name} {grid[0]}^2 {size[0]}px{' skin camera' if skin else ''}"
        record("control", f"frame latency vs 50 ms, mean, {case}", f"{frame_ms.mean():.1f} ms",
               frame_ms.mean() / 50.0, "<= 1")
        record("control", f"frame latency vs 50 ms, p95, {case}", f"{np.percentile(frame_ms, 95):.1f} ms",
               np.percentile(frame_ms, 95) / 50.0, "<= 1")
    print(f"predictor: {label}")
    print("(solve / render: mean over the frames whose contact changed, counted under 'frames')")
    print(head)
    print("\n".join(rows))


if __name__ == "__main__":
    main()
