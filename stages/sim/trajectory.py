"""Contact trajectories: the simulation grid, the real-collection protocol, calibration.

Every function returns a plain ``dict`` of numpy arrays sharing the frame axis N (the same
artifact drives the simulator and the hardware capture). Units: mm, seconds. Fields:

  position     (N,3) float64  indenter tip in the sensor frame, mm; the pad surface is z = 0,
                              so z = -depth; x, y = surface point + shift
  depth        (N,)  float64  indentation below the surface, mm (>= 0)
  shift        (N,2) float64  lateral displacement since touchdown, mm (solver ``shift``)
  phase        (N,)  int8     0 press, 1 shear out, 2 shear back, 3 release
  contact_id   (N,)  int32    one id per touchdown..lift-off sequence, 0-based, increasing
  indenter_id  (N,)  int16    index into ALL_INDENTERS (== INDENTERS for the 18 shapes)
  paired       (N,)  bool     location-paired frame (see each function)
  indenters    (20,) str      ALL_INDENTERS, the names that indenter_id indexes (not per frame)

plus per-function extras documented below.
"""
from __future__ import annotations

import math

import numpy as np

from stages.common import InputError
from stages.sim.indenters import ALL_INDENTERS, INDENTERS


def _indenter_ids(indenters) -> list[int]:
    ids = []
    for name in indenters:
        if name not in ALL_INDENTERS:
            raise InputError(f"unknown indenter {name!r} (known: {', '.join(ALL_INDENTERS)})")
        ids.append(ALL_INDENTERS.index(name))
    if not ids:
        raise InputError("the trajectory names no indenters")
    return ids


def check_depths(depths_mm, what: str = "depths_mm") -> np.ndarray:
    dep = np.asarray(depths_mm, float)
    if dep.ndim != 1 or dep.size == 0 or not np.all(dep > 0):
        raise InputError(f"{what} must be a non-empty list of depths > 0 mm, got {depths_mm!r}")
    return dep


