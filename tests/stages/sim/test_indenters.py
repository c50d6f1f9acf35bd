import numpy as np
import pytest
import trimesh

from stages.sim import indenters as I
from stages.sim.indenters import (ALL_INDENTERS, INDENTERS, SEEN, UNSEEN, export_ply,
                                  grid_coords, height_map, indenter_meta, make_indenter)

# Expected bounding boxes (x-y centre, extents x, y, z) in mm, from the documented shape
# definitions (the authors' dimensions, in their mount's frame). Tolerance 0.01 mm
# (polygonised circles put vertices on the +-x/+-y extremes; the sphere's sampled arc misses
# its equator by < 0.001 mm; the pacman's mouth cuts a 64-gon 0.004 mm inside its circle).
EXTENTS_TOL = 0.01
MOON_TIP = 2.309            # where the crescent's two circles (r 3.5 at 0, r 2.7 at 1.7) cross
PACMAN_X = 3 * np.cos(np.radians(33))
EXPECTED_EXTENTS = {
    "cone": (8, 8, 10),
    "cylinder": (6, 6, 10),
    "cylinder_sh": (7, 7, 10),
    "cylinder_si": (6, 14, 6),
    "dotin": (8, 8, 10),
    "dots": (14, 14, 10),
    "hemisphere": (14, 14, 10),
    "hexagon": (7, 7 * np.sqrt(3) / 2, 10),
    "line": (2, 16, 10),
    "moon": (3.5 + MOON_TIP, 7, 10),
    "pacman": (3 + PACMAN_X, 6, 10),
    "prism": (5, 7, 10),
    "random": (3.372 + 3.606, 2.34 + 2.276, 10),
    "sphere": (10, 10, 10),
    "sphere_s": (6, 6, 10),
    "torus": (9, 9, 10),
    "triangle": (7, 5, 10),
    "wave": (14, 14, 10),
    "calib_prism": (12, 15, 6),
    "calib_cone": (12, 12, 6),
    "calib_punch": (4, 4, 10),
}
OFF_CENTRE = {"moon": ((MOON_TIP - 3.5) / 2, 0), "pacman": ((PACMAN_X - 3) / 2, 0),
              "random": ((3.606 - 3.372) / 2, (2.276 - 2.34) / 2)}


def test_names_and_groups():
    assert len(INDENTERS) == 18 and len(set(INDENTERS)) == 18
    assert len(SEEN) == 12 and len(UNSEEN) == 6
    assert set(SEEN).isdisjoint(UNSEEN) and set(SEEN) | set(UNSEEN) == set(INDENTERS)
    from tests.helpers import ROOT
    import yaml
    splits = yaml.safe_load((ROOT / "params.yaml").read_text())["splits"]
    assert set(UNSEEN) == set(splits["test_indenters"])            # the authors' unseen group
    assert ALL_INDENTERS[:18] == INDENTERS and set(EXPECTED_EXTENTS) == set(ALL_INDENTERS)


@pytest.mark.parametrize("name", ALL_INDENTERS)
def test_mesh_is_watertight_with_expected_bbox(name):
    mesh = make_indenter(name)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0
    np.testing.assert_allclose(mesh.extents, EXPECTED_EXTENTS[name], atol=EXTENTS_TOL)
    lo, hi = mesh.bounds
    assert abs(lo[2]) < 1e-9, "tip must be at z = 0"
    np.testing.assert_allclose((lo[:2] + hi[:2]) / 2, OFF_CENTRE.get(name, (0, 0)), atol=EXTENTS_TOL / 2)
    meta = indenter_meta(name)
    assert meta["group"] == ("calibration" if name.startswith("calib") else
                             "unseen" if name in UNSEEN else "seen")
    np.testing.assert_allclose(meta["bbox"], mesh.bounds)


