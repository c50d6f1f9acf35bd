"""The gripper interface the controllers drive, and its twin: a parallel gripper whose two
fingers carry simulated marker-based tactile sensors (GelSight twins by default).

Interface (:class:`Gripper`): ``width()`` opening in m, ``move(width_m, speed_m_s)`` a
non-blocking target, ``stop()``, ``read_sensors()`` a mapping finger -> (H, W) uint8 marker
image, and ``step(dt)``, which advances the twin and, on hardware, just paces the loop.  A
Franka hand fits behind it in a few lines (no dependency here); with libfranka's
``franka::Gripper`` (or its Python bindings), whose ``move(width, speed)`` blocks and whose
``stop()`` pre-empts it::

    class FrankaGripper:
        def __init__(self, hand, cameras, offset_m):   # cameras: finger -> () -> marker image
            self.hand, self.cameras, self.offset = hand, cameras, offset_m
            self.pool = concurrent.futures.ThreadPoolExecutor(1)
            self.tick = time.monotonic()
        def width(self):
            return self.hand.readOnce().width - self.offset     # gel-to-gel, not jaw opening
        def move(self, width_m, speed_m_s):
            self.hand.stop()                                   # pre-empt the running move
            self.pool.submit(self.hand.move, width_m + self.offset, speed_m_s)
        def stop(self):
            self.hand.stop()
        def read_sensors(self):
            return {finger: grab() for finger, grab in self.cameras.items()}
        def step(self, dt):                                    # real time: keep the loop rate
            self.tick += dt
            time.sleep(max(0.0, self.tick - time.monotonic()))

Twin (:class:`GripperTwin`).  Frames: each finger's pad frame has x along the pad, y along
gravity (down in the marker image) and z out of the pad; the right finger faces the left one,
so its x is mirrored.  The width is the gap between the two undeformed gel surfaces.

Normal: the fingers close at the commanded speed; the closure c = object width - gap is shared
by the series chain finger mount (k_f, each), gel (each), object (k_o):
2 F / k_f + 2 d_gel + F / k_o = c, with F = F_gel(d_gel) from the FEM-lite contact solver for the
object's face as the indenter.  F_gel(d) and the full-stick tangential stiffness K(d) (F_t = K s)
are tabulated once per object at 24 depths (log-log interpolation, exact for any power law;
Hertz and flat punches are power laws) and the series equation is solved by bisection, so a
physics substep costs microseconds.  The mounts' compliance matters: a P loop on width with
the paper's Kp = 0.4 mm/N needs Kp * stiffness < 2 (else it oscillates), and a gel pressed by a
flat face alone is tens of N/mm; 4 N/mm per finger (printed sensor mount and finger flex) keeps
any object below 2 N/mm.

Tangential: the external load L(t) (N, in the left pad frame: gravity and pulls) meets the
friction of both contacts, capacity 2 mu F, plus a viscous term c v of the elastomer interface
(implicit Coulomb step with the object's mass): the object sticks while the impulse can be
cancelled, else slides at v = (|L| - 2 mu F) / c once the transient of m / c (milliseconds)
is over.  Each pad carries half the friction force.  A sliding object's face moves across the
pads (the contact patch follows its slip); past `drop_mm` it is lost.

Sensing (at the frames, lazily, only when the contact state changed): contact solves of the
face at its slip position and depth d_gel, pressed and then sheared to carry the pad's shear
(full stick: the slip annulus near saturation is not resolved), give the true force and the
displacement field.  Two ways turn the field into the marker image:
  SkinCamera (camera=, what the control node uses): the skin's own image chain, the one its
      training frames came through: the Mitsuba render of the deformed pad with the skin's
      look (LEDs, camera noise; stages.markers.render.Renderer), segmented as the markers node
      segments it.  A force model then reads the twin's frames as it reads the skin's.  A shot
      is taken per finger when the contact state changes (the open pad's too), so its noise
      holds while the contact does.
  drawn masks (camera=None): the pattern's marker centres move with the field interpolated at
      them and are seen through the renders' pinhole camera (pressing brings the surface
      closer: markers spread and grow), each ellipse mapped by the local Jacobian, and
      stages.markers.patterns.rasterize draws the binary image: no Mitsuba, no segmentation.
      They agree with the renders' `truth` on 99.8% of the pixels, yet force models are
      sensitive to the marker edges: on the same deformations of A-II's unseen indenters the
      transfer model reads 0.99 of the true force on drawn masks and 1.27 on A-II's frames.
Gel hysteresis is not modelled: its switch at every depth reversal would chatter under the
controller's tiny corrections.
"""
from __future__ import annotations

