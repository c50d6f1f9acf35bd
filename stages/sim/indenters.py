"""The paper's 18 indenters (plus 3 rigid calibration indenters) as procedural meshes.

Frame convention for every indenter mesh (mm):
  * the tip's lowest point is at z = 0 and the body extends to +z (the pad surface is the
    plane z = 0 and pressing moves the indenter towards -z, see ``trajectory.py``);
  * the lateral reference point ("the tip position") is the origin, the centre of the
    authors' 16 x 16 mm printing mount: a shape that is not symmetric about it (moon, pacman,
    random, triangle, wave) sits where it sits on their mount.

The dimensions are the authors' (their repository's sim/assets/indenters/input/stl, each shape
printed 10 mm tall on a 16 x 16 x 10 mm mount), measured from those files with
stages.sim.stl and this module's height maps; outlines they draw freehand (random, triangle)
are their vertices. The mount itself is left out: it lies 10 mm above the tip, far beyond any
pressing depth. UNSEEN is the authors' unseen group, from their training configs (the test
split of `splits`); the other 12 are SEEN.

Height maps: :func:`height_map` rasterises an indenter's lower surface on the pad grid by a
numpy z-buffer over its downward-facing triangles (no ray-tracing backend needed).
"""
from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # trimesh is imported lazily so that importing the names stays cheap
    import trimesh

INDENTERS: tuple[str, ...] = (
    "cone", "cylinder", "cylinder_sh", "cylinder_si", "dotin", "dots", "hemisphere",
    "hexagon", "line", "moon", "pacman", "prism", "random", "sphere", "sphere_s", "torus",
    "triangle", "wave",
)
UNSEEN: tuple[str, ...] = ("cone", "pacman", "sphere_s", "torus", "triangle", "wave")
SEEN: tuple[str, ...] = tuple(n for n in INDENTERS if n not in UNSEEN)
CALIBRATION_INDENTERS: tuple[str, ...] = ("calib_prism", "calib_cone", "calib_punch")
# indenter_id in every trajectory indexes this tuple; its first 18 entries are INDENTERS.
ALL_INDENTERS: tuple[str, ...] = INDENTERS + CALIBRATION_INDENTERS

_SECTIONS = 64  # multiple of 4, so revolved solids have vertices on the +-x / +-y extremes

TIP_HEIGHT = 10.0  # every shape rises 10 mm from its tip to the authors' mount

# The authors' freehand outlines (mm, in the mount's frame), vertex by vertex from their STLs.
RANDOM_OUTLINE = (
    (0.589, 1.58), (0.767, 1.844), (1.006, 2.057), (1.29, 2.204), (1.601, 2.276), (1.92, 2.27),
    (2.228, 2.185), (2.505, 2.027), (2.735, 1.805), (2.903, 1.533), (2.999, 1.229), (3.017, 0.91),
    (1.801, -0.491), (3.606, -0.858), (2.121, -2.34), (-3.121, -1.199), (-3.372, 0.737),
    (-2.567, 0.918), (-2.538, 0.598), (-2.436, 0.294), (-2.265, 0.022), (-2.036, -0.203),
    (-1.76, -0.367), (-1.454, -0.463), (-1.133, -0.485), (-0.817, -0.431), (-0.522, -0.305),
    (-0.264, -0.114), (-0.058, 0.133), (0.084, 0.42))
TRIANGLE_VERTICES = ((0.5, -2.5), (-3.5, -1.983), (3.5, 2.5))
PACMAN_MOUTH_DEG = (-33.0, 37.0)  # the mouth's edges, counter-clockwise from +x
DOTS_ANGLES_DEG = (36.0, 108.0, 180.0, 252.0, 324.0)  # five domes on a 3 mm circle