def test_volumes_match_geometry():
    # 64-gon revolutions: area factor sin(2pi/64)*64/(2pi) = 0.9984.
    poly = 64 * np.sin(2 * np.pi / 64) / (2 * np.pi)
    assert make_indenter("cylinder").volume == pytest.approx(np.pi * 9 * 10 * poly, rel=1e-6)
    assert make_indenter("cylinder_sh").volume == pytest.approx(np.pi * (3.5 ** 2 - 2.7 ** 2) * 10 * poly,
                                                                rel=1e-6)
    assert make_indenter("line").volume == pytest.approx(2 * 16 * 10, rel=1e-9)
    assert make_indenter("prism").volume == pytest.approx(5 * 7 * 10, rel=1e-9)
    (ax, ay), (bx, by), (cx, cy) = I.TRIANGLE_VERTICES
    area = 0.5 * abs((bx - ax) * (cy - ay) - (cx - ax) * (by - ay))
    assert make_indenter("triangle").volume == pytest.approx(area * 10, rel=1e-9)
    frustum = np.pi * 10 / 3 * (0.5 ** 2 + 0.5 * 4 + 4 ** 2)      # tip r 0.5, base r 4, 10 tall
    assert make_indenter("cone").volume == pytest.approx(frustum * poly, rel=1e-6)


def test_copies_are_independent_and_random_is_deterministic():
    a = make_indenter("random")
    a.apply_translation([1.0, 0.0, 0.0])
    b = make_indenter("random")
    assert abs(b.bounds[0, 0] + 3.372) < 1e-9
    rebuilt = I._finish(I._build("random"))
    np.testing.assert_allclose(np.sort(rebuilt.vertices, axis=0), np.sort(b.vertices, axis=0))


def test_unknown_name_raises():
    with pytest.raises(KeyError):
        make_indenter("banana")
    with pytest.raises(KeyError):
        height_map("banana", shape=8, spacing=1.0)


def test_export_ply_roundtrip(tmp_path):
    mesh = make_indenter("pacman")
    path = tmp_path / "pacman.ply"
    export_ply(mesh, path)
    back = trimesh.load(path, force="mesh")
    assert back.is_watertight
    assert len(back.faces) == len(mesh.faces)
    np.testing.assert_allclose(back.bounds, mesh.bounds, atol=1e-5)


def test_grid_coords_convention():
    x, y = grid_coords((4, 6), 0.5)
    np.testing.assert_allclose(x, [-1.25, -0.75, -0.25, 0.25, 0.75, 1.25])
    np.testing.assert_allclose(y, [-0.75, -0.25, 0.25, 0.75])


def test_sphere_height_map_matches_spherical_cap():
    n, spacing, R, c = 128, 20 / 128, 5.0, (0.3, -0.7)
    hm = height_map("sphere", shape=(n, n), spacing=spacing, position=c)
    x, y = grid_coords(n, spacing)
    r = np.hypot(x[None, :] - c[0], y[:, None] - c[1])
    inner = r < 0.9 * R
    cap = R - np.sqrt(R ** 2 - r[inner] ** 2)
    # Tolerance: 64-section revolve sags < 0.005 mm radially; slope <= 2.1 inside 0.9 R.
    np.testing.assert_allclose(hm[inner], cap, atol=0.015)
    centre = r < 0.5 * R
    np.testing.assert_allclose(hm[centre], R - np.sqrt(R ** 2 - r[centre] ** 2), atol=0.006)
    finite = np.isfinite(hm)
    assert np.all(r[finite] <= R + 1e-6) and np.all(finite[r < R - 0.05])