import bisect
import math
from typing import Callable, Iterator, Mapping, Protocol

import numpy as np

from stages.control.objects import GraspObject, profile_height
from stages.markers.patterns import MarkerSet, gelsight_pattern, rasterize
from stages.sim.contact import solve_contact
from stages.sim.indenters import grid_coords
from stages.sim.sensors import pad_grid

FINGERS = ("left", "right")
_TABLE_SHIFT_MM = 0.1          # full stick is linear: any small shift gives the stiffness


class Gripper(Protocol):
    """What a force controller needs from a gripper (twin or hardware)."""

    def width(self) -> float:
        """Current opening in m."""

    def move(self, width_m: float, speed_m_s: float) -> None:
        """Start moving towards `width_m` at `speed_m_s`; returns at once."""

    def stop(self) -> None:
        """Hold the current width."""

    def read_sensors(self) -> Mapping:
        """finger name -> (H, W) uint8 binary marker image (white markers on black)."""

    def step(self, dt: float) -> None:
        """Advance by dt seconds (the twin simulates; hardware waits)."""


class GelTable:
    """Normal force and full-stick tangential stiffness of one gel against one object face, at
    24 depths up to max_depth_mm (denser near 0).  The stiffness only guesses a shift's
    direction (GripperTwin._solve_frame scales the actual solve)."""

    def __init__(self, height: np.ndarray, solver: Mapping, max_depth_mm: float = 1.6, n: int = 24):
        self.depth = max_depth_mm * (np.arange(1, n + 1) / n) ** 2
        force, stiff = np.zeros(n), np.zeros((n, 2, 2))
        for i, d in enumerate(self.depth):
            rx = solve_contact(height, d, shift=(_TABLE_SHIFT_MM, 0.0), **solver)
            ry = solve_contact(height, d, shift=(0.0, _TABLE_SHIFT_MM), **solver)
            force[i] = -rx.force[2]
            stiff[i] = np.stack([rx.force[:2], ry.force[:2]], axis=1) / _TABLE_SHIFT_MM
        if not np.all(np.diff(force) > 0):
            raise ValueError("gel force table is not increasing: the face misses the pad grid")
        self.normal, self.stiffness_table = force, stiff
        self._ld, self._lf = np.log(self.depth), np.log(force)
        self._slope = np.diff(self._lf) / np.diff(self._ld)
        # scalar lookups in the physics substeps: plain floats beat numpy calls by 10x
        self._ld_list, self._lf_list = self._ld.tolist(), self._lf.tolist()
        self._slope_list = self._slope.tolist()

    def force(self, depth: float) -> float:
        """Gel normal force (N) at `depth` mm: piecewise power law between the table nodes."""
        if depth <= 0:
            return 0.0
        ld = math.log(depth)
        i = min(max(bisect.bisect_left(self._ld_list, ld) - 1, 0), len(self._slope_list) - 1)
        return math.exp(self._lf_list[i] + self._slope_list[i] * (ld - self._ld_list[i]))

    def stiffness(self, depth: float) -> np.ndarray:
        """(2, 2) N/mm with F_t = K s under full stick, linear in depth between the nodes."""
        d = np.clip(depth, self.depth[0], self.depth[-1])
        return np.stack([[np.interp(d, self.depth, self.stiffness_table[:, r, c]) for c in range(2)]
                         for r in range(2)])

    def series_depth(self, closure_mm: float, compliance_mm_N: float) -> float:
        """Gel depth d solving 2 d + F(d) * compliance = closure (both gels and the compliance
        of everything else in series), by bisection."""
        if closure_mm <= 0:
            return 0.0
        lo, hi = 0.0, 0.5 * closure_mm
        for _ in range(40):                         # 2^-40 of the closure: far below a micron
            mid = 0.5 * (lo + hi)
            if 2 * mid + self.force(mid) * compliance_mm_N > closure_mm:
                hi = mid
            else:
                lo = mid
        return 0.5 * (lo + hi)


