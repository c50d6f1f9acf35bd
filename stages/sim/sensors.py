"""Sensor and elastomer catalogue entries (params.yaml `sensors`, `materials`) as solver inputs.

A sensor entry gives its pad (`pad_mm` x, y; `thickness_mm`; `curvature_radius_mm`, 0 for a
flat pad), its elastomer (`material`, a key of `materials`), the solver grid (`grid` rows y,
cols x; `spacing_mm`), `max_depth_mm` (the depth that normalised depth 1 refers to) and the
trajectory it follows (`trajectory`, `depth_scale`).  A material gives `E` (Pa), `nu`, `mu`
(Coulomb friction) and `hysteresis` (see contact.solve_sequence).

A curved pad (TacTip's dome) is modelled as a flat layer whose initial gap to the indenter is
the dome's sag, added to the indenter's height map; depth then counts from first touch.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from stages.sim.indenters import grid_coords, height_map

_SOLVER_KEYS = ("E", "nu", "mu", "hysteresis")


def pad_grid(spec: Mapping) -> tuple[tuple[int, int], float]:
    """The solver grid (rows, cols) and its spacing in mm."""
    h, w = (int(v) for v in spec["grid"])
    return (h, w), float(spec["spacing_mm"])


def material_of(spec: Mapping, materials: Mapping) -> dict:
    """The sensor's elastomer: E (Pa), nu, mu, hysteresis."""
    name = spec["material"]
    if name not in materials:
        raise KeyError(f"sensor material {name!r} is not in the catalogue ({', '.join(materials)})")
    return {k: float(materials[name][k]) for k in _SOLVER_KEYS}


def surface_gap(spec: Mapping) -> np.ndarray:
    """(h, w) mm: the undeformed pad surface below its highest point (0 for a flat pad).

    On a dome of curvature radius R and base diameter pad_mm[0] the sag is
    R - sqrt(R^2 - r^2); cells beyond the base are +inf (no pad there, nothing to touch).
    """
    shape, spacing = pad_grid(spec)
    radius = float(spec["curvature_radius_mm"])
    if radius <= 0:
        return np.zeros(shape)
    x, y = grid_coords(shape, spacing)
    r2 = x[None, :] ** 2 + y[:, None] ** 2
    base = 0.5 * float(spec["pad_mm"][0])
    sag = radius - np.sqrt(np.maximum(radius * radius - np.minimum(r2, base * base), 0.0))
    return np.where(r2 <= base * base, sag, np.inf)


def contact_height(mesh, spec: Mapping, point, gap: np.ndarray | None = None) -> np.ndarray:
    """Indenter height map on the sensor's grid, tip over `point` (x, y) mm, plus the pad's gap,
    lowered by the gap at first touch, so that depth counts from touchdown on a curved pad too.

    The first touch is min(height + gap) less min(height): a tip between grid cells sits
    min(height) above its nearest cell, an offset the grid must keep (a flat pad then gets
    exactly the indenter's own height map; subtracting min(height + gap) alone would press
    every sharp tip one sampling offset too deep).  All +inf when the indenter misses the pad.
    """
    shape, spacing = pad_grid(spec)
    height = height_map(mesh, shape=shape, spacing=spacing, position=point)
    touch = height + (surface_gap(spec) if gap is None else gap)
    finite = np.isfinite(touch)
    if finite.any():
        touch -= touch[finite].min() - height[np.isfinite(height)].min()
    return touch


def solver_kwargs(spec: Mapping, material: Mapping) -> dict:
    """Keyword arguments of contact.solve_sequence for this sensor and elastomer."""
    _, spacing = pad_grid(spec)
    return {"spacing": spacing, "E": material["E"], "nu": material["nu"],
            "thickness": float(spec["thickness_mm"]), "mu": material["mu"],
            "hysteresis": material["hysteresis"]}


def sensor_attrs(name: str, spec: Mapping, material: Mapping) -> dict:
    """What an artifact records about the sensor that made it (units in the key names)."""
    return {"sensor": name, "material": spec["material"], "E_pa": material["E"],
            "nu": material["nu"], "mu": material["mu"], "hysteresis": material["hysteresis"],
            "pad_mm": [float(v) for v in spec["pad_mm"]], "thickness_mm": float(spec["thickness_mm"]),
            "curvature_radius_mm": float(spec["curvature_radius_mm"]),
            "max_depth_mm": float(spec["max_depth_mm"]), "spacing_mm": float(spec["spacing_mm"]),
            "units": "mm, N, Pa; force (Fx, Fy, Fz) on the pad, Fz < 0 pressing"}
