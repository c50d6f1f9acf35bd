"""The FEM-lite twin a robot drives, for emulated capture.

`ContactTwin` turns one measured tip position after another into the pad's contact state with
the same machinery and memory as the `deform` node: a contact starts when the tip first goes
below the pad surface (its touchdown point fixes the indenter's height map, see
sensors.contact_height), every later pose is one frame of the incremental solver (friction
slip and the pressure field carried over, E lowered by the hysteresis while the depth
decreases), and it ends when the tip is back at or above the surface.  Fed the frames of a
trajectory contact, it gives deform's forces for those frames.

`World` holds the twin's latest state, stamped under a lock, for the emulated devices:
  wrench   (Fx, Fy, Fz, Tx, Ty, Tz) N and N m about the pad centre, pad frame, Fz < 0 pressing
  image    the marker pattern with every marker centre moved by the pad's lateral displacement
           under it, rasterised white on black to the camera frame (the pad's height fills the
           frame's height, centred), RGB
  signals  uSkin raw counts (16, 3) from the pad's displacement by the `taxels` node's model
           (stages.markers.uskin.taxel_signals: cell-mean displacement x gains around 32768,
           taxels row-major, row = y), on the twin's pad
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Callable, Mapping

import numpy as np

from stages.capture.poses import to_sensor
from stages.sim.contact import _frame, _pack, _t_unit   # one solver frame with carried memory
from stages.sim.indenters import grid_coords
from stages.sim.sensors import contact_height, pad_grid, solver_kwargs, surface_gap

_TOUCH_MM = 1e-9       # the tip is in contact when it is deeper than this


@dataclass(frozen=True)
class ContactState:
    depth: float                 # mm below the surface at first touch (<= 0: no contact)
    pressure: np.ndarray         # (h, w) Pa
    traction: np.ndarray         # (h, w, 2) Pa
    displacement: np.ndarray     # (h, w, 3) mm
    force: np.ndarray            # (3,) N, Fz < 0 pressing


class ContactTwin:
    """Incremental contact of the mounted indenter on one sensor's pad."""

    def __init__(self, spec: Mapping, material: Mapping, mesh_of: Callable[[str], object]):
        self.spec, self.mesh_of = spec, mesh_of
        self.kw = solver_kwargs(spec, material)
        self.shape, self.spacing = pad_grid(spec)
        self.grid_x, self.grid_y = grid_coords(self.shape, self.spacing)
        self.gap = surface_gap(spec)
        self.t_unit = _t_unit(self.kw["thickness"], self.spacing)
        h, w = self.shape
        self.rest = ContactState(0.0, np.zeros((h, w)), np.zeros((h, w, 2)), np.zeros((h, w, 3)), np.zeros(3))
        self.mounted: str | None = None
        self._contact: dict | None = None

    def mount(self, name: str) -> None:
        self.mounted, self._contact = name, None

    def step(self, tip_mm) -> ContactState:
        tip = np.asarray(tip_mm, float)
        depth = -float(tip[2])
        if depth <= _TOUCH_MM or self.mounted is None:
            self._contact = None
            return self.rest
        c = self._contact
        if c is None:
            height = contact_height(self.mesh_of(self.mounted), self.spec, tip[:2], self.gap)
            c = self._contact = {"height": height, "point": tip[:2].copy(), "slip": None, "warm": None,
                                 "depth": None}
        shift = tip[:2] - c["point"]
        unloading = c["depth"] is not None and depth < c["depth"] - 1e-12
        e = self.kw["E"] * (1.0 - self.kw["hysteresis"]) if unloading else self.kw["E"]
        p, q, ut, disp = _frame(c["height"], depth, shift, c["slip"], self.spacing, self.kw["nu"],
                                self.t_unit, self.kw["mu"], c["warm"])
        c["slip"], c["depth"] = shift - ut, depth
        c["warm"] = p if p.any() else c["warm"]
        pressure, traction, disp, force = _pack(p, q, disp, self.spacing, e)
        return ContactState(depth, pressure, traction, disp, force)

    # -- what the devices measure --------------------------------------------------------
    def wrench(self, state: ContactState) -> np.ndarray:
        """(6,) force N and torque N m about the pad centre on the surface, pad frame."""
        area = self.spacing ** 2 * 1e-6
        fx, fy = state.traction[..., 0] * area, state.traction[..., 1] * area
        fz = -state.pressure * area
        x, y = self.grid_x[None, :] * 1e-3, self.grid_y[:, None] * 1e-3
        torque = [float((y * fz).sum()), float((-x * fz).sum()), float((x * fy - y * fx).sum())]
        return np.concatenate([state.force, torque])