def sim_grid_trajectory(*, positions_mm=(-4.0, 0.0, 4.0),
                        depths_mm=(0.3, 0.6, 0.9, 1.2, 1.5), indenters=INDENTERS) -> dict:
    """The paper's simulation grid: every (x, y) in positions x positions, every depth.

    Order: indenter, then x, then y, then depth ascending. One contact per (indenter, x, y),
    so 9 x 5 = 45 frames per indenter with the defaults (810 for 18 indenters). All frames
    are pure presses (phase 0, zero shift) and all count as location-paired.
    Extras: ``point_id`` (N,) int16, index of the (x, y) point within the indenter's grid.
    """
    pos = np.asarray(positions_mm, float)
    dep = check_depths(depths_mm)
    ids = _indenter_ids(indenters)
    ind, gx, gy, gd = np.meshgrid(np.arange(len(ids)), pos, pos, dep, indexing="ij")
    n_pts, n_dep = pos.size ** 2, dep.size
    n = gd.size
    depth = gd.ravel()
    return {
        "position": np.column_stack([gx.ravel(), gy.ravel(), -depth]),
        "depth": depth,
        "shift": np.zeros((n, 2)),
        "phase": np.zeros(n, np.int8),
        "contact_id": (np.arange(n) // n_dep).astype(np.int32),
        "indenter_id": np.asarray(ids, np.int16)[ind.ravel()],
        "point_id": ((np.arange(n) // n_dep) % n_pts).astype(np.int16),
        "paired": np.ones(n, bool),
        "indenters": np.array(ALL_INDENTERS),
    }


def surface_points(n_points: int = 5, offset_mm: float = 3.0) -> np.ndarray:
    """(n_points, 2) mm: the centre, then n_points-1 points on a circle of radius offset_mm
    starting on +x and going counter-clockwise (5 -> centre, +x, +y, -x, -y)."""
    if n_points < 1:
        raise ValueError("n_points must be >= 1")
    a = 2 * np.pi * np.arange(n_points - 1) / max(n_points - 1, 1)
    ring = offset_mm * np.column_stack([np.cos(a), np.sin(a)])
    return np.vstack([[[0.0, 0.0]], ring])


def _depth_levels(step: float, max_depth: float) -> np.ndarray:
    n = max(int(math.floor(max_depth / step + 1e-9)), 1)
    levels = step * np.arange(1, n + 1)
    if max_depth - levels[-1] > 1e-9:
        levels = np.append(levels, max_depth)
    return np.minimum(levels, max_depth)


def collection_trajectory(*, n_points: int = 5, point_offset_mm: float = 3.0,
                          depth_step_mm: float = 0.25, max_depth_mm: float = 1.0,
                          shear_radius_mm: float = 1.0, n_directions: int = 8,
                          rate_hz: float = 40.0, speed_mm_s: float = 1.5,
                          indenters=INDENTERS, shear_every_depth: bool = True,
                          n_paired: int = 4, dwell_samples: int = 0) -> dict:
    """The real-collection protocol (paper Fig. 4B, Supplementary Text 7), sampled in time.

    For every indenter and every surface point (:func:`surface_points`), and for every depth
    level (depth_step, 2*depth_step, ..., max_depth): press from the surface to the level
    (phase 0), then for each of ``n_directions`` directions at k*360/n deg (counter-clockwise
    from +x) shear out to ``shear_radius_mm`` (phase 1) and back (phase 2), then release to the
    surface (phase 3). This reading ("moving down, moving laterally, returning laterally,
    moving up" at every depth) gives 4 x (1 + 16 + 1) = 72 movements per point, and
    72 x 5 points x 12 seen indenters x 4 paired frames = 17,280 location-paired images per
    sensor, exactly the paper's count. ``shear_every_depth=False`` instead presses step by
    step down to max depth, shears only there, then releases (one contact per point).

    Each movement is a straight line in (shift, depth) sampled at ``rate_hz`` with
    n = max(ceil(length * rate / speed), n_paired) samples at fractions 1/n .. 1 (the target
    itself is sampled last), followed by ``dwell_samples`` samples held at the target. The
    last ``n_paired`` samples of each movement are ``paired``. The press that starts a contact
    is also sampled at fraction 0, its start on the untouched surface: every contact's first
    frame is a no-contact frame, as every contact of the authors' recordings starts with one
    (its frame 0000, which their M2M code also uses as the untouched frame) and as a force
    model in use reads the skin at rest before anything touches it. The defaults give about 168k
    frames for 18 indenters (the paper collected ~180k per sensor). TacTip: depth_step_mm=1.125,
    max_depth_mm=4.5, rate_hz=20.

    Extras: ``time`` (N,) s on a nominal clock (indenter changes take no time), ``point_id``
    (N,) int16, ``direction_id`` (N,) int8 (-1 outside shear phases), ``movement_id`` (N,)
    int32, ``depth_level`` (N,) float64 target depth of the current cycle in mm,
    ``points`` (n_points, 2) mm and ``directions_deg`` (n_directions,) (not per frame).
    """
    if rate_hz <= 0 or speed_mm_s <= 0 or n_paired < 1 or dwell_samples < 0:
        raise InputError("rate_hz, speed_mm_s, n_paired must be positive; dwell_samples >= 0")
    ids = _indenter_ids(indenters)
    points = surface_points(n_points, point_offset_mm)
    levels = _depth_levels(depth_step_mm, max_depth_mm)
    ang = 2 * np.pi * np.arange(n_directions) / n_directions
    dirs = shear_radius_mm * np.column_stack([np.cos(ang), np.sin(ang)])
    zero = np.zeros(2)

    # One movement = (start shift, start depth, end shift, end depth, phase, direction, level,
    # new contact?). The same list serves every (indenter, point).
    moves = []

    def shears(depth, level):
        for k, d in enumerate(dirs):
            moves.append((zero, depth, d, depth, 1, k, level, False))
            moves.append((d, depth, zero, depth, 2, k, level, False))

    if shear_every_depth:
        for lv in levels:
            moves.append((zero, 0.0, zero, lv, 0, -1, lv, True))
            shears(lv, lv)
            moves.append((zero, lv, zero, 0.0, 3, -1, lv, False))
    else:
        prev = 0.0
        for j, lv in enumerate(levels):
            moves.append((zero, prev, zero, lv, 0, -1, lv, j == 0))
            prev = lv
        shears(prev, prev)
        moves.append((zero, prev, zero, 0.0, 3, -1, prev, False))

    # Sample the movement list once; per (indenter, point) copies only add offsets.
    step = speed_mm_s / rate_hz
    parts = {k: [] for k in ("shift", "depth", "phase", "dir", "level", "move", "paired",
                             "newc")}
    for m, (s0, d0, s1, d1, ph, k, lv, newc) in enumerate(moves):
        length = math.hypot(float(np.linalg.norm(s1 - s0)), d1 - d0)
        n = max(int(math.ceil(length / step - 1e-9)), n_paired)
        f = np.concatenate([np.arange(0 if newc else 1, n + 1) / n, np.ones(dwell_samples)])
        cnt = f.size
        parts["shift"].append(s0 + f[:, None] * (s1 - s0))
        parts["depth"].append(d0 + f * (d1 - d0))
        for key, val in (("phase", ph), ("dir", k), ("level", lv), ("move", m)):
            parts[key].append(np.full(cnt, val))
        parts["paired"].append(np.arange(cnt) >= cnt - n_paired)
        parts["newc"].append(np.arange(cnt) == 0 if newc else np.zeros(cnt, bool))
    one = {k: np.concatenate(v) for k, v in parts.items()}
    per = one["depth"].size
    contacts_per = int(one["newc"].sum())
    moves_per = len(moves)

    reps = len(ids) * len(points)
    rep = np.repeat(np.arange(reps), per)
    pt = rep % len(points)
    shift = np.tile(one["shift"], (reps, 1))
    depth = np.tile(one["depth"], reps)
    xy = points[pt] + shift
    contact = np.tile(np.cumsum(one["newc"]) - 1, reps) + rep * contacts_per
    n = depth.size
    return {
        "position": np.column_stack([xy, -depth]),
        "depth": depth,
        "shift": shift,
        "phase": np.tile(one["phase"], reps).astype(np.int8),
        "contact_id": contact.astype(np.int32),
        "indenter_id": np.asarray(ids, np.int16)[rep // len(points)],
        "point_id": pt.astype(np.int16),
        "direction_id": np.tile(one["dir"], reps).astype(np.int8),
        "movement_id": (np.tile(one["move"], reps) + rep * moves_per).astype(np.int32),
        "depth_level": np.tile(one["level"], reps).astype(float),
        "paired": np.tile(one["paired"], reps),
        "time": np.arange(n) / rate_hz,
        "indenters": np.array(ALL_INDENTERS),
        "points": points,
        "directions_deg": np.degrees(ang),
    }


def calibration_trajectory(*, max_depth_mm: float = 1.4, n_steps: int = 28,
                           repetitions: int = 3, indenter: str = "calib_prism",
                           position_mm=(0.0, 0.0), rate_hz: float = 40.0,
                           shear_mm: float = 0.0, shear_steps: int = 8) -> dict:
    """Material-compensation calibration: ``repetitions`` indentations to d_max and back.

    Per repetition (one contact each): loading at depths k*d_max/n_steps for k = 1..n_steps
    (phase 0; the peak d_max is sampled once), then, with ``shear_mm`` > 0, the shear leg at
    d_max: out along +x to shear_mm in ``shear_steps`` steps (phase 1) and back (phase 2), then
    the same along +y; then unloading at k = n_steps-1..0 (phase 3, ending at the surface).
    Quasi-static steps, one sample per step at ``rate_hz``.  The press and release frames
    give the force-depth curves (stages.force.compensation.fit_curves), the shear leg the
    sensor's shear-to-normal ratio (compensation.shear_ratio).
    Extras: ``loading`` (N,) bool (phases 0-2), ``normalised_depth`` (N,) depth / d_max,
    ``time`` (N,) s.  ``paired`` is all False (these frames are calibration, not M2M pairs).
    """
    if n_steps < 1 or repetitions < 1 or max_depth_mm <= 0:
        raise ValueError("n_steps, repetitions and max_depth_mm must be positive")
    if shear_mm < 0 or shear_steps < 1:
        raise ValueError("shear_mm must be >= 0 and shear_steps positive")
    (iid,) = _indenter_ids([indenter])
    press, release = np.arange(1, n_steps + 1), np.arange(n_steps - 1, -1, -1)
    out_back = np.r_[np.arange(1, shear_steps + 1), np.arange(shear_steps - 1, -1, -1)] / shear_steps
    leg = shear_mm * out_back if shear_mm > 0 else np.zeros(0)
    leg_phase = np.r_[np.ones(shear_steps), np.full(shear_steps, 2)] if shear_mm > 0 else np.zeros(0)
    shear_x = np.r_[np.zeros(n_steps), leg, np.zeros(leg.size), np.zeros(n_steps)]
    shear_y = np.r_[np.zeros(n_steps), np.zeros(leg.size), leg, np.zeros(n_steps)]
    k_one = np.r_[press, np.full(2 * leg.size, n_steps), release]       # steps of d_max / n_steps
    phase_one = np.r_[np.zeros(n_steps), leg_phase, leg_phase, np.full(n_steps, 3)]
    contact = np.repeat(np.arange(repetitions), k_one.size).astype(np.int32)
    depth = max_depth_mm * np.tile(k_one, repetitions) / n_steps
    phase = np.tile(phase_one, repetitions).astype(np.int8)
    n = depth.size
    shift = np.c_[np.tile(shear_x, repetitions), np.tile(shear_y, repetitions)]
    pos = np.empty((n, 3))             # the indenter's position: the touchdown point
    pos[:, 0], pos[:, 1], pos[:, 2] = position_mm[0], position_mm[1], -depth
    return {
        "position": pos,
        "depth": depth,
        "shift": shift,
        "phase": phase,
        "contact_id": contact,
        "indenter_id": np.full(n, iid, np.int16),
        "paired": np.zeros(n, bool),
        "loading": phase != 3,
        "normalised_depth": depth / max_depth_mm,
        "time": np.arange(n) / rate_hz,
        "indenters": np.array(ALL_INDENTERS),
    }
