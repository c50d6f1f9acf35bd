"""Node `capture`: the robot presses the indenter through a trajectory while every device is read.

Acquisition is step-and-hold: for every selected trajectory frame the robot makes a blocking
moveL to the frame's tip position (poses.py: sensor-frame mm -> TCP pose through
`robot.origin`, `robot.yaw_deg`; depth times `session.depth_scale`), then reads the TCP pose,
every sensor (each sample taken at or after the robot stopped, see devices.py), and the TCP
pose again.  Each row's `position` is the measured tip position interpolated linearly
between those two pose readings at the force sample's timestamp (at the camera's when there is
no F/T sensor); `depth` = -position z, `shift` = the trajectory's shift corrected by the
measured lateral error; `target` keeps the commanded position.  `rate_hz` > 0 paces the steps
to at most that rate (the paper recorded at 40 Hz); 0 runs as fast as the devices answer.

Per contact (one touchdown .. lift-off of the trajectory): the robot goes `approach_mm` above
the touchdown point (via `clearance_mm` at the start and at indenter changes), the F/T sensor
is tared there (mean of `tare_samples` readings), the frames are captured, the robot lifts
back, and the staging file commits the contact.  At the first contact the camera frame and
taxel signals at the lifted pose are kept as the no-contact references.  Forces are stored
as sign * (reading - tare) per axis (`sign`: the F/T mounting -> the paper's pad frame, Fz < 0
pressing).  A dropped camera frame is retried; when every retry fails the row repeats the last
good frame and `camera_valid` is False.

Indenter changes (session.tool_change): "auto" lets the emulated twin mount the next indenter
itself; on hardware, or with "operator", the operator mounts the trajectory's first indenter
before starting, and at every change the capture stops (DeviceError "mount indenter 'prism'
...") with everything so far committed; the next `pipeline run capture` continues with that
indenter assumed mounted.

Faults: any device error stops the capture with a DeviceError naming the device and the frame;
complete contacts stay in the staging file and the next run resumes after them (staging.py).
A resumed run must share every parameter that shapes the data (trajectory selection, devices,
origin, F/T scale and sign, camera size, emulator physics...); addresses, timeouts, loss limits,
retries, robot speeds, `rate_hz` and faults (OPERATIONAL) may change, e.g. a longer timeout_s.

When every contact is captured the node yields the staged rows in chunks and returns the rest;
the engine seals it into the store, and only once the artifact is durably published does it
delete the staging file (`after_publish`), so a kill at any instant leaves the staging file or
the artifact.

Curved pads: the pose map puts first touch at z = 0 at every point, true on a flat pad (and in
the twin, which counts depth from first touch at each touchdown point as deform does); on a
dome the hardware's off-centre points first touch lower by the dome's sag, which this capture
does not add.

Outputs (N frames): force (N,3) float32 N, torque (N,3) float32 N m (F/T devices; NaN
without one), position (N,3), target (N,3), depth (N,), normalised_depth (N,) float32 (depth /
session.max_depth_mm, default the deepest target), shift (N,2), phase, contact_id,
indenter_id, paired, frame (trajectory rows), timestamps/<device> (N,) s on the host clock
(robot: its first pose reading after the move), raw (N,H,W,3) uint8 and camera_valid (N,)
bool (camera; H,W = camera.out_size or camera.size), signals (N,16,3) int32 raw counts (xela
or slcan); reference_raw (H,W,3), reference_signals (16,3), indenters (names); attrs: sensor,
devices, emulate, frames, contacts, sessions, seconds, rate_hz_achieved, per-device counters
(`<device>_<counter>`, e.g. netft_lost, camera_invalid), robot origin/yaw, units.
"""
from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import time
from typing import Mapping

import numpy as np

from stages.capture import DeviceError
from stages.capture.devices import DEVICES, Camera, Robot, client_class
from stages.capture.poses import check_origin, to_pose, to_sensor
from stages.capture.staging import Staging
from stages.common import InputError

SESSION_DEFAULTS = {"name": None, "indenters": None, "contacts_per_indenter": 0, "frame_stride": 1,
                    "depth_scale": 1.0, "max_depth_mm": None, "chunk_frames": 64, "tool_change": "auto"}
