"""Indenters from STL files: pymeshlab's repairs, the watertight check and the placement."""
import numpy as np
import pytest
import trimesh

from stages.common import InputError
from stages.sim.indenters import INDENTERS, indenter_set, make_indenter
from stages.sim.stl import compare_footprints, load_stl


def _write(path, vertices, faces):
    trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces), process=False).export(str(path))
    return path


def _box_with_hole_and_duplicates(path, extents=(4.0, 6.0, 10.0), at=(3.0, -2.0, 5.0)):
    box = trimesh.creation.box(extents=extents)
    box.apply_translation(at)
    faces = np.asarray(box.faces)
    top = np.flatnonzero(box.face_normals[:, 2] > 0.5)             # the two triangles of the +z face
    kept = np.delete(faces, top, axis=0)
    return _write(path, box.vertices, np.r_[kept, kept[:3]])        # a hole, and 3 faces twice


def _spike_on_block(path):
    """A 16 x 16 x 10 mm block with a 4-sided pyramid on top, tip up at z = 20 (the authors' way)."""
    block = trimesh.creation.box(extents=(16, 16, 10))
    block.apply_translation((0, 0, 5))
    v = np.array([[-3, -3, 10], [3, -3, 10], [3, 3, 10], [-3, 3, 10], [0.5, 0, 20]], float)
    f = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4], [0, 2, 1], [0, 3, 2]])
    spike = trimesh.Trimesh(v, f)
    spike.fix_normals()
    return _write(path, *(lambda m: (m.vertices, m.faces))(trimesh.util.concatenate([block, spike])))


def test_holes_and_duplicate_faces_are_repaired_and_placed(tmp_path):
    mesh = load_stl(_box_with_hole_and_duplicates(tmp_path / "box.stl"), tip="-z")
    assert mesh.is_watertight and mesh.is_winding_consistent and len(mesh.faces) == 12
    assert mesh.volume == pytest.approx(4 * 6 * 10)
    np.testing.assert_allclose(mesh.bounds, [[-2, -3, 0], [2, 3, 10]], atol=1e-12)


def test_the_narrower_end_is_the_tip(tmp_path):
    path = _spike_on_block(tmp_path / "spike.stl")
    auto = load_stl(path)
    z = auto.vertices[:, 2]
    assert np.ptp(auto.vertices[z < 1e-9], axis=0)[:2].tolist() == [0.0, 0.0]    # one tip vertex at z = 0
    np.testing.assert_allclose(auto.vertices[np.argmin(z)], [0.5, 0.0, 0.0])    # x kept, y turned
    assert auto.bounds[1, 2] == pytest.approx(20.0) and auto.volume > 0
    down = load_stl(path, tip="-z")                                               # taken as it is: the block presses
    assert np.ptp(down.vertices[down.vertices[:, 2] < 1e-9], axis=0)[:2].tolist() == [16.0, 16.0]
    assert load_stl(path, tip="+z").vertices.tolist() == auto.vertices.tolist()


def test_a_mesh_that_cannot_be_repaired_is_one_line(tmp_path):
    cyl = trimesh.creation.cylinder(radius=3.0, height=8.0, sections=64)
    open_top = np.asarray(cyl.faces)[cyl.triangles_center[:, 2] < 3.99]             # the top cap removed
    path = _write(tmp_path / "cone.stl", cyl.vertices, open_top)
    with pytest.raises(InputError, match=rf"^indenter mesh {path} cannot be repaired: not watertight after "
                                         r"closing holes of up to 30 edges \(64 open edge\(s\), 0 shared by "
                                         r"more than two faces\)$"):
        load_stl(path)
    (tmp_path / "junk.stl").write_bytes(b"\x00" * 10)
    with pytest.raises(InputError, match=rf"^indenter mesh {tmp_path}/junk.stl is not a readable STL file"):
        load_stl(tmp_path / "junk.stl")


def _authors_style(mesh, path):
    """`mesh` printed the authors' way: turned tip up on a 16 x 16 x 10 mm mount, tip at z = 20."""
    up = mesh.copy()
    up.apply_transform(np.diag([1.0, -1.0, -1.0, 1.0]))             # 180 degrees about x
    up.apply_translation([0.0, 0.0, 20.0])
    mount = trimesh.creation.box(bounds=[[-8, -8, 0], [8, 8, 10.5]])  # overlaps the shape's base
    trimesh.boolean.union([mount, up], engine="manifold").export(str(path))
    return path


def test_stl_footprints_agree_with_the_procedural_shapes(tmp_path):
    """Generated STLs of the procedural dimensions, on the authors' mount and tip up, load back
    with the procedural footprints (cells under 0.5/1.0/1.5 mm, 65 x 65 grid of 0.39 mm)."""
    for name in INDENTERS:
        _authors_style(make_indenter(name), tmp_path / f"{name}.stl")
    rows = compare_footprints(tmp_path)
    assert [r["name"] for r in rows] == list(INDENTERS)
    assert max(r["max_rel_diff"] for r in rows) <= 0.10, rows
    assert [r["procedural"] for r in rows if r["name"] == "sphere"] == [[97, 185, 261]]
    from stages.sim.indenters import _finish, _sphere_on_shank
    narrow = _finish(_sphere_on_shank(4.0, 2.0, 10.0))                 # a sphere 2 mm narrower
    _authors_style(narrow, tmp_path / "sphere.stl")
    (row,) = compare_footprints(tmp_path, names=["sphere"])
    assert row["max_rel_diff"] > 0.10 and row["stl"][2] < 0.8 * 261


def test_indenter_set_takes_the_stl_meshes_it_finds(tmp_path):
    _box_with_hole_and_duplicates(tmp_path / "cone.stl")
    art = indenter_set(["cone", "sphere"], stl_dir=str(tmp_path), stl_tip="-z")
    stl = load_stl(tmp_path / "cone.stl", tip="-z")
    np.testing.assert_array_equal(art["meshes"]["cone"]["vertices"], stl.vertices.astype(np.float32))
    np.testing.assert_array_equal(art["meshes"]["sphere"]["faces"], make_indenter("sphere").faces)
    assert art["attrs"]["from_stl"] == ["cone"] and art["volume_mm3"][0] == pytest.approx(240.0)
    with pytest.raises(InputError, match=r"holds no <name>.stl for any of indenters.names \(wave\)$"):
        indenter_set(["wave"], stl_dir=str(tmp_path))
    with pytest.raises(InputError, match=r"^indenters.stl_tip must be one of auto, \+z, -z, got 'up'$"):
        indenter_set(["cone"], stl_dir=str(tmp_path), stl_tip="up")


def test_pipeline_run_with_a_broken_mesh_exits_2(tmp_path):
    import os
    import subprocess
    import sys
    from tests.helpers import ROOT
    cyl = trimesh.creation.cylinder(radius=3.0, height=8.0, sections=64)
    path = _write(tmp_path / "cone.stl", cyl.vertices, np.asarray(cyl.faces)[cyl.triangles_center[:, 2] < 3.99])
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.run([sys.executable, "-m", "pipeline", "run", "indenters", "--profile", "ci", "--store",
                        str(tmp_path / "store"), "-p", f"indenters.stl_dir={tmp_path}"], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 2 and p.stderr.count("\n") == 1, p.stderr
    assert p.stderr.startswith(f"pipeline: error: node indenters: indenter mesh {path} cannot be repaired")
    assert not list((tmp_path / "store" / "objects").glob("*.h5"))