def test_cone_height_is_linear_in_radius():
    n, spacing = 96, 0.2
    hm = height_map("cone", shape=n, spacing=spacing)
    x, y = grid_coords(n, spacing)
    r = np.hypot(x[None, :], y[:, None])
    # Truncated cone: a flat tip of radius 0.5, radius 4 at height 10, so h = (r - 0.5) / 0.35
    # (64-gon: r is the inscribed radius on facets, so h lies between (r - 0.5) / 0.35 and
    # (r / cos(pi/64) - 0.5) / 0.35).
    assert np.all(hm[r < 0.5 * np.cos(np.pi / 64)] == 0.0)
    m = (r > 0.5) & (r < 3.8)
    assert np.all(hm[m] >= (r[m] - 0.5) / 0.35 - 1e-9)
    assert np.all(hm[m] <= (r[m] / np.cos(np.pi / 64) - 0.5) / 0.35 + 1e-9)


FLAT = ("cylinder", "cylinder_sh", "hexagon", "line", "prism", "dotin", "cone")
LINE_CONTACT = ("cylinder_si", "torus", "dots")  # contact along a line, a ring or at five points


@pytest.mark.parametrize("name", FLAT + LINE_CONTACT)
@pytest.mark.parametrize("pos", [(0.0, 0.0), (-4.0, 4.0), (2.3, -1.7)])
def test_contact_cells_are_centred_on_position(name, pos):
    # For these shapes the contact set is symmetric about the tip reference (the mount's
    # centre); triangle, moon, pacman, random and wave are not, by the authors' design.
    n, spacing = 192, 30 / 192  # 30 mm: the 16 mm bar stays on the grid at (-4, 4)
    hm = height_map(name, shape=(n, n), spacing=spacing, position=pos)
    if name in FLAT:
        assert np.min(hm) == 0.0
        weight = (hm <= 1e-9).astype(float)
    else:
        # cell centres miss the contact line or points by < 1 cell (steepest: the domes' flank)
        assert np.min(hm) <= 1.5 * spacing
        # a band about the contact line(s), weighted by closeness so that the cell count in
        # each band (which depends on sub-cell phase) does not bias the centroid
        weight = np.clip(0.2 - hm, 0.0, None)
    x, y = grid_coords(n, spacing)
    cx = (weight.sum(0) * x).sum() / weight.sum()
    cy = (weight.sum(1) * y).sum() / weight.sum()
    assert abs(cx - pos[0]) <= spacing and abs(cy - pos[1]) <= spacing


def test_triangle_contact_centroid_is_its_vertices_mean():
    # The authors' scalene triangle: its face centroid is the mean of its vertices,
    # (0.167, -0.661) mm from the mount's centre.
    n, spacing = 128, 20 / 128
    hm = height_map("triangle", shape=(n, n), spacing=spacing, position=(1.0, 2.0))
    x, y = grid_coords(n, spacing)
    ii, jj = np.nonzero(hm == 0.0)
    cx, cy = np.mean(I.TRIANGLE_VERTICES, axis=0)
    assert abs(x[jj].mean() - (1.0 + cx)) <= spacing / 4 and abs(y[ii].mean() - (2.0 + cy)) <= spacing / 4


# Largest height at a cell centre no more than half a cell diagonal (0.111 mm) from the tip,
# plus < 0.003 mm tessellation sag for the spheres.
CURVED_MAX = {"sphere": 0.004, "sphere_s": 0.006, "hemisphere": 0.004, "calib_cone": 0.112}


@pytest.mark.parametrize("name", sorted(CURVED_MAX))
def test_curved_tip_minimum_at_position(name):
    n, spacing, pos = 128, 20 / 128, (1.1, -3.3)
    hm = height_map(name, shape=(n, n), spacing=spacing, position=pos)
    i, j = np.unravel_index(np.argmin(hm), hm.shape)
    x, y = grid_coords(n, spacing)
    assert abs(x[j] - pos[0]) <= spacing / 2 + 1e-9 and abs(y[i] - pos[1]) <= spacing / 2 + 1e-9
    assert hm[i, j] <= CURVED_MAX[name]