FORCE_DEVICES, TACTILE_DEVICES = ("netft", "serial_ft"), ("xela", "slcan")
# device parameters a resumed run may change: where and how fast devices answer, how patient
# the capture is, and the emulators' faults
OPERATIONAL = frozenset({"faults", "ip", "host", "port", "url", "baudrate", "mode", "timeout_s", "retry_s",
                         "settle_s", "max_lost_fraction", "min_records", "retries", "max_consecutive",
                         "max_invalid_fraction", "min_samples", "flush", "fps", "speed", "acceleration",
                         "approach_mm", "clearance_mm"})
_LABELS = ("phase", "contact_id", "indenter_id", "paired")
_DTYPES = {"phase": np.int8, "contact_id": np.int32, "indenter_id": np.int16, "paired": bool}


def _session(session: Mapping | None, sensor: str) -> dict:
    unknown = set(session or {}) - set(SESSION_DEFAULTS)
    if unknown:
        raise InputError(f"capture session: unknown parameter(s) {', '.join(sorted(unknown))} "
                         f"(known: {', '.join(SESSION_DEFAULTS)})")
    s = {**SESSION_DEFAULTS, **(session or {})}
    s["name"] = str(s["name"] or sensor)
    if not s["name"] or any(c in s["name"] for c in "/\\"):
        raise InputError(f"capture session name {s['name']!r} must be a plain file-name part")
    if s["tool_change"] not in ("auto", "operator"):
        raise InputError(f"capture session: tool_change must be auto or operator, got {s['tool_change']!r}")
    return s


def _shaping(params: Mapping) -> dict:
    """The parameters that shape the captured data (what a resumed run must share)."""
    out = {k: v for k, v in params.items() if k not in OPERATIONAL}
    if "emulator" in out:
        out["emulator"] = {k: v for k, v in dict(out["emulator"] or {}).items() if k != "rate_hz"}
    return out


def _check_devices(devices) -> list[str]:
    devices = [str(d) for d in devices]
    unknown = [d for d in devices if d not in DEVICES]
    if unknown:
        raise InputError(f"capture: unknown device(s) {', '.join(unknown)} (known: {', '.join(DEVICES)})")
    if "robot" not in devices:
        raise InputError("capture: devices must include robot (it moves the indenter)")
    for group in (FORCE_DEVICES, TACTILE_DEVICES):
        if sum(d in devices for d in group) > 1:
            raise InputError(f"capture: choose one of {' / '.join(group)}")
    return list(dict.fromkeys(devices))


def _positive_ints(value, n: int, what: str) -> tuple[int, ...]:
    try:
        out = tuple(int(v) for v in value)
    except (TypeError, ValueError):
        out = ()
    if len(out) != n or min(out) < 1 or any(float(v) != int(v) for v in value):
        raise InputError(f"{what} must be {n} whole numbers >= 1, got {value!r}")
    return out


def _check_params(devices, device_params, robot_p, cam_p, session, rate_hz) -> tuple[int, int]:
    """Every shape and value the capture will use, checked before the staging file is touched
    (a bad value found later would leave a staging file that the corrected run refuses).
    Returns the camera's output size (h, w)."""
    from stages.capture.twin import marker_layout
    check_origin(robot_p["origin"])
    for d in devices:
        sign = device_params[d].get("sign")
        if sign is not None and (np.shape(sign) != (3,) or not np.isfinite(np.asarray(sign, float)).all()):
            raise InputError(f"{d}.sign must be 3 finite numbers (Fx, Fy, Fz), got {sign!r}")
    cam_out = _positive_ints(cam_p["out_size"] or cam_p["size"], 2, "camera.out_size")
    if "camera" in devices:
        _positive_ints(cam_p["size"], 2, "camera.size")
        marker_layout(str(cam_p["pattern"]), int(cam_p["pattern_seed"]))
    if not (isinstance(rate_hz, (int, float)) and np.isfinite(rate_hz) and rate_hz >= 0):
        raise InputError(f"capture.rate_hz must be a number >= 0 (0: as fast as the devices go), got {rate_hz!r}")
    for key, low in (("frame_stride", 1), ("contacts_per_indenter", 0), ("chunk_frames", 1)):
        if int(session[key]) < low or float(session[key]) != int(session[key]):
            raise InputError(f"capture session: {key} must be a whole number >= {low}, got {session[key]!r}")
    if not float(session["depth_scale"]) > 0:
        raise InputError(f"capture session: depth_scale must be > 0, got {session['depth_scale']!r}")
    return cam_out