_DESCRIPTIONS = {
    "cone": ("truncated cone, tip diameter 1 mm, base diameter 8 mm, 10 mm tall", 8.0),
    "cylinder": ("flat cylindrical punch, diameter 6 mm", 6.0),
    "cylinder_sh": ("cylindrical shell, outer diameter 7 mm, inner 5.4 mm", 7.0),
    "cylinder_si": ("cylinder on its side, diameter 6 mm, 14 mm long along y", 6.0),
    "dotin": ("8 x 8 mm square punch with a hemispherical dimple of radius 2 mm", 8.0),
    "dots": ("5 hemispheres (radius 1 mm, on a 3 mm circle) under a 14 x 14 mm plate", 2.0),
    "hemisphere": ("spherical cap of radius 20 mm cut to a 14 x 14 mm square", 14.0),
    "hexagon": ("hexagonal flat punch, circumradius 3.5 mm (corner on +x)", 7.0),
    "line": ("flat bar 2 x 16 mm (long axis along y)", 2.0),
    "moon": ("crescent: disc r 3.5 minus disc r 2.7 offset 1.7 mm along +x", 7.0),
    "pacman": ("disc r 3 with a 70 deg mouth from -33 to +37 deg", 6.0),
    "prism": ("rectangular flat punch 5 x 7 mm (long side along y)", 5.0),
    "random": ("freehand flat outline (the authors' 30 vertices)", 7.0),
    "sphere": ("sphere, diameter 10 mm, on a 5 mm shank", 10.0),
    "sphere_s": ("small sphere, diameter 6 mm, on a 3 mm shank", 6.0),
    "torus": ("torus (ring radius 3, tube radius 1.5 mm) on a hollow shank", 9.0),
    "triangle": ("scalene triangular flat punch (the authors' 3 vertices)", 7.0),
    "wave": ("two ridges along y (radii 3 and 2 mm, crests at x = -2.2 and +2.45) "
             "between plates 2 and 1 mm up, 14 x 14 mm", 14.0),
    "calib_prism": ("rigid calibration prism: 90 deg knife edge 15 mm long along y", 12.0),
    "calib_cone": ("rigid calibration cone: 90 deg apex, base diameter 12 mm", 12.0),
    "calib_punch": ("rigid calibration flat punch, diameter 4 mm, height 10 mm", 4.0),
}


# ---------------------------------------------------------------- mesh construction helpers
def _finish(mesh: "trimesh.Trimesh") -> "trimesh.Trimesh":
    """Merge, orient outwards and put the tip at z = 0 (x-y stay in the mount's frame)."""
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    if mesh.volume < 0:
        mesh.invert()
    mesh.apply_translation([0.0, 0.0, -mesh.bounds[0][2]])
    if not mesh.is_watertight:
        raise RuntimeError("indenter mesh is not watertight")
    return mesh


def _revolve(profile) -> "trimesh.Trimesh":
    """Solid of revolution about z of an (r, z) profile (open ends on the axis or closed loop)."""
    import trimesh

    return trimesh.creation.revolve(np.asarray(profile, float), sections=_SECTIONS)


def _arc(cx, cz, radius, a0, a1, n=48):
    a = np.linspace(a0, a1, n)
    return np.column_stack([cx + radius * np.cos(a), cz + radius * np.sin(a)])


def _extrude(poly, height=TIP_HEIGHT) -> "trimesh.Trimesh":
    """Extrude a shapely footprint from z = 0 to ``height`` (flat punch)."""
    import trimesh

    return trimesh.creation.extrude_polygon(poly, height)


def _extrude_xz(poly, length) -> "trimesh.Trimesh":
    """Extrude a shapely profile drawn in (x, z) along y, centred on y = 0 (edges, ridges)."""
    mesh = _extrude(poly, length)
    rot = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], float)
    mesh.apply_transform(rot)  # (u, v, w) -> (u, -w, v)
    mesh.apply_translation([0.0, length / 2, 0.0])
    return mesh


def _boolean(kind, meshes) -> "trimesh.Trimesh":
    import trimesh

    return getattr(trimesh.boolean, kind)(meshes, engine="manifold")