@pytest.mark.parametrize("name,radius", [("cylinder", 3.0), ("calib_punch", 2.0)])
def test_flat_punch_contact_area(name, radius):
    n, spacing = 128, 20 / 128
    hm = height_map(name, shape=n, spacing=spacing, position=(0.5, 0.5))
    area = np.count_nonzero(hm <= 1e-9) * spacing ** 2
    assert area == pytest.approx(np.pi * radius ** 2, rel=0.03)
    assert np.isinf(hm).sum() + np.count_nonzero(hm <= 1e-9) == hm.size  # flat: 0 or absent


def test_yaw_rotates_footprint():
    n, spacing = 101, 0.2  # odd grid: the centre cell is at the origin
    base = np.isfinite(height_map("line", shape=n, spacing=spacing))
    rot = np.isfinite(height_map("line", shape=n, spacing=spacing, yaw_deg=90.0))
    x, y = grid_coords(n, spacing)
    ii, jj = np.nonzero(base)
    assert np.ptp(y[ii]) > 15 and np.ptp(x[jj]) < 2.1  # 2 x 16 mm bar along y
    ii, jj = np.nonzero(rot)
    assert np.ptp(x[jj]) > 15 and np.ptp(y[ii]) < 2.1  # now along x
    assert np.array_equal(rot, base.T)
    diag = np.isfinite(height_map("line", shape=n, spacing=spacing, yaw_deg=45.0))
    ii, jj = np.nonzero(diag)
    assert np.corrcoef(x[jj], y[ii])[0, 1] < -0.95  # counter-clockwise: y turns to -x+y


def test_yaw_moves_pacman_mouth():
    n, spacing = 101, 0.2
    x, y = grid_coords(n, spacing)
    j2, j0, i2, i0 = np.argmin(abs(x - 2.5)), np.argmin(abs(x)), np.argmin(abs(y - 2.5)), \
        np.argmin(abs(y))
    h0 = height_map("pacman", shape=n, spacing=spacing)
    h90 = height_map("pacman", shape=n, spacing=spacing, yaw_deg=90.0)
    assert np.isinf(h0[i0, j2]) and np.isfinite(h0[i2, j0])  # mouth opens to +x
    assert np.isinf(h90[i2, j0]) and np.isfinite(h90[i0, j2])  # mouth opens to +y


def test_height_map_accepts_mesh_and_off_pad_is_empty():
    mesh = make_indenter("hexagon")
    a = height_map(mesh, shape=(40, 50), spacing=0.4, position=(1.0, 2.0), yaw_deg=30.0)
    b = height_map("hexagon", shape=(40, 50), spacing=0.4, position=(1.0, 2.0), yaw_deg=30.0)
    assert a.shape == (40, 50) and a.dtype == np.float64
    np.testing.assert_array_equal(a, b)
    assert np.all(np.isinf(height_map("hexagon", shape=32, spacing=0.5, position=(30, 0))))


def test_height_map_rows_follow_y():
    n, spacing = 64, 0.25
    hm = height_map("sphere_s", shape=n, spacing=spacing, position=(0.0, 5.0))
    x, y = grid_coords(n, spacing)
    ii, _ = np.nonzero(np.isfinite(hm))
    assert abs(y[ii].mean() - 5.0) < spacing


def test_export_artifact_ply(tmp_path):
    import h5py
    import trimesh
    from stages.sim.indenters import export_artifact_ply, indenter_set
    art = indenter_set(["sphere", "line"])
    with h5py.File(tmp_path / "ind.h5", "w") as f:
        for name in ("sphere", "line"):
            for k, v in art["meshes"][name].items():
                f[f"meshes/{name}/{k}"] = v
    paths = export_artifact_ply(tmp_path / "ind.h5", tmp_path / "ply")
    assert sorted(p.name for p in paths) == ["line.ply", "sphere.ply"]
    back = trimesh.load(tmp_path / "ply" / "sphere.ply")
    assert back.is_watertight and np.allclose(back.extents, make_indenter("sphere").extents, atol=1e-4)