def plan(trajectory: Mapping, session: Mapping) -> tuple[dict, list[np.ndarray], np.ndarray]:
    """The trajectory's arrays, the selected frames split per contact, and the indenter names."""
    from stages.sim.deform import select_frames
    keys = ("position", "depth", "shift", "phase", "contact_id", "indenter_id", "paired")
    missing = [k for k in keys + ("indenters",) if k not in trajectory]
    if missing:
        raise InputError(f"capture: the trajectory lacks {', '.join(missing)}")
    t = {k: np.asarray(trajectory[k]) for k in keys}
    names = np.asarray(trajectory["indenters"]).astype(str)
    frames = select_frames(trajectory, int(session["contacts_per_indenter"]), int(session["frame_stride"]))
    if session["indenters"]:
        wanted = [str(n) for n in session["indenters"]]
        bad = [n for n in wanted if n not in names]
        if bad:
            raise InputError(f"capture session: unknown indenter(s) {', '.join(bad)}")
        frames = frames[np.isin(names[t["indenter_id"][frames]], wanted)]
    if frames.size == 0:
        raise InputError("capture: the trajectory selection has no frames")
    cuts = np.flatnonzero(np.diff(t["contact_id"][frames])) + 1
    return t, np.split(frames, cuts), names


def _layout(devices, cam_size) -> dict:
    lay = {"frame": ((), np.int64), "position": ((3,), np.float64), "target": ((3,), np.float64),
           "depth": ((), np.float64), "normalised_depth": ((), np.float32), "shift": ((2,), np.float64),
           "phase": ((), np.int8), "contact_id": ((), np.int32), "indenter_id": ((), np.int16),
           "paired": ((), bool), "force": ((3,), np.float32),
           "torque": ((3,), np.float32)}
    lay.update({f"timestamps/{d}": ((), np.float64) for d in devices})
    if "camera" in devices:
        lay["raw"] = ((cam_size[0], cam_size[1], 3), np.uint8)
        lay["camera_valid"] = ((), bool)
    if any(d in devices for d in TACTILE_DEVICES):
        lay["signals"] = ((16, 3), np.int32)
    return lay


def _digest(t: Mapping, frames: np.ndarray, names) -> str:
    h = hashlib.sha256()
    for k in ("position", "depth", "shift", "phase", "contact_id", "indenter_id", "paired"):
        h.update(np.ascontiguousarray(t[k][frames]).tobytes())
    h.update(frames.tobytes())
    h.update("\0".join(names).encode())
    return h.hexdigest()[:16]


def _mesh_provider(indenters):
    cache = {}

    def mesh_of(name: str):
        if name not in cache:
            if indenters is not None:
                from stages.sim.indenters import mesh_from_artifact
                cache[name] = mesh_from_artifact(indenters, name)
            else:
                from stages.sim.indenters import make_indenter
                cache[name] = make_indenter(name)
        return cache[name]
    return mesh_of