def _disc(radius, centre=(0.0, 0.0)):
    from shapely.geometry import Point

    return Point(*centre).buffer(radius, quad_segs=_SECTIONS // 4)


def _regular_polygon(n, circumradius):
    from shapely.geometry import Polygon

    a = 2 * np.pi * np.arange(n) / n
    return Polygon(np.column_stack([circumradius * np.cos(a), circumradius * np.sin(a)]))


def _sphere_on_shank(radius, shank_radius, top):
    a_end = np.pi - np.arcsin(shank_radius / radius)
    a = np.linspace(0.0, a_end, 48)
    arc = np.column_stack([radius * np.sin(a), radius - radius * np.cos(a)])
    return _revolve(np.vstack([arc, [[shank_radius, top], [0.0, top]]]))


def _ball(radius, centre):
    """A closed sphere of revolution (``_SECTIONS`` around, 48 along)."""
    mesh = _revolve(_arc(0.0, 0.0, radius, -np.pi / 2, np.pi / 2))
    mesh.apply_translation(centre)
    return mesh


def _plate(side, bottom, top=TIP_HEIGHT):
    import trimesh

    return trimesh.creation.box(bounds=[[-side / 2, -side / 2, bottom], [side / 2, side / 2, top]])


def _wave_profile():
    """The wave's (x, z) cross-section: a plate 2 mm up, a ridge of radius 3 (crest x = -2.2),
    a rounded trough (radius 0.5, centre (0.367, 0.62)), a ridge of radius 2 (crest x = 2.452),
    a plate 1 mm up; 14 mm wide."""
    from shapely.geometry import Polygon

    left = _arc(-2.2, 3.0, 3.0, np.pi + np.arcsin(1 / 3), 2 * np.pi - np.arccos(2.2 / 3), 40)
    trough = _arc(0.367, 0.62, 0.5, np.pi - np.arccos(0.367 / 0.5),
                  np.arccos((0.784 - 0.367) / 0.5), 12)
    right = _arc(2.452, 2.0, 2.0, np.pi + np.arcsin(np.sqrt(4 - (2.452 - 0.784) ** 2) / 2),
                 2 * np.pi - np.arcsin(1 / 2), 40)
    x = np.vstack([[[-7.0, 2.0]], left, trough[1:-1], right, [[7.0, 1.0], [7.0, TIP_HEIGHT],
                                                            [-7.0, TIP_HEIGHT]]])
    return Polygon(x)


def _build(name: str) -> "trimesh.Trimesh":
    import trimesh
    from shapely.geometry import Polygon, box

    if name == "cone":
        return _revolve([[0, 0], [0.5, 0], [4, TIP_HEIGHT], [0, TIP_HEIGHT]])
    if name == "cylinder":
        return _revolve([[0, 0], [3, 0], [3, TIP_HEIGHT], [0, TIP_HEIGHT]])
    if name == "cylinder_sh":
        return _revolve([[2.7, 0], [3.5, 0], [3.5, TIP_HEIGHT], [2.7, TIP_HEIGHT], [2.7, 0]])
    if name == "cylinder_si":
        mesh = _revolve([[0, -7], [3, -7], [3, 7], [0, 7]])
        mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
        return mesh
    if name == "dotin":
        return _boolean("difference", [_extrude(box(-4, -4, 4, 4)), _ball(2.0, [0, 0, 0])])
    if name == "dots":
        domes = [_ball(1.0, [3 * np.cos(np.radians(a)), 3 * np.sin(np.radians(a)), 1.0])
                 for a in DOTS_ANGLES_DEG]
        return _boolean("union", [_plate(14, 1.0)] + domes)
    if name == "hemisphere":
        r = np.linspace(0.0, 7 * np.sqrt(2) + 0.1, 64)
        cap = np.column_stack([r, 20 - np.sqrt(400 - r ** 2)])
        dome = _revolve(np.vstack([cap, [[r[-1], TIP_HEIGHT], [0, TIP_HEIGHT]]]))
        return _boolean("intersection", [dome, _plate(14, -1.0)])
    if name == "hexagon":
        return _extrude(_regular_polygon(6, 3.5))
    if name == "line":
        return _extrude(box(-1, -8, 1, 8))
    if name == "moon":
        return _extrude(_disc(3.5).difference(_disc(2.7, (1.7, 0.0))))
    if name == "pacman":
        a0, a1 = np.radians(PACMAN_MOUTH_DEG)
        mouth = Polygon([(0, 0), (10 * np.cos(a0), 10 * np.sin(a0)), (10 * np.cos(a1), 10 * np.sin(a1))])
        return _extrude(_disc(3.0).difference(mouth))
    if name == "prism":
        return _extrude(box(-2.5, -3.5, 2.5, 3.5))
    if name == "random":
        return _extrude(Polygon(RANDOM_OUTLINE))
    if name == "sphere":
        return _sphere_on_shank(5.0, 2.5, TIP_HEIGHT)
    if name == "sphere_s":
        return _sphere_on_shank(3.0, 1.5, TIP_HEIGHT)
    if name == "torus":
        # the tube (ring radius 3, tube radius 1.5) joined to a hollow shank from r 2.5 to 3.2:
        # from the shank's outer wall round the tube's outside, bottom and inside to its inner wall
        start, end = np.arccos(0.2 / 1.5), np.arccos(-0.5 / 1.5) - 2 * np.pi
        return _revolve(np.vstack([[[3.2, TIP_HEIGHT]], _arc(3.0, 1.5, 1.5, start, end, 129),
                                   [[2.5, TIP_HEIGHT], [3.2, TIP_HEIGHT]]]))
    if name == "triangle":
        return _extrude(Polygon(TRIANGLE_VERTICES))
    if name == "wave":
        return _extrude_xz(_wave_profile(), 14.0)
    if name == "calib_prism":
        return _extrude_xz(Polygon([(0, 0), (6, 6), (-6, 6)]), 15)
    if name == "calib_cone":
        return _revolve([[0, 0], [6, 6], [0, 6]])
    if name == "calib_punch":
        return _revolve([[0, 0], [2, 0], [2, 10], [0, 10]])
    raise KeyError(f"unknown indenter {name!r}; known: {', '.join(ALL_INDENTERS)}")


@functools.lru_cache(maxsize=None)
def _cached(name: str) -> "trimesh.Trimesh":
    return _finish(_build(name))


def make_indenter(name: str) -> "trimesh.Trimesh":
    """A fresh copy of indenter ``name`` (watertight, mm, tip at z = 0, the mount's frame)."""
    if name not in _DESCRIPTIONS:
        raise KeyError(f"unknown indenter {name!r}; known: {', '.join(ALL_INDENTERS)}")
    return _cached(name).copy()


def indenter_meta(name: str) -> dict:
    """bbox (2,3) mm, extents (3,) mm, nominal_size_mm, volume_mm3, group, description."""
    if name not in _DESCRIPTIONS:
        raise KeyError(f"unknown indenter {name!r}; known: {', '.join(ALL_INDENTERS)}")
    mesh = _cached(name)
    desc, size = _DESCRIPTIONS[name]
    group = "calibration" if name in CALIBRATION_INDENTERS else (
        "unseen" if name in UNSEEN else "seen")
    return {
        "name": name, "group": group, "description": desc, "nominal_size_mm": size,
        "bbox": mesh.bounds.copy(), "extents": mesh.extents.copy(),
        "volume_mm3": float(mesh.volume), "n_faces": int(len(mesh.faces)),
        "index": ALL_INDENTERS.index(name),
    }


def export_ply(mesh: "trimesh.Trimesh", path) -> None:
    """Write ``mesh`` as binary PLY (units mm)."""
    mesh.export(str(path), file_type="ply")


# ------------------------------------------------------------------------- height maps
def grid_coords(shape, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Cell-centre coordinates (x of columns (w,), y of rows (h,)) of a pad grid, mm.

    The grid is centred on the pad centre: x_j = (j - (w-1)/2) * spacing and
    y_i = (i - (h-1)/2) * spacing, so ``array[i, j]`` is the value at (x_j, y_i) and the row
    index grows with +y.
    """
    h, w = (shape, shape) if np.isscalar(shape) else shape
    return ((np.arange(w) - (w - 1) / 2) * spacing, (np.arange(h) - (h - 1) / 2) * spacing)


def _lower_triangles(mesh) -> np.ndarray:
    """Downward-facing, non-vertical triangles (T,3,3) with z measured from the lowest point.

    For a watertight solid the lowest crossing of any vertical line enters the solid through
    a face whose outward normal points down, so these faces alone define the lower surface.
    """
    tris = np.asarray(mesh.triangles, float)
    normals = np.asarray(mesh.face_normals)
    tris = tris[normals[:, 2] < -1e-9].copy()
    tris[..., 2] -= float(np.min(mesh.vertices[:, 2]))
    return tris


@functools.lru_cache(maxsize=128)
def _lower_triangles_named(name: str, yaw_deg: float) -> np.ndarray:
    tris = _lower_triangles(_cached(name))
    tris = _rotate_xy(tris, yaw_deg)
    tris.setflags(write=False)
    return tris


def _rotate_xy(tris: np.ndarray, yaw_deg: float) -> np.ndarray:
    if yaw_deg == 0.0:
        return tris.copy()
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    out = tris.copy()
    out[..., 0] = c * tris[..., 0] - s * tris[..., 1]
    out[..., 1] = s * tris[..., 0] + c * tris[..., 1]
    return out


def _rasterise(tris: np.ndarray, h: int, w: int, spacing: float) -> np.ndarray:
    """Minimum z over triangles at every cell centre (z-buffer), +inf where none covers it."""
    zbuf = np.full(h * w, np.inf)
    if len(tris) == 0:
        return zbuf.reshape(h, w)
    gx = tris[..., 0] / spacing + (w - 1) / 2  # continuous column index
    gy = tris[..., 1] / spacing + (h - 1) / 2  # continuous row index
    z = tris[..., 2]
    x0, y0, z0 = gx[:, 0], gy[:, 0], z[:, 0]
    e1x, e1y, e2x, e2y = gx[:, 1] - x0, gy[:, 1] - y0, gx[:, 2] - x0, gy[:, 2] - y0
    det = e1x * e2y - e2x * e1y
    eps = 1e-9
    jlo = np.maximum(np.ceil(gx.min(1) - eps), 0).astype(np.int64)
    jhi = np.minimum(np.floor(gx.max(1) + eps), w - 1).astype(np.int64)
    ilo = np.maximum(np.ceil(gy.min(1) - eps), 0).astype(np.int64)
    ihi = np.minimum(np.floor(gy.max(1) + eps), h - 1).astype(np.int64)
    nj, ni = jhi - jlo + 1, ihi - ilo + 1
    keep = (nj > 0) & (ni > 0) & (np.abs(det) > 1e-12)
    idx = np.nonzero(keep)[0]
    if idx.size == 0:
        return zbuf.reshape(h, w)
    # Affine coefficients per triangle: barycentrics l1, l2 and z as functions of (j, i).
    inv = 1.0 / det[idx]
    a1, b1 = e2y[idx] * inv, -e2x[idx] * inv
    a2, b2 = -e1y[idx] * inv, e1x[idx] * inv
    dz1, dz2 = z[idx, 1] - z0[idx], z[idx, 2] - z0[idx]
    cnt = nj[idx] * ni[idx]
    t = np.repeat(np.arange(idx.size), cnt)
    k = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    njt = nj[idx][t]
    jj = jlo[idx][t] + k % njt
    ii = ilo[idx][t] + k // njt
    dx, dy = jj - x0[idx][t], ii - y0[idx][t]
    l1 = a1[t] * dx + b1[t] * dy
    l2 = a2[t] * dx + b2[t] * dy
    inside = (l1 >= -eps) & (l2 >= -eps) & (l1 + l2 <= 1 + eps)
    zz = z0[idx][t] + l1 * dz1[t] + l2 * dz2[t]
    np.minimum.at(zbuf, (ii * w + jj)[inside], zz[inside])
    return zbuf.reshape(h, w)


def height_map(mesh_or_name, *, shape, spacing: float, position=(0.0, 0.0),
               yaw_deg: float = 0.0) -> np.ndarray:
    """Indenter lower-surface profile on a pad grid, (h, w) float64 in mm.

    ``shape`` (h, w) cells (or an int for square) of ``spacing`` mm, centred on the pad centre
    with the cell-centre convention of :func:`grid_coords` (x along columns, y along rows).
    The indenter is rotated by ``yaw_deg`` about z (counter-clockwise seen from +z, about its
    tip reference point, i.e. the mesh origin) and its tip placed at lateral ``position``
    (x, y) mm. Values are the height of the lower surface above the indenter's lowest point
    (0 at the tip); ``np.inf`` where the indenter is absent. A mesh passed directly keeps its
    own x-y origin as the tip reference.
    """
    h, w = (int(shape), int(shape)) if np.isscalar(shape) else (int(shape[0]), int(shape[1]))
    if spacing <= 0 or h <= 0 or w <= 0:
        raise ValueError("shape and spacing must be positive")
    if isinstance(mesh_or_name, str):
        if mesh_or_name not in _DESCRIPTIONS:
            raise KeyError(f"unknown indenter {mesh_or_name!r}")
        tris = _lower_triangles_named(mesh_or_name, float(yaw_deg))
    else:
        tris = _rotate_xy(_lower_triangles(mesh_or_name), float(yaw_deg))
    px, py = float(position[0]), float(position[1])
    if px != 0.0 or py != 0.0:
        tris = tris + np.array([px, py, 0.0])
    return _rasterise(tris, h, w, float(spacing))


def indenter_set(names, stl_dir: str | None = None, stl_tip: str = "auto") -> dict:
    """Node `indenters`: every named mesh (vertices mm, faces) with its metadata.  With
    `stl_dir`, a name with a <name>.stl there takes that mesh, repaired and placed by
    stages.sim.stl (`stl_tip`: which end presses); the others stay procedural."""
    names = list(names)
    metas = [indenter_meta(n) for n in names]
    found = {}
    if stl_dir is not None:
        from stages.sim.stl import stl_meshes
        found = stl_meshes(stl_dir, names, stl_tip)
    meshes = {}
    for n, meta in zip(names, metas):
        mesh = found[n] if n in found else make_indenter(n)
        if n in found:
            meta.update(extents=mesh.extents.copy(), volume_mm3=float(mesh.volume))
        meshes[n] = {"vertices": mesh.vertices.astype(np.float32), "faces": mesh.faces.astype(np.int32)}
    attrs = {"units": "mm", "convention": "tip lowest point at z=0, body towards +z"}
    if stl_dir is not None:
        attrs.update(stl_dir=str(stl_dir), from_stl=[n for n in names if n in found])
    return {
        "names": names,
        "group": [m["group"] for m in metas],
        "extents": np.array([m["extents"] for m in metas], np.float32),
        "volume_mm3": np.array([m["volume_mm3"] for m in metas]),
        "meshes": meshes,
        "attrs": attrs,
    }


def mesh_from_artifact(art, name: str) -> "trimesh.Trimesh":
    """Rebuild one mesh from an `indenters` artifact (or any mapping of the same layout)."""
    import trimesh
    return trimesh.Trimesh(np.asarray(art[f"meshes/{name}/vertices"]),
                            np.asarray(art[f"meshes/{name}/faces"]), process=False)


def export_artifact_ply(artifact_path, out_dir) -> list:
    """Write every mesh of an `indenters` artifact (an HDF5 file) to OUT_DIR/<name>.ply."""
    import h5py
    from pathlib import Path
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    with h5py.File(artifact_path, "r") as f:
        for name in f["meshes"]:
            path = out / f"{name}.ply"
            export_ply(mesh_from_artifact(f, name), path)
            written.append(path)
    return written


if __name__ == "__main__":  # python -m stages.sim.indenters "$(pipeline get indenters)" ply/
    import os
    import sys
    if len(sys.argv) != 3:
        sys.exit("usage: python -m stages.sim.indenters INDENTERS_ARTIFACT.h5 OUT_DIR")
    if not os.path.isfile(sys.argv[1]):
        sys.exit(f"no such artifact file: {sys.argv[1]!r} (see `pipeline get indenters`)")
    for p in export_artifact_ply(sys.argv[1], sys.argv[2]):
        print(p)
