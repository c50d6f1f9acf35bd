"""Sensor frame (mm) <-> UR robot TCP poses (m, rad).

The sensor lies flat with its pad facing up; its frame has z out of the pad (pressing moves the
indenter towards -z, as in the trajectories) and x rotated by `yaw_deg` from the robot base's x
about the base's z.  `origin` is the TCP pose [x, y, z, rx, ry, rz] (base frame, m and UR
axis-angle rad) at which the mounted indenter's tip touches the pad centre, so

    pose(p) = origin[:3] + Rz(yaw) p / 1000,  orientation = origin[3:] (the tool never rotates)

and a tip position p = (x, y, -depth) mm maps to a TCP pose by that formula.  Calibrate
`origin` by jogging the tip onto the pad centre until the F/T sensor just reads a touch.
"""
from __future__ import annotations

import numpy as np

from stages.common import InputError


def _yaw(yaw_deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def check_origin(origin) -> np.ndarray:
    o = np.asarray(origin, float)
    if o.shape != (6,) or not np.isfinite(o).all():
        raise InputError(f"robot origin must be 6 finite numbers [x, y, z, rx, ry, rz] (m, rad), got {origin!r}")
    return o


def to_pose(position_mm, origin, yaw_deg: float = 0.0) -> np.ndarray:
    """(..., 3) tip positions in the sensor frame, mm -> (..., 6) TCP poses."""
    o = check_origin(origin)
    p = np.asarray(position_mm, float)
    xyz = o[:3] + (p @ _yaw(yaw_deg).T) / 1000.0
    return np.concatenate([xyz, np.broadcast_to(o[3:], xyz.shape)], axis=-1)


def to_sensor(pose, origin, yaw_deg: float = 0.0) -> np.ndarray:
    """(..., 6) TCP poses -> (..., 3) tip positions in the sensor frame, mm."""
    o = check_origin(origin)
    d = (np.asarray(pose, float)[..., :3] - o[:3]) * 1000.0
    return d @ _yaw(yaw_deg)