def _bilinear(field: np.ndarray, gx: np.ndarray, gy: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """field (h, w, k) on the grid (gx columns, gy rows) at points (n, 2) mm -> (n, k)."""
    fx = np.clip((pts[:, 0] - gx[0]) / (gx[1] - gx[0]), 0, gx.size - 1.000001)
    fy = np.clip((pts[:, 1] - gy[0]) / (gy[1] - gy[0]), 0, gy.size - 1.000001)
    i, j = fy.astype(int), fx.astype(int)
    ty, tx = (fy - i)[:, None], (fx - j)[:, None]
    return ((1 - ty) * ((1 - tx) * field[i, j] + tx * field[i, j + 1])
            + ty * ((1 - tx) * field[i + 1, j] + tx * field[i + 1, j + 1]))


def deformed_markers(markers: MarkerSet, displacement: np.ndarray, grid_x: np.ndarray,
                     grid_y: np.ndarray, camera_mm: float | None = None) -> MarkerSet:
    """Markers carried by the pad's surface displacement (h, w, 3) mm on the solver grid, as
    the camera behind the pad sees them.

    A surface point p moves to p + u(p); a pinhole camera camera_mm behind the undeformed
    surface (None: orthographic) images it at P = s (p + u), s = D / (D + uz), so pressed
    regions (uz < 0, towards the camera) magnify as in the Mitsuba renders.  Each centre goes to
    P(centre) and each ellipse is mapped by the Jacobian of P there (from the field's gradients).
    """
    gx, gy = grid_x[1] - grid_x[0], grid_y[1] - grid_y[0]
    comps = [displacement[..., k] for k in range(3)]
    field = np.stack(comps + [np.gradient(c, gx, axis=1) for c in comps]
                     + [np.gradient(c, gy, axis=0) for c in comps], -1)
    at = _bilinear(field, grid_x, grid_y, markers.centers)
    moved = markers.centers + at[:, :2]
    grad = np.stack([at[:, 3:5], at[:, 6:8]], -1)        # (n, 2, 2): d(ux, uy) / d(x, y)
    jac = np.eye(2) + grad
    if camera_mm is not None:
        scale = camera_mm / (camera_mm + at[:, 2])
        grad_uz = np.stack([at[:, 5], at[:, 8]], -1)
        jac = scale[:, None, None] * jac - (scale ** 2 / camera_mm)[:, None, None] \
            * moved[:, :, None] * grad_uz[:, None, :]
        moved = scale[:, None] * moved
    c, s = np.cos(markers.angles), np.sin(markers.angles)
    shape = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2) * markers.axes[:, None, :]
    u, sv, _ = np.linalg.svd(jac @ shape)
    return MarkerSet(moved, sv, np.arctan2(u[:, 1, 0], u[:, 0, 0]), markers.pad_size_mm)


def _mirror_x(displacement: np.ndarray) -> np.ndarray:
    """The facing finger's view of a symmetric contact: x flipped (columns and ux)."""
    out = displacement[:, ::-1].copy()
    out[..., 0] *= -1
    return out


