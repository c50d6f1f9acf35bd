"""Indenters from STL files: a lab's 3D-printed shapes (or the authors' 18, under
sim/assets/indenters/input/stl in their repository) in place of the procedural ones.

Each mesh goes through pymeshlab: duplicate vertices removed and vertices closer than
MERGE_MM merged (an STL repeats every vertex once per triangle), duplicate and zero-area
faces removed, holes of up to MAX_HOLE_EDGES edges closed, faces oriented coherently.  It
must then be watertight with consistent winding; it is turned outwards (positive volume),
tip down, and placed as stages.sim.indenters places the procedural shapes: mm, the tip's
lowest point at z = 0, the x-y bounding box centred on the origin (for the authors' files, the
centre of their mount, the procedural shapes' frame).

Which end is the tip: `tip` "-z" (the mesh already points down, as ours), "+z" (it points up,
as the authors' files do: a 16 x 16 x 10 mm mounting block at z 0..10 and the shape above it;
turned by 180 degrees about x, so x keeps its direction), or "auto": the end whose slab of
TIP_SLAB of the height has the smaller x-y extent.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from stages.common import InputError

MERGE_MM = 1e-3                 # far below a print's resolution: merges only coincident vertices
MAX_HOLE_EDGES = 30             # pymeshlab's default: a hole this small is a modelling slip
TIP_SLAB = 0.1                  # share of the height compared at each end (tip "auto")
TIPS = ("auto", "+z", "-z")


def _repair(path: Path):
    """(vertices, faces) of the STL after pymeshlab's repairs, or an InputError naming it."""
    import pymeshlab
    ms = pymeshlab.MeshSet()
    try:
        ms.load_new_mesh(str(path))
    except pymeshlab.PyMeshLabException as exc:
        raise InputError(f"indenter mesh {path} is not a readable STL file ({str(exc).strip()})") from None
    if ms.current_mesh().face_number() == 0:
        raise InputError(f"indenter mesh {path} holds no triangles")
    try:
        ms.meshing_remove_duplicate_vertices()
        ms.meshing_merge_close_vertices(threshold=pymeshlab.PureValue(MERGE_MM))
        ms.meshing_remove_duplicate_faces()
        ms.meshing_remove_null_faces()
        ms.meshing_remove_unreferenced_vertices()
        ms.meshing_close_holes(maxholesize=MAX_HOLE_EDGES)
        ms.meshing_re_orient_faces_coherently()
    except pymeshlab.PyMeshLabException as exc:
        raise InputError(f"indenter mesh {path} cannot be repaired ({str(exc).strip()})") from None
    m = ms.current_mesh()
    return np.asarray(m.vertex_matrix(), float), np.asarray(m.face_matrix(), np.int64)


def _tip_up(vertices: np.ndarray) -> bool:
    """Whether the narrower end (the tip) is at +z."""
    z = vertices[:, 2]
    lo, hi = z.min(), z.max()
    slab = TIP_SLAB * (hi - lo)

    def extent(sel):
        xy = vertices[sel, :2]
        return float(np.prod(np.ptp(xy, axis=0))) if len(xy) else 0.0
    return extent(z >= hi - slab) < extent(z <= lo + slab)


def load_stl(path, tip: str = "auto"):
    """A watertight trimesh of the STL at `path` (mm), tip at z = 0, x-y bbox centred."""
    import trimesh
    if tip not in TIPS:
        raise InputError(f"indenters.stl_tip must be one of {', '.join(TIPS)}, got {tip!r}")
    path = Path(path)
    vertices, faces = _repair(path)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    if not mesh.is_watertight or not mesh.is_winding_consistent:
        counts = np.unique(mesh.edges_sorted, axis=0, return_counts=True)[1]
        raise InputError(f"indenter mesh {path} cannot be repaired: not watertight after closing holes of up to "
                         f"{MAX_HOLE_EDGES} edges ({int(np.sum(counts == 1))} open edge(s), "
                         f"{int(np.sum(counts > 2))} shared by more than two faces)")
    if mesh.volume < 0:
        mesh.invert()
    if tip == "+z" or (tip == "auto" and _tip_up(mesh.vertices)):
        mesh.apply_transform(np.diag([1.0, -1.0, -1.0, 1.0]))     # 180 degrees about x
    lo, hi = mesh.bounds
    mesh.apply_translation([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    return mesh


def stl_meshes(stl_dir, names, tip: str = "auto") -> dict:
    """{name: mesh} for each of `names` with a <name>.stl (or .STL) in `stl_dir`."""
    folder = Path(stl_dir)
    if not folder.is_dir():
        raise InputError(f"indenters.stl_dir: no folder {folder}")
    files = {p.stem: p for p in sorted(folder.iterdir()) if p.suffix.lower() == ".stl"}
    found = {n: load_stl(files[n], tip) for n in names if n in files}
    if not found:
        raise InputError(f"indenters.stl_dir: {folder} holds no <name>.stl for any of indenters.names "
                         f"({', '.join(names)})")
    return found


FOOTPRINT_DEPTHS = (0.5, 1.0, 1.5)   # mm: the depths at which contact footprints are compared


def footprint_cells(mesh_or_name, shape, spacing: float, depths=FOOTPRINT_DEPTHS) -> list:
    """Cells of a pad grid whose indenter surface lies within each depth of the tip."""
    from stages.sim.indenters import height_map
    hm = height_map(mesh_or_name, shape=shape, spacing=spacing)
    return [int(np.count_nonzero(hm <= d)) for d in depths]


def compare_footprints(stl_dir, names=None, shape=(65, 65), spacing: float = 0.390625,
                       tip: str = "auto", depths=FOOTPRINT_DEPTHS) -> list:
    """For each indenter with a <name>.stl in `stl_dir`: its footprint cells and the procedural
    shape's at each depth, and their largest relative difference (the default grid is the
    GelSight pads')."""
    from stages.sim.indenters import INDENTERS
    found = stl_meshes(stl_dir, list(INDENTERS if names is None else names), tip)
    rows = []
    for name, mesh in found.items():
        stl, ours = footprint_cells(mesh, shape, spacing, depths), footprint_cells(name, shape, spacing, depths)
        rel = max(abs(a - b) / max(a, 1) for a, b in zip(stl, ours))
        rows.append({"name": name, "stl": stl, "procedural": ours, "max_rel_diff": rel})
    return rows


if __name__ == "__main__":   # python -m stages.sim.stl DIR: a folder's STLs against the procedural shapes
    import sys
    if len(sys.argv) != 2:
        sys.exit("usage: python -m stages.sim.stl STL_DIR")
    try:
        table = compare_footprints(sys.argv[1])
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    print("cells of the 65 x 65 GelSight grid (0.39 mm) within "
          + " / ".join(f"{d} mm" for d in FOOTPRINT_DEPTHS) + " of the tip: STL | procedural")
    for r in table:
        print(f"{r['name']:12s} {' '.join(f'{c:5d}' for c in r['stl'])} | "
              f"{' '.join(f'{c:5d}' for c in r['procedural'])}   {100 * r['max_rel_diff']:5.1f}%")