class _Run:
    """One capture run over the contacts the staging file still lacks."""

    def __init__(self, clients, devices, staging: Staging, robot_p: Mapping, session: Mapping,
                 cam_out, rate_hz: float, max_depth: float, world=None):
        self.c, self.devices, self.st, self.world = clients, devices, staging, world
        self.robot = clients["robot"]
        self.ft = next((clients[d] for d in FORCE_DEVICES if d in clients), None)
        self.tactile = next((clients[d] for d in TACTILE_DEVICES if d in clients), None)
        self.cam = clients.get("camera")
        self.origin, self.yaw = check_origin(robot_p["origin"]), float(robot_p["yaw_deg"])
        self.approach, self.clearance = float(robot_p["approach_mm"]), float(robot_p["clearance_mm"])
        self.scale, self.cam_out = float(session["depth_scale"]), cam_out
        self.period = 1.0 / float(rate_hz) if rate_hz and rate_hz > 0 else 0.0
        self.max_depth = max_depth
        self.operator = session["tool_change"] == "operator" or world is None
        self.base = staging.counts()
        self.sign = np.asarray(self.ft.p["sign"], float) if self.ft is not None else np.ones(3)
        self.tare = np.zeros(6)

    def counts(self) -> dict:
        out = dict(self.base)
        for d, client in self.c.items():
            for k, v in client.counts().items():
                out[f"{d}_{k}"] = out.get(f"{d}_{k}", 0) + int(v)
        return out

    def goto(self, xyz_mm) -> None:
        self.robot.move(to_pose(np.asarray(xyz_mm, float), self.origin, self.yaw))

    def _camera_frame(self, image: np.ndarray) -> np.ndarray:
        if tuple(image.shape[:2]) == tuple(self.cam_out):
            return image
        import cv2
        return cv2.resize(image, (int(self.cam_out[1]), int(self.cam_out[0])), interpolation=cv2.INTER_AREA)

    def tare_ft(self) -> None:
        if self.ft is None:
            return
        since, reads = time.time(), []
        for _ in range(max(int(self.ft.p["tare_samples"]), 1)):
            reads.append(self.ft.read(since))
            since = reads[-1].t + 1e-6                  # a stream gives a newer record each time
        self.tare = np.mean([np.concatenate([r["force"], r["torque"]]) for r in reads], axis=0)

    def references(self) -> None:
        since = time.time()
        if self.cam is not None and "reference_raw" not in self.st.f:
            self.st.put("reference_raw", self._camera_frame(self.cam.read(since)["image"]))
        if self.tactile is not None and "reference_signals" not in self.st.f:
            self.st.put("reference_signals", self.tactile.read(since)["signals"].astype(np.int32))

    def sample(self, t: Mapping, r: int, target: np.ndarray) -> dict:
        self.goto(target)
        since = time.time()
        p0 = self.robot.pose()
        got = {d: self.c[d].read(since) for d in self.devices if d != "robot"}
        p1 = self.robot.pose()
        ref = next((got[d] for d in FORCE_DEVICES + ("camera",) + TACTILE_DEVICES if d in got), p0)
        span = p1.t - p0.t
        a = min(max((ref.t - p0.t) / span, 0.0), 1.0) if span > 0 else 0.0
        position = to_sensor(p0["pose"] + a * (p1["pose"] - p0["pose"]), self.origin, self.yaw)
        depth = -position[2]
        row = {"frame": r, "position": position, "target": target, "depth": depth,
               "normalised_depth": depth / self.max_depth,
               "shift": t["shift"][r] + (position[:2] - target[:2]), "timestamps/robot": p0.t,
               **{k: t[k][r] for k in _LABELS}}
        for d, s in got.items():
            row[f"timestamps/{d}"] = s.t
        if self.ft is not None:
            w = np.concatenate([got[self.ft.kind]["force"], got[self.ft.kind]["torque"]]) - self.tare
            row["force"], row["torque"] = self.sign * w[:3], self.sign * w[3:]
        else:
            row["force"] = row["torque"] = np.full(3, np.nan)
        if self.cam is not None:
            row["raw"], row["camera_valid"] = self._camera_frame(got["camera"]["image"]), got["camera"]["valid"]
        if self.tactile is not None:
            row["signals"] = got[self.tactile.kind]["signals"]
        return row

    def contact(self, t: Mapping, rows: np.ndarray, names, first: bool) -> None:
        r0 = rows[0]
        point = t["position"][r0, :2] - t["shift"][r0]
        name = str(names[t["indenter_id"][r0]])
        mounted = self.st.get("mounted")
        changed = mounted != name
        if self.operator and changed and mounted is not None:
            self.st.set("mounted", name)          # the next run assumes the operator did it
            raise DeviceError(f"{self.robot.name}: mount indenter {name!r} (replacing {mounted!r}), then run "
                              "the capture again to continue")
        self.st.set("mounted", name)
        if self.world is not None:
            self.world.mount(name)
        if first or changed:
            self.goto([point[0], point[1], self.clearance])
        self.goto([point[0], point[1], self.approach])
        self.tare_ft()
        if first:
            self.references()
        t0, due = time.monotonic(), time.monotonic()
        for r in rows:
            if self.period:
                time.sleep(max(due - time.monotonic(), 0.0))
                due = max(due + self.period, time.monotonic() - self.period)
            target = np.array([t["position"][r, 0], t["position"][r, 1], -float(t["depth"][r]) * self.scale])
            try:
                self.st.append(self.sample(t, r, target))
            except DeviceError as exc:
                raise DeviceError(f"{exc} (trajectory frame {r}, contact {int(t['contact_id'][r])})") from None
        self.goto([point[0], point[1], self.approach])
        if self.cam is not None:
            # a contact ending in repeated frames is the start of a disconnect unless the camera
            # delivers again: committed, it would be kept by the resume, unlike the frames an
            # uninterrupted capture takes there
            try:
                self.cam.confirm()
            except DeviceError as exc:
                raise DeviceError(f"{exc} (end of contact {int(t['contact_id'][rows[-1]])}, "
                                  "which is captured again)") from None
        self.st.commit(self.counts(), time.monotonic() - t0)