class SkinCamera:
    """A skin's image chain for the twin's pads: the Mitsuba render of the deformed pad with the
    skin's look (stages.markers.render.Renderer: the renders' camera, LEDs and camera noise),
    then the markers node's segmentation of its camera look (the render's `truth` for look
    none).  Built once (the Mitsuba scene) and shared by every twin on the same grid.

    grid_x / grid_y: the twin's solver grid (mm); markers: the skin's pattern; spec: the skin's
    params (`look`, optional `light`, `noise`); segmentation: the `segmentation` params;
    upsample: mesh vertices per solver cell and axis (2 on a 33x33 grid gives the 65x65
    vertex grid the training frames were rendered on).  Camera noise of shot i is seeded by
    (seed, i), as the render node seeds frame i.  reference_seed: the seed of the no-contact
    reference shot (default seed).  The render node's seed gives the skin's own reference, the
    one its models were trained with, as a sensor keeps the reference captured at set-up.
    """

    def __init__(self, grid_x, grid_y, markers: MarkerSet, *, spec: Mapping, size=(128, 128),
                 segmentation: Mapping | None = None, seed: int = 0, upsample: float = 1.0,
                 backend: str = "auto", reference_seed: int | None = None):
        from stages.markers.render import Renderer
        from stages.markers.unify import segmentation_params

        look = spec.get("look", "none")
        if look not in ("none", "gelsight", "tactip"):
            raise ValueError(f"SkinCamera: look {look!r} is not a camera look (none, gelsight, tactip)")
        shape = (len(grid_y), len(grid_x))
        self.look, self.size, self.grid_shape = look, tuple(int(v) for v in size), shape
        self.markers = markers
        self.renderer = Renderer(grid_x, grid_y, np.zeros(shape), np.ones(shape, bool), markers,
                                 look=look, size=self.size, backend=backend,
                                 light=spec.get("light"), noise=float(spec.get("noise", 0.0)),
                                 seed=int(seed), upsample=float(upsample))
        self.segmentation = segmentation_params(segmentation or {}, look) if look != "none" else {}
        self.reference_seed = int(seed if reference_seed is None else reference_seed)
        self.renderer.seed = self.reference_seed
        self.reference = self(np.zeros(shape + (3,), np.float32), -1)
        self.renderer.seed = int(seed)

    def __call__(self, displacement: np.ndarray, index: int) -> np.ndarray:
        """(H, W) uint8 0/255 marker image of the pad's displacement (h, w, 3) mm."""
        from stages.markers.segment import segment

        out = self.renderer.render(np.asarray(displacement, np.float32), int(index))
        return out["truth"] if self.look == "none" else segment(out["raw"], **self.segmentation)


class _Images(Mapping):
    """The twin's sensor readings of one frame, rendered on first access (most loops read one)."""

    def __init__(self, twin: "GripperTwin", displacement):
        self.twin, self.displacement, self.cache = twin, displacement, {}

    def __getitem__(self, finger: str) -> np.ndarray:
        return self.image(finger).copy()

    def image(self, finger: str) -> np.ndarray:
        if finger not in FINGERS:
            raise KeyError(f"unknown finger {finger!r}; expected one of {FINGERS}")
        if finger not in self.cache:
            self.cache[finger] = self.twin.render(finger, self.displacement)
        return self.cache[finger]

    def __iter__(self) -> Iterator[str]:
        return iter(FINGERS)

    def __len__(self) -> int:
        return len(FINGERS)


