"""Grasp objects for the gripper twin: the paper's daily objects as catalogue entries.

An entry (params `control.objects.<name>`, a plain mapping) gives
  width_mm        the object's uncompressed width between the fingers
  stiffness_N_mm  its compression stiffness across that width (a spring in series with the gels)
  shape           contact face: "sphere" (curved both ways), "cylinder" (curved across y, its axis
                  along the pad's x, i.e. horizontal, across gravity) or "flat"
  radius_mm       the face's radius of curvature (ignored for "flat")
  face_mm         [x, y] extent of the face that can touch the pad (the object's silhouette)
  mass_kg, mu     mass and the Coulomb friction coefficient against the gel
  fragility       "fragile" | "medium" | "robust" -> target grasp force 0.6 / 0.8 / 1.2 N (paper)
  crush_N         normal force at which the object is damaged

The paper lists its objects (9 for grasping: potato chip, grape, strawberry, orange, plum, wood
block, glue stick, meat box, tea box; 4 for slip: banana, plum, meat box, glue stick) but none of
their properties; DEFAULT_OBJECTS holds plausible values (sizes from the initial gripper widths
the paper quotes, 25 mm for grapes to 75 mm for oranges; gel friction of silicone on dry
surfaces, 0.6-1.2).  They are twin assumptions, not measurements.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from stages.common import check_option

from stages.sim.indenters import grid_coords

TARGET_N = {"fragile": 0.6, "medium": 0.8, "robust": 1.2}
SHAPES = ("sphere", "cylinder", "flat")
GRAVITY = 9.81


@dataclass(frozen=True)
class GraspObject:
    name: str
    width_mm: float
    stiffness_N_mm: float
    shape: str
    radius_mm: float
    face_mm: tuple
    mass_kg: float
    mu: float
    fragility: str
    crush_N: float

    @property
    def target_N(self) -> float:
        return TARGET_N[self.fragility]

    @property
    def weight_N(self) -> float:
        return self.mass_kg * GRAVITY


_FIELDS = ("width_mm", "stiffness_N_mm", "shape", "radius_mm", "face_mm", "mass_kg", "mu",
           "fragility", "crush_N")


def grasp_object(name: str, entry: Mapping) -> GraspObject:
    """A catalogue entry as a GraspObject; a missing key or a bad value raises naming it."""
    missing = [k for k in _FIELDS if k not in entry]
    if missing:
        raise KeyError(f"object {name!r}: missing {', '.join(missing)}")
    check_option(f"control.objects.{name}.shape", entry["shape"], SHAPES)
    check_option(f"control.objects.{name}.fragility", entry["fragility"], tuple(TARGET_N))
    face = tuple(float(v) for v in entry["face_mm"])
    obj = GraspObject(name, float(entry["width_mm"]), float(entry["stiffness_N_mm"]),
                      str(entry["shape"]), float(entry["radius_mm"]), face,
                      float(entry["mass_kg"]), float(entry["mu"]), str(entry["fragility"]),
                      float(entry["crush_N"]))
    positive = {"width_mm": obj.width_mm, "stiffness_N_mm": obj.stiffness_N_mm,
                "mass_kg": obj.mass_kg, "mu": obj.mu, "crush_N": obj.crush_N,
                "face_mm": min(face) if len(face) == 2 else -1.0}
    if obj.shape != "flat":
        positive["radius_mm"] = obj.radius_mm
    bad = [k for k, v in positive.items() if not v > 0]
    if bad:
        raise ValueError(f"object {name!r}: {', '.join(bad)} must be positive "
                         f"(face_mm two values)")
    return obj


def profile_height(obj: GraspObject, shape, spacing: float, center=(0.0, 0.0)) -> np.ndarray:
    """The object's face as an indenter height map on a pad grid (mm above its lowest point,
    NaN outside the face), its lowest point at `center` (x, y) mm in the pad frame."""
    gx, gy = grid_coords(shape, spacing)
    x = gx[None, :] - float(center[0])
    y = gy[:, None] - float(center[1])
    half_x, half_y = 0.5 * obj.face_mm[0], 0.5 * obj.face_mm[1]
    r = obj.radius_mm
    if obj.shape == "sphere":
        r2 = x * x + y * y
        inside = (r2 <= min(half_x, half_y, r) ** 2)
        height = r - np.sqrt(np.maximum(r * r - r2, 0.0))
    elif obj.shape == "cylinder":
        inside = (np.abs(x) <= half_x) & (np.abs(y) <= min(half_y, r))
        height = np.broadcast_to(r - np.sqrt(np.maximum(r * r - y * y, 0.0)), inside.shape)
    else:
        inside = (np.abs(x) <= half_x) & (np.abs(y) <= half_y)
        height = np.zeros(inside.shape)
    return np.where(inside, height, np.nan)


def _entry(width, k, shape, radius, face, mass, mu, fragility, crush):
    return {"width_mm": width, "stiffness_N_mm": k, "shape": shape, "radius_mm": radius,
            "face_mm": list(face), "mass_kg": mass, "mu": mu, "fragility": fragility,
            "crush_N": crush}


# Soft (strawberry 0.4 N/mm) to stiff (wood 80 N/mm); fragile items crush a few N above target.
# Box faces bulge (tins, cardboard): a large radius, not a flat face, which on a 4 mm gel is
# hundreds of N/mm and moves the markers by microns at 1 N (the wood block keeps that case).
DEFAULT_OBJECTS = {
    "potato_chip": _entry(4.0, 2.0, "cylinder", 30.0, (25.0, 25.0), 0.002, 0.6, "fragile", 2.5),
    "grape": _entry(18.0, 0.8, "sphere", 9.0, (18.0, 18.0), 0.006, 0.8, "fragile", 4.0),
    "strawberry": _entry(28.0, 0.4, "sphere", 14.0, (25.0, 25.0), 0.02, 0.9, "fragile", 2.5),
    "orange": _entry(72.0, 3.0, "sphere", 36.0, (25.0, 25.0), 0.15, 0.7, "medium", 30.0),
    "plum": _entry(44.0, 1.5, "sphere", 22.0, (25.0, 25.0), 0.07, 0.8, "medium", 8.0),
    "wood_block": _entry(30.0, 80.0, "flat", 0.0, (20.0, 20.0), 0.03, 0.5, "robust", 500.0),
    "glue_stick": _entry(20.0, 20.0, "cylinder", 10.0, (25.0, 20.0), 0.03, 0.6, "robust", 60.0),
    "meat_box": _entry(60.0, 15.0, "sphere", 150.0, (25.0, 25.0), 0.15, 1.0, "robust", 80.0),
    "tea_box": _entry(70.0, 3.0, "sphere", 100.0, (25.0, 25.0), 0.1, 0.7, "medium", 10.0),
    "banana": _entry(36.0, 1.5, "cylinder", 18.0, (25.0, 25.0), 0.12, 1.0, "medium", 8.0),
}
GRASP_OBJECTS = ("potato_chip", "grape", "strawberry", "orange", "plum", "wood_block",
                 "glue_stick", "meat_box", "tea_box")
SLIP_OBJECTS = ("banana", "plum", "meat_box", "glue_stick")
