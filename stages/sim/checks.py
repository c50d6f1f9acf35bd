"""Node `contact_check`: the contact solver against Hertz on the grid the sim pad uses.

Hertz's sphere is the paraboloid r^2 / 2R on a half-space, so the metric measures the
solver's discretisation error at the data's own resolution, not the sphere-vs-paraboloid
or finite-layer differences (those are physics the twins keep).
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from stages.figures import figure_png
from stages.sim.contact import solve_contact_batch
from stages.sim.indenters import grid_coords
from stages.sim.sensors import material_of, pad_grid
from stages.sim.trajectory import check_depths


def hertz_force(depth, *, radius, E, nu):
    """N: F = 4/3 E* sqrt(R) d^1.5 with E* = E / (1 - nu^2); mm and Pa in, mm^2 -> m^2."""
    e_star = E / (1.0 - nu * nu)
    return 4.0 / 3.0 * e_star * np.sqrt(radius) * np.asarray(depth, float) ** 1.5 * 1e-6


def _hertz_png(depth, solver, hertz, title) -> np.ndarray:
    from matplotlib.figure import Figure
    fig = Figure(figsize=(4.5, 3.5))
    ax = fig.add_subplot()
    fine = np.linspace(0.0, depth.max(), 100)
    scale = hertz[-1] / depth[-1] ** 1.5
    ax.plot(fine, scale * fine ** 1.5, "-", lw=1, label="Hertz")
    ax.plot(depth, solver, "o", ms=5, label="solver")
    ax.set(xlabel="depth (mm)", ylabel="normal force (N)", title=title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return figure_png(fig)


def contact_check(*, spec: Mapping, materials: Mapping, radius_mm: float, depths_mm) -> dict:
    """Relative error of the solver's normal force against Hertz at each depth; the metric
    `contact/hertz_rel_error` is the largest.  spec: the sim sensor (grid, spacing, material)."""
    material = material_of(spec, materials)
    shape, spacing = pad_grid(spec)
    x, y = grid_coords(shape, spacing)
    height = (x[None, :] ** 2 + y[:, None] ** 2) / (2.0 * radius_mm)
    depth = check_depths(depths_mm, "contact_check.depths_mm")
    res = solve_contact_batch(np.broadcast_to(height, (depth.size,) + shape), depth,
                              spacing=spacing, E=material["E"], nu=material["nu"])
    solver = -res.force[:, 2]
    hertz = hertz_force(depth, radius=radius_mm, E=material["E"], nu=material["nu"])
    rel = np.abs(solver - hertz) / hertz
    return {"metrics": {"contact/hertz_rel_error": float(rel.max())},
            "depth": depth, "force_solver": solver, "force_hertz": hertz, "rel_error": rel,
            "figures": {"hertz": _hertz_png(depth, solver, hertz,
                                            f"sphere R {radius_mm:g} mm, grid {shape[1]}x{shape[0]} "
                                            f"@ {spacing:g} mm")},
            "attrs": {"radius_mm": float(radius_mm), "spacing_mm": spacing, "grid": list(shape),
                      "E_pa": material["E"], "nu": material["nu"], "units": "mm, N"}}