class GripperTwin:
    """Two parallel fingers with tactile sensor twins and one object between them.

    sensor / material: a sensor catalogue entry and its elastomer (params `sensors.<name>`,
    `materials.<name>`); grid (rows, cols) overrides the sensor's solver grid (the same pad,
    coarser cells, for speed).  pattern: the marker layout (GelSight A-II by default); size:
    marker image (H, W).  load: t -> external tangential load on the object (2,) N in the left
    pad frame (None: none).  width_m: initial opening (default object width + approach_mm).
    camera_mm: the drawn masks' pinhole camera distance behind the pad ("render": the Mitsuba
    renders' camera for this image size; None: orthographic).  camera: a SkinCamera on this
    twin's grid (None: drawn masks); it then makes the images (a shot per finger and changed
    contact state, the open pad's too) and the reference, and its pattern replaces `pattern`.
    first_shot: the camera's shots are numbered from first_shot + 1 (their noise streams: give
    each episode its own).
    """

    def __init__(self, obj: GraspObject, *, sensor: Mapping, material: Mapping,
                 pattern: MarkerSet | None = None, size=(128, 128), grid=None,
                 width_m: float | None = None, approach_mm: float = 3.0, finger_N_mm: float = 4.0,
                 damping_N_s_m: float = 30.0, load: Callable[[float], np.ndarray] | None = None,
                 substep_s: float = 0.005, max_width_m: float = 0.08, drop_mm: float = 8.0,
                 camera_mm: float | str | None = "render", table: GelTable | None = None,
                 camera: SkinCamera | None = None, first_shot: int = 0):
        shape, spacing = pad_grid(sensor)
        if grid is not None:
            new = tuple(int(v) for v in grid)
            spacing *= (shape[1] - 1) / (new[1] - 1)
            shape = new
        self.obj, self.shape, self.spacing = obj, shape, float(spacing)
        self.grid_x, self.grid_y = grid_coords(shape, self.spacing)
        self.solver = {"spacing": self.spacing, "E": float(material["E"]), "nu": float(material["nu"]),
                       "thickness": float(sensor["thickness_mm"])}
        self.table = table or GelTable(profile_height(obj, shape, self.spacing), self.solver)
        if camera is not None:
            self.markers = camera.markers
        else:
            self.markers = pattern if pattern is not None else gelsight_pattern("A-II")
        self.size = tuple(int(v) for v in size)
        self.camera, self._shots = camera, int(first_shot)
        if camera is not None:
            if camera.size != self.size or camera.grid_shape != tuple(self.shape):
                raise ValueError(f"GripperTwin: the camera renders {camera.size} images of a "
                                 f"{camera.grid_shape} grid, the twin has {self.size} images "
                                 f"of a {tuple(self.shape)} grid")
            self.reference = camera.reference.copy()
        else:
            self.reference = rasterize(self.markers, size=self.size)
        if camera_mm == "render":                  # the camera of the marker renders (render[skin])
            from stages.markers.render import camera_distance
            camera_mm = camera_distance(self.size, self.markers.pad_size_mm)
        self.camera_mm = None if camera_mm is None else float(camera_mm)
        self.compliance = 2.0 / float(finger_N_mm) + 1.0 / obj.stiffness_N_mm    # mm/N
        self.damping, self.load, self.substep = float(damping_N_s_m), load, float(substep_s)
        self.max_width, self.drop_mm = float(max_width_m), float(drop_mm)
        w0 = (obj.width_mm + approach_mm) * 1e-3 if width_m is None else float(width_m)
        self.t = 0.0
        self._width = self._target = min(w0, self.max_width)
        self._speed = 0.0
        self.gel_mm = self.normal_N = self.max_normal_N = 0.0
        self.slip_mm = np.zeros(2)
        self.velocity = np.zeros(2)                 # object slip velocity, m/s
        self.shear_N = np.zeros(2)                  # tangential force on the left pad
        self.crushed = self.dropped = False
        self._frame, self._closure, self._pressed_cache = None, None, None
        self._physics(0.0)

    # -- the Gripper interface
    def width(self) -> float:
        return self._width

    def move(self, width_m: float, speed_m_s: float) -> None:
        self._target = float(np.clip(width_m, 0.0, self.max_width))
        self._speed = abs(float(speed_m_s))

    def stop(self) -> None:
        self._target = self._width

    def step(self, dt: float) -> None:
        n = max(1, int(np.ceil(dt / self.substep - 1e-9)))
        h = dt / n
        for _ in range(n):
            reach = self._speed * h
            self._width += min(max(self._target - self._width, -reach), reach)
            self.t += h
            self._physics(h)
        if self._frame is not None and self._frame[0] != self._state_key():
            self._frame = None                      # unchanged contact: keep solve and images

    def read_sensors(self) -> Mapping:
        """finger -> marker image of this frame; each image is drawn when first looked up."""
        self._solve_frame()
        return self._frame[3]

    def render(self, finger: str, displacement: np.ndarray | None) -> np.ndarray:
        """A finger's marker image for the left pad's displacement field (None: no contact; a
        camera still takes a shot of the open pad, with its own noise)."""
        if self.camera is not None:
            if displacement is None:
                view = np.zeros(self.shape + (3,), np.float32)
            else:
                view = _mirror_x(displacement) if finger == "right" else displacement
            self._shots += 1                        # each shot its own camera noise
            return self.camera(view, self._shots)
        if displacement is None:
            return self.reference.copy()
        view = _mirror_x(displacement) if finger == "right" else displacement
        markers = deformed_markers(self.markers, view, self.grid_x, self.grid_y, self.camera_mm)
        return rasterize(markers, size=self.size)

    # -- twin-only state
    def true_force(self, finger: str = "left") -> np.ndarray:
        """(Fx, Fy, Fz) N the object exerts on a finger's pad, in that pad's frame (Fz < 0)."""
        force = self._solve_frame()[0].copy()
        if finger == "right":
            force[0] *= -1
        elif finger != "left":
            raise KeyError(f"unknown finger {finger!r}; expected one of {FINGERS}")
        return force

    @property
    def sliding(self) -> bool:
        return bool(np.any(self.velocity != 0))

    def _physics(self, h: float) -> None:
        """Normal force from the series chain, then one implicit Coulomb + viscous slip step."""
        closure = self.obj.width_mm - self._width * 1e3
        if self.dropped or closure <= 0:
            self.gel_mm = self.normal_N = 0.0
        elif closure != self._closure:             # the width holds most of the time
            self.gel_mm = self.table.series_depth(closure, self.compliance)
            self.normal_N = self.table.force(self.gel_mm)
        self._closure = closure
        self.max_normal_N = max(self.max_normal_N, self.normal_N)
        self.crushed |= self.normal_N > self.obj.crush_N
        load = np.zeros(2) if self.load is None or self.dropped else np.asarray(self.load(self.t), float)
        if h <= 0 or self.dropped:
            self.shear_N = 0.5 * load if self.normal_N > 0 else np.zeros(2)
            return
        m, cap = self.obj.mass_kg, 2.0 * self.obj.mu * self.normal_N
        impulse = m * self.velocity + h * load
        size = float(np.hypot(*impulse))
        if size <= h * cap:                                   # friction can hold it: stick
            self.velocity = np.zeros(2)
            friction = load
        else:
            direction = impulse / size
            self.velocity = (impulse - h * cap * direction) / (m + self.damping * h)
            friction = cap * direction + self.damping * self.velocity
        self.slip_mm = self.slip_mm + self.velocity * h * 1e3
        self.shear_N = 0.5 * friction
        if float(np.hypot(*self.slip_mm)) > self.drop_mm:
            self.dropped, self.velocity = True, np.zeros(2)
            self.gel_mm = self.normal_N = 0.0
            self.shear_N = np.zeros(2)

    def _state_key(self) -> tuple:
        return (self.gel_mm, *self.slip_mm.tolist(), *self.shear_N.tolist())

    def _solve_frame(self):
        """(force (3,), displacement (h, w, 3) or None) of the left pad, cached per contact state.

        The full-stick shear response is linear in the shift for a given contact (the pressure
        does not depend on it), so a pressed-only solve and one sheared solve, combined with the
        weight that makes the pad's shear force equal to shear_N, give the exact field; the
        stiffness table only guesses the shift's direction (the coarse grid's contact set, and
        so the stiffness, changes in steps that no table between depths can follow).
        """
        if self._frame is None:
            if self.gel_mm <= 0:
                force, disp = np.zeros(3), None
            else:
                height, pressed = self._pressed()
                force, disp = pressed.force, pressed.displacement
                if np.any(self.shear_N != 0):
                    guess = np.linalg.solve(self.table.stiffness(self.gel_mm), self.shear_N)
                    sheared = solve_contact(height, self.gel_mm, shift=tuple(guess), **self.solver)
                    ft = sheared.force[:2]
                    if float(ft @ ft) > 0:   # the sheared contact carries shear: scale it to shear_N
                        weight = float(ft @ self.shear_N) / float(ft @ ft)
                        force = force + weight * (sheared.force - force)
                        disp = disp + weight * (sheared.displacement - disp)
            self._frame = (self._state_key(), force, disp, _Images(self, disp))
        return self._frame[1], self._frame[2]

    def _pressed(self):
        """(height map, contact pressed without shear), reused while depth and slip hold."""
        key = (self.gel_mm, *self.slip_mm.tolist())
        if self._pressed_cache is None or self._pressed_cache[0] != key:
            height = profile_height(self.obj, self.shape, self.spacing, center=self.slip_mm)
            self._pressed_cache = (key, height, solve_contact(height, self.gel_mm, **self.solver))
        return self._pressed_cache[1:]
