"""The paper's 18 indenters (plus 3 rigid calibration indenters) as procedural meshes.

Frame convention for every indenter mesh (mm):
  * the tip's lowest point is at z = 0 and the body extends to +z (the pad surface is the
    plane z = 0 and pressing moves the indenter towards -z, see ``trajectory.py``);
  * the lateral reference point ("the tip position") is the origin: each mesh is centred so
    that the centre of its x-y bounding box is at (0, 0).

The authors' CAD files are not available; shapes are rebuilt from the names and the paper's
pictures at realistic sizes (tips 4-12 mm across, 6-12 mm tall). The seen/unseen split used by
the authors is not published: we keep the 12 basic primitives as SEEN and hold out 6 shapes
whose contact footprints appear nowhere in the seen group (dot-in-ring, crescent, notched disc,
random bumps, curved ring, periodic ridges) as UNSEEN.

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
UNSEEN: tuple[str, ...] = ("dotin", "moon", "pacman", "random", "torus", "wave")
SEEN: tuple[str, ...] = tuple(n for n in INDENTERS if n not in UNSEEN)
CALIBRATION_INDENTERS: tuple[str, ...] = ("calib_prism", "calib_cone", "calib_punch")
# indenter_id in every trajectory indexes this tuple; its first 18 entries are INDENTERS.
ALL_INDENTERS: tuple[str, ...] = INDENTERS + CALIBRATION_INDENTERS

RANDOM_SEED = 20250611
_SECTIONS = 64  # multiple of 4, so revolved solids have vertices on the +-x / +-y extremes

_DESCRIPTIONS = {
    "cone": ("apex-down cone, base diameter 10 mm, height 8 mm", 10.0),
    "cylinder": ("flat cylindrical punch, diameter 8 mm, height 10 mm", 8.0),
    "cylinder_sh": ("cylindrical shell, outer diameter 8 mm, wall 1 mm, height 10 mm", 8.0),
    "cylinder_si": ("cylinder on its side, diameter 6 mm, length 10 mm along x", 6.0),
    "dotin": ("dot (diameter 2 mm) inside a ring (6-8 mm), 2 mm recess between", 8.0),
    "dots": ("4 pins (diameter 1.5 mm, pitch 5 mm) under a 10x10 mm plate", 1.5),
    "hemisphere": ("dome, radius 6 mm, flat side up", 12.0),
    "hexagon": ("hexagonal flat punch, circumradius 4 mm (corner on +x)", 8.0),
    "line": ("flat bar 10 x 1 mm (long axis along x)", 1.0),
    "moon": ("crescent: disc r 4 minus disc r 4 offset 2.5 mm along +x", 8.0),
    "pacman": ("disc r 4 with a 60 deg mouth opening towards +x", 8.0),
    "prism": ("triangular prism edge-down (knife edge along y, 10 mm), 8 mm wide, 6 mm tall", 8.0),
    "random": ("disc r 5 with 9 random spherical bumps (fixed seed)", 10.0),
    "sphere": ("sphere, diameter 8 mm, on a 4 mm shank", 8.0),
    "sphere_s": ("small sphere, diameter 4 mm, on a 2 mm shank", 4.0),
    "torus": ("torus (ring radius 3.5, tube radius 1 mm) under a disc plate", 9.0),
    "triangle": ("equilateral triangular flat punch, circumradius 4.5 mm (corner on +x)", 9.0),
    "wave": ("sinusoidal ridges along y: wavelength 4 mm, 1.2 mm peak-to-valley", 10.0),
    "calib_prism": ("rigid calibration prism: 90 deg knife edge 15 mm long along y", 12.0),
    "calib_cone": ("rigid calibration cone: 90 deg apex, base diameter 12 mm", 12.0),
    "calib_punch": ("rigid calibration flat punch, diameter 4 mm, height 10 mm", 4.0),
}


# ---------------------------------------------------------------- mesh construction helpers
def _finish(mesh: "trimesh.Trimesh") -> "trimesh.Trimesh":
    """Merge, orient outwards, centre the x-y bbox on the origin and put the tip at z = 0."""
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    if mesh.volume < 0:
        mesh.invert()
    lo, hi = mesh.bounds
    mesh.apply_translation([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
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


def _extrude(poly, height) -> "trimesh.Trimesh":
    """Extrude a shapely footprint from z = 0 to ``height`` (flat punch)."""
    import trimesh

    return trimesh.creation.extrude_polygon(poly, height)


def _extrude_xz(poly, length) -> "trimesh.Trimesh":
    """Extrude a shapely profile drawn in (x, z) along y (used for edge-down prisms, waves)."""
    mesh = _extrude(poly, length)
    rot = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], float)
    mesh.apply_transform(rot)  # (u, v, w) -> (u, -w, v)
    return mesh


def _union(meshes) -> "trimesh.Trimesh":
    import trimesh

    return trimesh.boolean.union(meshes, engine="manifold")


def _disc(radius):
    from shapely.geometry import Point

    return Point(0.0, 0.0).buffer(radius, quad_segs=_SECTIONS // 4)


def _regular_polygon(n, circumradius):
    from shapely.geometry import Polygon

    a = 2 * np.pi * np.arange(n) / n
    return Polygon(np.column_stack([circumradius * np.cos(a), circumradius * np.sin(a)]))


def _sphere_on_shank(radius, shank_radius, top):
    a_end = np.pi - np.arcsin(shank_radius / radius)
    a = np.linspace(0.0, a_end, 48)
    arc = np.column_stack([radius * np.sin(a), radius - radius * np.cos(a)])
    return _revolve(np.vstack([arc, [[shank_radius, top], [0.0, top]]]))


def _random_bumps():
    import trimesh

    rng = np.random.default_rng(RANDOM_SEED)
    n = 9
    rad = rng.uniform(0.9, 1.3, n)
    protrusion = rng.uniform(0.3, 1.2, n)  # < 2 * rad, so every bump overlaps the disc
    ang, rr = rng.uniform(0, 2 * np.pi, n), 3.5 * np.sqrt(rng.uniform(0, 1, n))
    base = protrusion.max()  # disc underside; the deepest bump ends at z = 0
    parts = [trimesh.creation.cylinder(radius=5.0, segment=[[0, 0, base], [0, 0, 10.0]],
                                       sections=_SECTIONS)]
    for k in range(n):
        s = trimesh.creation.icosphere(subdivisions=3, radius=rad[k])
        s.apply_translation([rr[k] * np.cos(ang[k]), rr[k] * np.sin(ang[k]),
                             base - protrusion[k] + rad[k]])
        parts.append(s)
    return _union(parts)


def _build(name: str) -> "trimesh.Trimesh":
    import trimesh
    from shapely.geometry import Polygon, box

    if name == "cone":
        return _revolve([[0, 0], [5, 8], [0, 8]])
    if name == "cylinder":
        return _revolve([[0, 0], [4, 0], [4, 10], [0, 10]])
    if name == "cylinder_sh":
        return _revolve([[3, 0], [4, 0], [4, 10], [3, 10], [3, 0]])
    if name == "cylinder_si":
        mesh = _revolve([[0, -5], [3, -5], [3, 5], [0, 5]])
        mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
        return mesh
    if name == "dotin":
        return _revolve([[0, 0], [1, 0], [1, 2], [3, 2], [3, 0], [4, 0], [4, 10], [0, 10]])
    if name == "dots":
        parts = [trimesh.creation.box(extents=(10, 10, 6),
                                      transform=trimesh.transformations.translation_matrix(
                                          [0, 0, 5]))]
        for x in (-2.5, 2.5):
            for y in (-2.5, 2.5):
                parts.append(trimesh.creation.cylinder(
                    radius=0.75, segment=[[x, y, 0], [x, y, 2.5]], sections=32))
        return _union(parts)
    if name == "hemisphere":
        a = np.linspace(0, np.pi / 2, 48)
        arc = np.column_stack([6 * np.sin(a), 6 - 6 * np.cos(a)])
        return _revolve(np.vstack([arc, [[0, 6]]]))
    if name == "hexagon":
        return _extrude(_regular_polygon(6, 4.0), 10)
    if name == "line":
        return _extrude(box(-5, -0.5, 5, 0.5), 10)
    if name == "moon":
        from shapely.geometry import Point

        return _extrude(_disc(4.0).difference(Point(2.5, 0).buffer(4.0, quad_segs=16)), 10)
    if name == "pacman":
        c, s = 10 * np.cos(np.pi / 6), 10 * np.sin(np.pi / 6)
        return _extrude(_disc(4.0).difference(Polygon([(0, 0), (c, -s), (c, s)])), 10)
    if name == "prism":
        return _extrude_xz(Polygon([(0, 0), (4, 6), (-4, 6)]), 10)
    if name == "random":
        return _random_bumps()
    if name == "sphere":
        return _sphere_on_shank(4.0, 2.0, 12.0)
    if name == "sphere_s":
        return _sphere_on_shank(2.0, 1.0, 10.0)
    if name == "torus":
        zp = 1.7  # plate underside: above the 1.5 mm maximum indentation of the tube
        t = np.arcsin(zp - 1.0)
        arc = _arc(3.5, 1.0, 1.0, np.pi - t, 2 * np.pi + t, 97)  # passes the bottom (z = 0)
        return _revolve(np.vstack([[[0, zp]], arc, [[5, zp], [5, 8], [0, 8]]]))
    if name == "triangle":
        return _extrude(_regular_polygon(3, 4.5), 10)
    if name == "wave":
        x = np.linspace(-5, 5, 101)
        z = 0.6 * (1 - np.cos(2 * np.pi * x / 4.0))  # crests (z = 0) at x = 0, +-4
        return _extrude_xz(Polygon(np.vstack([np.column_stack([x, z]), [[5, 8], [-5, 8]]])), 10)
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
    """A fresh copy of indenter ``name`` (watertight, mm, tip at z = 0, x-y bbox centred)."""
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
