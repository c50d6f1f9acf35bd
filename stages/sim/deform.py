"""Simulation twins: pad deformation and force labels along a contact trajectory.

`deform_sequence` (node `deform[sensor=...]`) streams a contact-sequence artifact, one chunk
per contact; `calibrate` (node `calibrate[sensor=...]`) gives the force-normalised-depth curves
of the calibration indentation that material compensation rescales labels with.

Every contact is solved by contact.solve_sequence from rest, so friction memory (shear out vs
back) and hysteresis (unloading softer than loading) act within a contact and never leak
between contacts.  Per-frame fields (frame axis N):
  force (N,3) float32 N, (Fx, Fy, Fz) on the pad, Fz < 0 pressing
  depth (N,) mm from first touch; normalised_depth (N,) float32, depth / sensor max_depth_mm
  position (N,3) mm indenter tip in the sensor frame (z = -depth); shift (N,2) mm since touchdown
  phase (N,) int8 0 press, 1 shear out, 2 shear back, 3 release; contact_id (N,) int32;
  indenter_id (N,) int16 (indexes `indenters`); paired (N,) bool; frame (N,) int64, the
  trajectory frame each row comes from (location pairing with other sensors and the hardware)
  displacement (N,h,w,3) float32 mm (ux, uy, uz; uz < 0 into the pad); pressure (N,h,w) float32 Pa
plus grid_x (w,), grid_y (h,) mm, surface_z (h,w) mm (the undeformed surface, 0 on a flat pad,
-sag on a dome), on_pad (h,w) bool, indenters (names), figures/force_trace.
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from stages.figures import figure_png
from stages.sim.contact import solve_sequence
from stages.sim.indenters import grid_coords, mesh_from_artifact
from stages.sim.sensors import (contact_height, material_of, pad_grid, sensor_attrs, solver_kwargs,
                                surface_gap)

_FRAME_KEYS = ("position", "depth", "shift", "phase", "contact_id", "indenter_id", "paired")


def _arrays(trajectory: Mapping, keys) -> dict:
    return {k: np.asarray(trajectory[k]) for k in keys if k in trajectory}


def select_frames(trajectory: Mapping, contacts_per_indenter: int = 0, frame_stride: int = 1,
                  contacts_of: Mapping[str, int] | None = None) -> np.ndarray:
    """Indices of the trajectory frames a twin simulates.

    contacts_per_indenter > 0 keeps that many contacts per indenter, evenly spread over the
    indenter's contacts in the collection protocol's order (by surface point, then depth
    level): with fewer contacts than points x levels, the picks' levels follow from that
    spacing (2 of 5 points x 4 levels: the second and fourth level, at the second and
    fourth point); 0 keeps all.  contacts_of (indenter
    name -> count) gives some indenters another count (the validation indenters more, so
    that the choices made on them rest on more contacts).  frame_stride > 1 keeps
    every stride-th sample of each movement counted back from its end, so every movement's
    target is kept, and every contact's first frame (its start, at rest).  The pick depends on
    the trajectory only, so every sensor simulated on the same trajectory gets the same frames
    (location-paired).
    """
    t = _arrays(trajectory, ("contact_id", "indenter_id", "movement_id"))
    contact, indenter = t["contact_id"], t["indenter_id"]
    keep = np.ones(contact.size, bool)
    contacts_of = dict(contacts_of or {})
    if contacts_per_indenter > 0 or contacts_of:
        names = np.asarray(trajectory["indenters"]).astype(str)
        chosen = []
        for iid in dict.fromkeys(indenter.tolist()):                 # order of appearance
            ids = np.unique(contact[indenter == iid])
            want = int(contacts_of.get(str(names[iid]), contacts_per_indenter))
            k = min(want, ids.size) if want > 0 else ids.size
            chosen.append(ids[((np.arange(k) + 0.5) * ids.size / k).astype(int)])
        keep &= np.isin(contact, np.concatenate(chosen))
    frames = np.flatnonzero(keep)
    if frame_stride > 1 and "movement_id" in t and frames.size:
        move = t["movement_id"][frames]
        ends = np.append(np.flatnonzero(np.diff(move)), move.size - 1)  # last row of each movement
        pos = np.arange(move.size)
        first = np.r_[True, np.diff(contact[frames]) != 0]
        frames = frames[((ends[np.searchsorted(ends, pos)] - pos) % int(frame_stride) == 0) | first]
    return frames


def _contacts(frames: np.ndarray, contact: np.ndarray) -> list[np.ndarray]:
    """Split the selected frame indices into runs of one contact each."""
    cid = contact[frames]
    cuts = np.flatnonzero(np.diff(cid)) + 1
    return np.split(frames, cuts) if frames.size else []


class _Meshes:
    """Indenter meshes from the `indenters` artifact, rebuilt once each."""

    def __init__(self, indenters: Mapping, names):
        self.art, self.names, self.cache = indenters, [str(n) for n in names], {}

    def __call__(self, iid: int):
        if iid not in self.cache:
            self.cache[iid] = mesh_from_artifact(self.art, self.names[iid])
        return self.cache[iid]


def _scale_shear(t: dict, shear_scale: float) -> None:
    """A sensor's shear strokes: the trajectory's shifts (and the positions they moved the tip
    to) times its `shear_scale`, in place."""
    if shear_scale != 1.0:
        shift = np.asarray(t["shift"], float)
        position = np.array(t["position"], float)
        position[:, :2] += (shear_scale - 1.0) * shift
        t["shift"], t["position"] = (shift * shear_scale).astype(t["shift"].dtype), position.astype(t["position"].dtype)


def _solve_contact_run(rows, t, meshes, spec, gap, kwargs, depth_scale):
    """One contact: height at the touchdown point, then the whole sequence with memory."""
    first = rows[0]
    point = t["position"][first, :2] - t["shift"][first]
    height = contact_height(meshes(int(t["indenter_id"][first])), spec, point, gap)
    depth = t["depth"][rows] * depth_scale
    return depth, solve_sequence(height, depth, t["shift"][rows], t["phase"][rows], **kwargs)


def _force_trace_png(force: np.ndarray, title: str) -> np.ndarray:
    from matplotlib.figure import Figure
    fig = Figure(figsize=(8, 3))
    ax = fig.add_subplot()
    for k, label in enumerate(("Fx", "Fy", "Fz")):
        ax.plot(force[:, k], lw=0.8, label=label)
    ax.set(xlabel="frame", ylabel="force (N)", title=title)
    ax.legend(loc="lower right", ncol=3, fontsize=8)
    fig.tight_layout()
    return figure_png(fig)


def deform_sequence(*, indenters: Mapping, sim_trajectory: Mapping, collection_trajectory: Mapping,
                    sensor: str, spec: Mapping, materials: Mapping,
                    contacts_per_indenter: int = 0, frame_stride: int = 1,
                    val_indenters: Sequence[str] = (), val_contacts_per_indenter: int = 0):
    """Node `deform[sensor=...]`: yields one chunk per contact, returns the per-sensor data.

    spec: the sensor's catalogue entry; its `trajectory` names the input to follow
    (`sim_trajectory` or `collection_trajectory`, the latter subsampled by
    contacts_per_indenter, val_contacts_per_indenter for the val_indenters (0: as the others)
    and frame_stride, see select_frames); its `depth_scale` multiplies that trajectory's
    depths and its `shear_scale` the shear strokes (the authors' TacTip protocol is the
    GelSight one with 4.5x the depths and 1.5x the shear radius).
    """
    from tqdm import tqdm

    sources = {"sim_trajectory": sim_trajectory, "collection_trajectory": collection_trajectory}
    if spec["trajectory"] not in sources:
        raise KeyError(f"sensor {sensor!r}: unknown trajectory {spec['trajectory']!r} "
                       f"(one of {', '.join(sources)})")
    trajectory = sources[spec["trajectory"]]
    material = material_of(spec, materials)
    kwargs = solver_kwargs(spec, material)
    scale, max_depth = float(spec["depth_scale"]), float(spec["max_depth_mm"])
    t = _arrays(trajectory, _FRAME_KEYS)
    _scale_shear(t, float(spec.get("shear_scale", 1.0)))
    if t["depth"].max(initial=0.0) * scale > max_depth * (1 + 1e-9):
        raise ValueError(f"sensor {sensor!r}: the trajectory presses to "
                         f"{t['depth'].max() * scale:.3g} mm, deeper than max_depth_mm {max_depth}")
    if spec["trajectory"] == "collection_trajectory":
        more = {str(n): int(val_contacts_per_indenter) for n in val_indenters} if val_contacts_per_indenter else {}
        frames = select_frames(trajectory, contacts_per_indenter, frame_stride, more)
    else:
        frames = np.arange(t["depth"].size)
    names = np.asarray(trajectory["indenters"]).astype(str)
    meshes, gap = _Meshes(indenters, names), surface_gap(spec)
    forces = []
    for rows in tqdm(_contacts(frames, t["contact_id"]), desc=f"deform[{sensor}]", unit="contact",
                     disable=None, leave=False):
        depth, res = _solve_contact_run(rows, t, meshes, spec, gap, kwargs, scale)
        position = t["position"][rows].copy()
        position[:, 2] = -depth
        force = res.force.astype(np.float32)
        forces.append(force)
        yield {"force": force, "depth": depth, "normalised_depth": (depth / max_depth).astype(np.float32),
               "position": position, "shift": t["shift"][rows], "phase": t["phase"][rows].astype(np.int8),
               "contact_id": t["contact_id"][rows].astype(np.int32),
               "indenter_id": t["indenter_id"][rows].astype(np.int16),
               "paired": t["paired"][rows].astype(bool), "frame": rows.astype(np.int64),
               "displacement": res.displacement.astype(np.float32),
               "pressure": res.pressure.astype(np.float32)}
    shape, spacing = pad_grid(spec)
    grid_x, grid_y = grid_coords(shape, spacing)
    on_pad = np.isfinite(gap)
    force = np.concatenate(forces) if forces else np.zeros((0, 3), np.float32)
    return {"grid_x": grid_x, "grid_y": grid_y, "surface_z": np.where(on_pad, -gap, 0.0),
            "on_pad": on_pad, "indenters": names,
            "figures": {"force_trace": _force_trace_png(force, f"{sensor}: force labels")},
            "attrs": {**sensor_attrs(sensor, spec, material), "trajectory": spec["trajectory"],
                      "depth_scale": scale, "shear_scale": float(spec.get("shear_scale", 1.0)),
                      "frames": int(frames.size)}}


def _force_depth_png(normalised, force, phase, repetition, title) -> np.ndarray:
    from matplotlib.figure import Figure
    fig = Figure(figsize=(4.5, 3.5))
    ax = fig.add_subplot()
    for rep in np.unique(repetition):
        for mask, style, colour, label in ((phase == 0, "-", "C0", "loading"),
                                           (phase == 3, "--", "C1", "unloading")):
            m = mask & (repetition == rep)
            ax.plot(normalised[m], -force[m, 2], style, color=colour, marker=".", ms=3, lw=0.8,
                    label=label if rep == repetition[0] else None)
    ax.set(xlabel="normalised depth", ylabel="-Fz (N)", title=title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return figure_png(fig)


def calibrate(*, indenters: Mapping, trajectory: Mapping, sensor: str, spec: Mapping,
              materials: Mapping) -> dict:
    """Node `calibrate[sensor=...]`: the calibration indentation on one sensor.

    The calibration trajectory's normalised depth is pressed to the sensor's max_depth_mm
    (the material study's GelSight gels 1.4 mm, the paper's d_max; the homo and hetero
    GelSights 1 mm, TacTip 4.5 mm and uSkin 1 mm, the paper's heterogeneous calibration), so
    every sensor's curve spans normalised depth 0..1; its shear leg is the sensor's collection
    stroke (the trajectory's times the sensor's shear_scale).
    Returns depth (N,) mm, normalised_depth (N,), force (N,3) float32, loading (N,) bool,
    repetition (N,) int32, phase (N,) int8, shift (N,2) mm (the shear leg's), and
    figures/force_depth.
    """
    t = _arrays(trajectory, _FRAME_KEYS + ("loading", "normalised_depth"))
    _scale_shear(t, float(spec.get("shear_scale", 1.0)))
    material = material_of(spec, materials)
    kwargs = solver_kwargs(spec, material)
    max_depth = float(spec["max_depth_mm"])
    names = np.asarray(trajectory["indenters"]).astype(str)
    meshes, gap = _Meshes(indenters, names), surface_gap(spec)
    normalised = t["normalised_depth"]
    t["depth"] = normalised * max_depth
    force, solved = np.zeros((normalised.size, 3), np.float32), {}
    for rows in _contacts(np.arange(normalised.size), t["contact_id"]):
        # repetitions of a deterministic indentation are identical: solve each distinct one once
        key = (int(t["indenter_id"][rows[0]]), t["position"][rows[0], :2].tobytes(),
               t["depth"][rows].tobytes(), t["shift"][rows].tobytes(), t["phase"][rows].tobytes())
        if key not in solved:
            solved[key] = _solve_contact_run(rows, t, meshes, spec, gap, kwargs, 1.0)[1].force
        force[rows] = solved[key]
    loading, repetition = t["loading"].astype(bool), t["contact_id"].astype(np.int32)
    indenter = str(names[t["indenter_id"][0]])
    return {"depth": t["depth"], "normalised_depth": normalised, "force": force, "loading": loading,
            "repetition": repetition, "phase": t["phase"].astype(np.int8),
            "shift": np.asarray(t["shift"], np.float32),
            "figures": {"force_depth": _force_depth_png(normalised, force, t["phase"], repetition,
                                                        f"{sensor}: calibration ({indenter})")},
            # what a lab measures in this indentation, and nothing the twin alone knows (its
            # elastomer's modulus, friction or hysteresis): the calibration feeds non-oracle methods
            "attrs": {"sensor": sensor, "indenter": indenter, "max_depth_mm": max_depth,
                      "pad_mm": [float(v) for v in spec["pad_mm"]],
                      "units": "mm, N; force (Fx, Fy, Fz) on the pad, Fz < 0 pressing"}}