def marker_image(markers, displacement: np.ndarray, grid_x: np.ndarray, grid_y: np.ndarray, *,
                 size=(480, 640), supersample: int = 1) -> np.ndarray:
    """(H, W, 3) uint8: white markers moved by the lateral displacement under their centres."""
    from scipy.ndimage import map_coordinates

    from stages.markers.patterns import MarkerSet, rasterize
    h, w = (int(v) for v in size)
    c = markers.centers
    dx, dy = grid_x[1] - grid_x[0], grid_y[1] - grid_y[0]
    coords = np.stack([(c[:, 1] - grid_y[0]) / dy, (c[:, 0] - grid_x[0]) / dx])
    moved = c + np.stack([map_coordinates(displacement[..., k], coords, order=1, mode="constant")
                          for k in (0, 1)], axis=1)
    pad_h = markers.pad_size_mm[1]
    view = MarkerSet(moved, markers.axes, markers.angles, (pad_h * w / h, pad_h))
    import cv2
    return cv2.cvtColor(rasterize(view, size=(h, w), supersample=supersample), cv2.COLOR_GRAY2RGB)


def marker_layout(name: str, seed: int = 0):
    """A MarkerSet by its `patterns` artifact name: a sim pattern, gelsight-<twin>, tactip, uskin."""
    from stages.markers import patterns as pt
    if name in pt.PATTERNS:
        return pt.pattern(name)
    if name.startswith("gelsight-"):
        return pt.gelsight_pattern(name[len("gelsight-"):], seed=seed)
    if name in ("tactip", "uskin"):
        return pt.tactip_pattern() if name == "tactip" else pt.uskin_pattern()
    from stages.common import InputError
    raise InputError(f"unknown marker pattern {name!r} (a simulation pattern, gelsight-<twin>, tactip or uskin)")


class World:
    """The twin's latest state under a lock, as the emulated devices see it."""

    def __init__(self, twin: ContactTwin, *, origin, yaw_deg: float = 0.0, markers=None,
                 image_size=(480, 640), supersample: int = 1, gains=None, noise: float = 0.0):
        self.twin, self.origin, self.yaw = twin, np.asarray(origin, float), float(yaw_deg)
        self.markers, self.image_size, self.supersample = markers, tuple(image_size), int(supersample)
        self.gains, self.noise = gains, float(noise)
        self._lock = threading.Lock()
        self.pose = np.concatenate([self.origin[:3] + [0.0, 0.0, 0.05], self.origin[3:]])
        self.state, self.moves = twin.rest, 0
        self._cache: dict[str, tuple] = {}

    def mount(self, name: str) -> None:
        with self._lock:
            self.twin.mount(name)

    def move_to(self, pose) -> None:
        pose = np.asarray(pose, float)
        state = self.twin.step(to_sensor(pose, self.origin, self.yaw))
        with self._lock:
            self.pose, self.state = pose, state
            self.moves += 1

    def snapshot(self) -> tuple[float, np.ndarray, ContactState]:
        """(host time, TCP pose, state), taken together: a device stamping its sample with this
        time never reports a state older than a move that finished before it."""
        with self._lock:
            return time.time(), self.pose.copy(), self.state

    def _cached(self, kind: str, state: ContactState, make):
        hit = self._cache.get(kind)
        if hit is not None and hit[0] is state:
            return hit[1]
        value = make()
        self._cache[kind] = (state, value)
        return value

    def wrench(self, state: ContactState) -> np.ndarray:
        return self._cached("wrench", state, lambda: self.twin.wrench(state))

    def signals(self, state: ContactState) -> np.ndarray:
        from stages.markers.uskin import GAINS, taxel_signals
        tw = self.twin
        return self._cached("signals", state, lambda: taxel_signals(
            state.displacement[None], tw.grid_x, tw.grid_y, pad_mm=tw.spec["pad_mm"],
            gains=GAINS if self.gains is None else self.gains, noise=self.noise, seed=self.moves)[0])

    def image(self, state: ContactState) -> np.ndarray:
        if self.markers is None:
            raise ValueError("this emulated world has no marker pattern (camera.pattern)")
        return self._cached("image", state, lambda: marker_image(
            self.markers, state.displacement, self.twin.grid_x, self.twin.grid_y,
            size=self.image_size, supersample=self.supersample))