def _chunks(st: Staging, chunk: int):
    """Staged rows as nested mappings of at most `chunk` frames."""
    for a in range(0, st.rows, chunk):
        out: dict = {}
        for name in st.layout:
            head, _, tail = name.partition("/")
            value = st.read(name, a, a + chunk)
            if tail:
                out.setdefault(head, {})[tail] = value
            else:
                out[name] = value
        yield out


def capture(*, trajectory: Mapping, devices, robot: Mapping, netft: Mapping, serial_ft: Mapping,
            camera: Mapping, xela: Mapping, slcan: Mapping, sensor: str, rate_hz: float,
            staging_dir: str, emulate: bool, session: Mapping | None = None,
            indenters: Mapping | None = None, spec: Mapping | None = None,
            materials: Mapping | None = None, after_publish=None, forced: bool = False):
    """Source node `capture`: see the module docstring.  A generator: it captures (or resumes)
    into the staging file, then yields the staged rows in chunks and returns the rest.
    after_publish: the engine's; it deletes the staging file once the artifact holding its rows
    is durably published (called directly, without it, the node deletes the file on return).
    forced: the engine's, true in a `--force` run: a staging file whose session finished is
    then an earlier session's (published, or about to be when a run stopped), never this run's.

    session: name (staging file capture-<name>.h5; default the sensor), indenters (names to
    capture; default all the trajectory has), contacts_per_indenter / frame_stride (as the
    deform twins, so captured frames are location-paired with them), depth_scale,
    max_depth_mm, chunk_frames (rows per yielded chunk), tool_change (auto / operator).
    emulate: start the loopback emulators driven by the FEM-lite twin of `spec` (a sensors
    catalogue entry) and `materials`, meshes from `indenters` (built from the names if None).
    Each device mapping takes its client's parameters (devices.py), plus `emulator` settings
    and `faults` (emulators.py) used only when emulating.
    """
    devices = _check_devices(devices)
    s = _session(session, sensor)
    params = {"robot": robot, "netft": netft, "serial_ft": serial_ft, "camera": camera, "xela": xela,
              "slcan": slcan}
    device_params = {d: dict(params[d] or {}) for d in devices}
    from stages.capture.emulators import split_params
    for d in devices:                                   # validate names before touching anything
        client_class(d)(split_params(d, device_params[d])[0])
    robot_p = {**Robot.defaults, **{k: v for k, v in device_params["robot"].items() if k in Robot.defaults}}
    cam_p = {**Camera.defaults, **{k: v for k, v in device_params.get("camera", {}).items() if k in Camera.defaults}}
    cam_out = _check_params(devices, device_params, robot_p, cam_p, s, rate_hz)
    if emulate and (spec is None or materials is None):
        raise InputError("capture: emulate: true needs the twin's sensor catalogue entry (spec) and materials")
    t, contacts, names = plan(trajectory, s)
    frames = np.concatenate(contacts)
    max_depth = float(s["max_depth_mm"] or np.max(t["depth"][frames]) * float(s["depth_scale"]) or 1.0)
    check = {"trajectory": _digest(t, frames, names), "devices": devices, "sensor": sensor,
             "emulate": bool(emulate),
             "session": {k: v for k, v in s.items() if k not in ("chunk_frames", "tool_change")},
             **{d: _shaping(p) for d, p in device_params.items()}}
    if emulate:
        check["twin"] = {"spec": dict(spec), "material": dict(materials[spec["material"]])}
    os.makedirs(staging_dir, exist_ok=True)
    path = os.path.join(staging_dir, f"capture-{s['name']}.h5")
    layout = _layout(devices, cam_out)

    st = Staging(path, check, layout)
    if forced and st.complete:
        done = st.contacts_done
        st.close()
        raise InputError(f"staging file {path} holds an earlier session's finished capture ({done} "
                         "contacts, published or about to be when a run stopped): remove it for a fresh "
                         "capture, or run without --force to publish it if the store lacks it")
    try:
        if st.contacts_done < len(contacts):
            try:
                _capture(st, contacts, t, names, devices, device_params, robot_p, s, cam_out, rate_hz,
                         max_depth, emulate, spec, materials, indenters)
            except BaseException:
                st.rollback()
                raise
        st.set("complete", True)
        for chunk in _chunks(st, int(s["chunk_frames"])):
            yield chunk
        final = {"indenters": names}
        for key in ("reference_raw", "reference_signals"):
            if key in st.f:
                final[key] = st.f[key][()]
        counts = st.counts()
        seconds = float(st.get("seconds"))
        attrs = {"sensor": sensor, "devices": devices, "emulate": bool(emulate), "frames": st.rows,
                 "contacts": len(contacts), "sessions": int(st.get("sessions")), "seconds": seconds,
                 "rate_hz": float(rate_hz), "rate_hz_achieved": st.rows / seconds if seconds > 0 else 0.0,
                 "origin": [float(v) for v in robot_p["origin"]], "yaw_deg": float(robot_p["yaw_deg"]),
                 "depth_scale": float(s["depth_scale"]), "max_depth_mm": max_depth,
                 "units": "mm, N, N m, s (host clock); force in the pad frame, Fz < 0 pressing",
                 **counts}
        final["attrs"] = attrs
    finally:
        st.close()
    remove = functools.partial(_remove, path)
    if after_publish is None:
        remove()
    else:
        after_publish(remove)
    return final


def _remove(path: str) -> None:
    with contextlib.suppress(FileNotFoundError):
        os.remove(path)


def _capture(st, contacts, t, names, devices, device_params, robot_p, s, cam_out, rate_hz, max_depth,
             emulate, spec, materials, indenters) -> None:
    with contextlib.ExitStack() as stack:
        world = None
        if emulate:
            from stages.capture.emulators import Emulators
            from stages.sim.sensors import material_of
            emu = stack.enter_context(Emulators(devices, device_params, spec=spec,
                                                material=material_of(spec, materials),
                                                mesh_of=_mesh_provider(indenters)))
            clients, world = emu.clients, emu.world
        else:
            clients = {d: client_class(d)({k: v for k, v in device_params[d].items()
                                           if k not in ("faults", "emulator")}) for d in devices}
        for d in devices:
            stack.enter_context(clients[d])
        run = _Run(clients, devices, st, robot_p, s, cam_out, rate_hz, max_depth, world)
        from tqdm import tqdm
        done = st.contacts_done
        for k in tqdm(range(done, len(contacts)), desc="capture", unit="contact", disable=None, leave=False,
                      initial=done, total=len(contacts)):
            run.contact(t, contacts[k], names, first=(k == done))


CALIBRATION_SESSION = {"name": None, "chunk_frames": 64, "tool_change": "auto"}


def capture_calibration(*, trajectory: Mapping, sensor: str, spec: Mapping, devices, session: Mapping | None,
                        robot: Mapping, netft: Mapping, serial_ft: Mapping, camera: Mapping,
                        xela: Mapping, slcan: Mapping, rate_hz: float, staging_dir: str,
                        emulate: bool, materials: Mapping, indenters: Mapping | None = None,
                        after_publish=None, forced: bool = False):
    """Source node `capture_calibration[sensor]`: the material-compensation calibration pressed
    into a real sensor (or its emulated twin) and recorded with an F/T sensor, so that the
    compensation reads this sensor's own force-depth curves (stages.force.compensation) where
    `calibrate[sensor]` would compute its twin's.

    `trajectory` is the calibration trajectory (the calibration indenter to the trajectory's
    deepest point and back, its shear leg there), pressed every frame to the sensor's
    max_depth_mm (`spec`, its sensors catalogue entry) and sheared by the sensor's stroke (the
    trajectory's shift times its shear_scale), as calibrate presses its twin.  `devices`: the robot and an F/T
    sensor (a camera or skin, if listed, is recorded too but not needed).  `session`
    (CALIBRATION_SESSION): name (staging file capture-<name>.h5; default <sensor>-calibration),
    chunk_frames, tool_change.  The device parameters, rate_hz, emulate, staging and
    after_publish and forced are capture's.

    Returns capture's arrays (force, depth, normalised_depth = depth / max_depth_mm, phase,
    shift, ...) with attrs: calibration true, indenter (the trajectory's), max_depth_mm and
    pad_mm, as calibrate records them for the twin (`materials` drives only the emulators).
    """
    unknown = set(session or {}) - set(CALIBRATION_SESSION)
    if unknown:
        raise InputError(f"capture_calibration[{sensor}]: unknown session setting(s) {', '.join(sorted(unknown))} "
                         f"(known: {', '.join(CALIBRATION_SESSION)})")
    settings = {**CALIBRATION_SESSION, **dict(session or {})}
    devices = _check_devices(devices)
    if not any(d in devices for d in FORCE_DEVICES):
        raise InputError(f"capture_calibration[{sensor}]: devices {devices} read no force: add one of "
                         f"{' / '.join(FORCE_DEVICES)}")
    missing = [k for k in ("max_depth_mm", "pad_mm") if k not in spec]
    if missing:
        raise InputError(f"capture_calibration[{sensor}]: its sensors entry lacks {', '.join(missing)}")
    if spec.get("body", sensor) != sensor:   # the transfers look a calibration up by the gel's body
        raise InputError(f"capture_calibration[{sensor}]: a calibration belongs to a body; list "
                         f"{spec['body']} (the body {sensor} rides on) in capture.calibration.sensors")
    missing = [k for k in ("depth", "indenters", "indenter_id", "contact_id") if k not in trajectory]
    if missing:
        raise InputError(f"capture_calibration[{sensor}]: the trajectory lacks {', '.join(missing)}")
    depth = np.asarray(trajectory["depth"], float)
    deepest = float(np.max(depth)) if depth.size else 0.0
    if not deepest > 0:
        raise InputError(f"capture_calibration[{sensor}]: the calibration trajectory never presses (deepest {deepest} mm)")
    names = np.asarray(trajectory["indenters"]).astype(str)
    indenter = str(names[np.asarray(trajectory["indenter_id"])[0]])
    max_depth = float(spec["max_depth_mm"])
    t = {k: np.asarray(trajectory[k]) for k in ("position", "depth", "shift", "phase", "contact_id",
                                                "indenter_id", "paired", "indenters") if k in trajectory}
    t["movement_id"] = t["contact_id"]              # frame_stride 1 keeps every frame of a contact
    # a calibration trajectory's position is its touchdown point; capture's target is where the
    # shift moved the tip (a collection's position), at the sensor's stroke as calibrate presses it
    from stages.sim.deform import _scale_shear
    t["position"] = np.array(t["position"], float)
    t["position"][:, :2] += t["shift"]
    _scale_shear(t, float(spec.get("shear_scale", 1.0)))
    run = {"name": settings["name"] or f"{sensor}-calibration", "contacts_per_indenter": 0,
           "frame_stride": 1, "depth_scale": max_depth / deepest, "max_depth_mm": max_depth,
           "chunk_frames": int(settings["chunk_frames"]), "tool_change": settings["tool_change"]}
    final = yield from capture(trajectory=t, devices=devices, robot=robot, netft=netft, serial_ft=serial_ft,
                               camera=camera, xela=xela, slcan=slcan, sensor=sensor, rate_hz=rate_hz,
                               staging_dir=staging_dir, emulate=emulate, session=run,
                               indenters=indenters, spec=spec, materials=materials,
                               after_publish=after_publish, forced=forced)
    final["attrs"].update({"calibration": True, "indenter": indenter, "max_depth_mm": max_depth,
                           "pad_mm": [float(v) for v in spec["pad_mm"]]})
    return final
