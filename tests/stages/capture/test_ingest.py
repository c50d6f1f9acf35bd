"""Node `ingest[sensor]` on a tiny dataset written in exactly the authors' released layout
(authors_fixture), and the plan-time listings of stages.capture.authors_layout."""
import shutil

import numpy as np
import pytest
from PIL import Image

from stages.capture import authors_layout as layout
from stages.capture.ingest import ingest, pair_rows
from stages.common import InputError
from stages.sim.indenters import ALL_INDENTERS
from tests.helpers import concat, drain
from tests.stages.capture import authors_fixture as fx


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("genforce") / "dataset"
    return root, fx.write_dataset(root)


def run(root, sensor, size=(480, 640), **kw):
    chunks, final = drain(ingest(root=str(root), sensor=sensor, size=list(size), **kw))
    return concat(chunks), final


def ordered(truth):
    """The fixture's contacts in ingest order: stages.sim.indenters order, points as integers."""
    key = lambda c: (ALL_INDENTERS.index(c["indenter"].replace("-", "_")), c["point"])
    return sorted(truth["contacts"], key=key)


def test_listings_follow_the_folders(dataset, tmp_path):
    root, _ = dataset
    assert layout.sensors("authors", str(root)) == ["Array-I", "Array-II", "ratio_6", "ratio_8", "gelsight", "tactip"]
    assert layout.sensors("authors", str(root / "training")) == layout.sensors("authors", str(root))
    assert layout.calibrated_sensors("authors", str(root)) == ["ratio_6", "ratio_8", "gelsight", "tactip"]
    assert layout.sensors("twin", None) == [] and layout.calibrated_sensors("twin", "/nowhere") == []
    assert layout.ordered_pairs("authors", str(root), "hetero") == [["gelsight", "tactip"], ["tactip", "gelsight"]]
    with pytest.raises(InputError, match=r"^data.source must be one of twin, authors, got 'real'$"):
        layout.sensors("real", str(root))
    with pytest.raises(InputError, match=r"data.root is not set: -p data.root=DIR"):
        layout.sensors("authors", None)
    with pytest.raises(InputError, match=f"^data.root: no folder {tmp_path}/nope$"):
        layout.sensors("authors", str(tmp_path / "nope"))


def test_a_set_without_a_sensor_a_study_needs(dataset):
    root, _ = dataset
    assert layout.require_sensors("authors", str(root), "homo", ["Array-II"]) == ["Array-I", "Array-II"]
    with pytest.raises(InputError, match=r"^data.root: the homo set has no sensor 'Circle-II' \(no folder "
                                         r".*/training/homo/img/npy/Circle-II; found: Array-I, Array-II\)$"):
        layout.require_sensors("authors", str(root), "homo", ["Array-I", "Circle-II"])
    assert layout.require_sensors("twin", str(root), "homo", ["Circle-II"]) == []


def test_homo_frames_forces_torques_and_pairs_are_the_files(dataset):
    root, truth = dataset
    art, final = run(root, "Array-I")
    contacts = ordered(truth["Array-I"])
    assert final["indenters"] == list(ALL_INDENTERS) and final["attrs"]["frames"] == len(art["phase"])
    assert [final["indenters"][i] for i in np.unique(art["indenter_id"])] == ["cone", "sphere_s", "wave"]
    row = 0
    for cid, c in enumerate(contacts):
        rows = slice(row, row + c["n"])
        p, s1, s2, r = c["lengths"]
        expect_images = np.stack([fx.mask("Array-I", c["indenter"], c["point"], k) for k in range(c["n"])]) * 255
        np.testing.assert_array_equal(art["images"][rows], expect_images)
        np.testing.assert_array_equal(art["force"][rows], c["force"].astype(np.float32))
        np.testing.assert_array_equal(art["torque"][rows], (c["torque"] / 1000).astype(np.float32))   # N mm -> N m
        np.testing.assert_array_equal(art["phase"][rows], [0] * p + [1] * s1 + [2] * s2 + [3] * r)
        paired = np.flatnonzero(art["paired"][rows])
        assert paired.tolist() == sorted([0, *c["ends"][:3]])
        assert [art["paired_position"][rows][k] for k in [*c["ends"][:3], 0]] == [0, 1, 2, 3]
        assert set(art["contact_id"][rows]) == {cid} and set(art["point"][rows]) == {c["point"]}
        assert {final["indenters"][i] for i in art["indenter_id"][rows]} == {c["indenter"]}
        np.testing.assert_array_equal(art["file_frame"][rows], np.arange(c["n"]))
        row += c["n"]
    assert row == len(art["phase"]) and art["paired"].sum() == 4 * len(contacts)
    np.testing.assert_array_equal(final["reference"], fx.mask("Array-I", "", 0, -1) * 255)
    assert "depth" not in art and final["attrs"]["set"] == "homo"
    assert len(set(art["frame"].tolist())) == len(art["frame"])          # a key per frame


def test_resize_is_the_area_share_of_marker_pixels(dataset):
    root, truth = dataset
    art, final = run(root, "Array-I", size=(60, 80))                      # 8 x 8 pixel blocks
    c = ordered(truth["Array-I"])[0]
    bits = np.stack([fx.mask("Array-I", c["indenter"], c["point"], k) for k in range(c["n"])])
    share = bits.reshape(c["n"], 60, 8, 80, 8).mean(axis=(2, 4))
    np.testing.assert_array_equal(art["images"][:c["n"]], np.where(share >= 0.5, 255, 0))
    assert art["images"].dtype == np.uint8 and final["reference"].shape == (60, 80)


def test_jpg_frames_binarised_as_the_authors_loaders_do(dataset):
    root, truth = dataset
    art, final = run(root, "Array-II")
    c = ordered(truth["Array-II"])[0]
    folder = root / "training/homo/img/npy/Array-II" / c["indenter"] / str(c["point"])
    expect = np.stack([(np.array(Image.open(folder / f"{k:04d}.jpg")) > 50) * 255 for k in range(c["n"])])
    np.testing.assert_array_equal(art["images"][:c["n"]], expect)
    assert final["attrs"]["jpg_frames"] == len(art["phase"])
    assert final["attrs"]["reference_from"].endswith("Array-II_ref.jpg")


def test_hetero_depth_is_the_authors_normalisation(dataset):
    root, truth = dataset
    art, final = run(root, "gelsight", size=(48, 64))
    top, bottom = 1.12310475, -0.07459319
    row = 0
    for c in ordered(truth["gelsight"]):
        z = np.r_[c["inc"], c["dec"]]
        rows = slice(row, row + c["n"])
        np.testing.assert_array_equal(art["normalised_depth"][rows], ((top - z) / (top + 0.07459319)).astype(np.float32))
        np.testing.assert_array_equal(art["depth"][rows], (top - z).astype(np.float32))
        np.testing.assert_array_equal(art["loading"][rows], np.arange(c["n"]) < len(c["inc"]))
        row += c["n"]
    assert final["attrs"]["depth_top"] == top and final["attrs"]["depth_bottom"] == bottom
    assert art["normalised_depth"].max() == pytest.approx(1.0) and art["normalised_depth"].min() == pytest.approx(0.0)


def test_modulus_crlf_files_and_spelling_variants(dataset):
    root, truth = dataset
    art, final = run(root, "ratio_6", size=(48, 64), modulus_depth_mm=1.5)     # CRLF everywhere
    assert [final["indenters"][i] for i in np.unique(art["indenter_id"])] == ["cone", "sphere_s", "wave"]   # sphere-s
    z = np.concatenate([np.r_[c["inc"], c["dec"]] for c in ordered(truth["ratio_6"])])
    np.testing.assert_array_equal(art["normalised_depth"], z.astype(np.float32))
    np.testing.assert_array_equal(art["depth"], (z * 1.5).astype(np.float32))
    np.testing.assert_array_equal(art["force"], np.concatenate([c["force"] for c in ordered(truth["ratio_6"])]).astype(np.float32))


def test_pairs_by_motion_position_never_by_frame_number(dataset):
    from stages.m2m.data import paired_table
    root, truth = dataset
    a, fa = run(root, "Array-I", size=(48, 64))
    b, fb = run(root, "Array-II", size=(48, 64))
    a["indenters"], b["indenters"] = fa["indenters"], fb["indenters"]
    ra, rb = pair_rows(a, b)
    assert len(ra) == 3 * 2 * 4
    for i, j in zip(ra, rb):
        assert fa["indenters"][a["indenter_id"][i]] == fb["indenters"][b["indenter_id"][j]]
        assert (a["point"][i], a["paired_position"][i]) == (b["point"][j], b["paired_position"][j])
    ends_a = {(c["indenter"], c["point"]): c["ends"] for c in truth["Array-I"]["contacts"]}
    ends_b = {(c["indenter"], c["point"]): c["ends"] for c in truth["Array-II"]["contacts"]}
    pos = a["paired_position"][ra]
    want_a = [([*ends_a[(fa["indenters"][a["indenter_id"][i]], a["point"][i])][:3], 0])[p] for i, p in zip(ra, pos)]
    want_b = [([*ends_b[(fb["indenters"][b["indenter_id"][j]], b["point"][j])][:3], 0])[p] for j, p in zip(rb, pos)]
    assert a["file_frame"][ra].tolist() == want_a and b["file_frame"][rb].tolist() == want_b
    assert want_a != want_b                                  # the sensors' frame numbers differ
    sel_a, sel_b = pair_rows(a, b, indenters=["wave"])
    assert len(sel_a) == 8 and {fb["indenters"][i] for i in b["indenter_id"][sel_b]} == {"wave"}
    # the twins' pairing (equal `frame` keys) pairs the same frames
    frames, rows = paired_table({"A": a, "B": b}, ["A", "B"], ["cone", "sphere_s", "wave"])
    assert sorted(zip(rows[0].tolist(), rows[1].tolist())) == sorted(zip(ra.tolist(), rb.tolist()))
    assert (np.diff(rows, axis=1) > 0).all()        # in key order, each sensor's rows in row order
    assert not set(a["frame"][~a["paired"]].tolist()) & set(b["frame"].tolist())


def test_a_contact_without_forces_is_left_out_as_the_authors_do(dataset, tmp_path):
    root = tmp_path / "d"
    shutil.copytree(dataset[0] / "training" / "homo", root / "training" / "homo")
    shutil.rmtree(root / "training/homo/force/Array-I/wave/10")
    art, final = run(root, "Array-I", size=(48, 64))
    assert final["attrs"]["skipped"] == ["wave/10"] and final["attrs"]["contacts"] == 5


def test_indenters_of_a_lab_follow_the_papers_and_keys_grow_with_the_rows(tmp_path):
    """`indenters` lists every paper indenter (a split naming one the sensor lacks selects
    nothing), then a lab's own; paired frame keys grow with the rows, 0000 first."""
    from stages.capture.ingest import indenter_code
    training = tmp_path / "training"
    fx.write_sensor(training, "homo", "Array-I", ["wave", "star", "knob"], [3, 1])
    art, final = run(tmp_path, "Array-I", size=(48, 64))
    extra = sorted(["star", "knob"], key=indenter_code)
    assert final["indenters"] == [*ALL_INDENTERS, *extra]
    assert [final["indenters"][i] for i in dict.fromkeys(art["indenter_id"].tolist())] == ["wave", *extra]
    keys = art["frame"][art["paired"]]
    assert (np.diff(keys) > 0).all() and len(keys) == 3 * 2 * 4
    assert (keys % 10)[:4].tolist() == [0, 1, 2, 3]                  # 0000, then the three motion ends


def test_npy_csv_last_files_are_read_first(dataset, tmp_path):
    """training_utils.py looks in the sibling npy_csv/ folder before the image folder."""
    root = tmp_path / "d"
    shutil.copytree(dataset[0] / "training" / "homo", root / "training" / "homo")
    img = root / "training/homo/img/npy/Array-I"
    alt = root / "training/homo/img/npy_csv/Array-I"
    for last in img.glob("*/*/last.csv"):
        (alt / last.parent.relative_to(img)).mkdir(parents=True)
        shutil.copy(last, alt / last.relative_to(img))
    c = ordered(dataset[1]["Array-I"])[0]
    n = c["n"]
    (alt / c["indenter"] / str(c["point"]) / "last.csv").write_text(
        "".join(f"C:\\GenForce\\{k:04d}.npy\r\n" for k in (1, 2, 3)))     # Windows paths, CRLF, the 3 M2M reads
    art, final = run(root, "Array-I", size=(48, 64))
    np.testing.assert_array_equal(art["phase"][:n], [0, 0, 1, 2] + [3] * (n - 4))
    assert np.flatnonzero(art["paired"][:n]).tolist() == [0, 1, 2, 3]
    assert art["paired_position"][:4].tolist() == [3, 0, 1, 2]
    assert final["attrs"]["last_csv_dir"] == str(alt)


def test_ft_header_variants(tmp_path):
    from stages.capture.authors_files import read_ft
    path = tmp_path / "ft.csv"
    path.write_bytes("\ufeffFx,Fy,Fz\r\n0.5,-0.25,-1.5\r\n".encode())       # BOM, CRLF, no units, no torques
    force, torque = read_ft(path)
    assert force.tolist() == [[0.5, -0.25, -1.5]] and torque is None
    path.write_text("Fx(N),Fy(N),Fz(N),Tx(Nm),Ty(Nm),Tz(Nm)\n1,2,3,0.004,0.005,0.006\n")
    assert read_ft(path)[1].tolist() == [[0.004, 0.005, 0.006]]
    path.write_text("Fx(mN),Fy(N),Fz(N)\n1,2,3\n")
    with pytest.raises(InputError, match=rf"^{path} header 'Fx\(mN\)': unit 'mn' is not N$"):
        read_ft(path)


# -------------------------------------------------------------------------------- bad input

@pytest.fixture()
def small(tmp_path):
    """One homo sensor (one indenter, one point) and one hetero sensor, fresh per test."""
    training = tmp_path / "training"
    fx.write_sensor(training, "homo", "Array-I", ["cone"], [1])
    fx.write_sensor(training, "hetero", "gelsight", ["cone"], [1])
    return tmp_path


def _contact(root, set_name="homo", sensor="Array-I"):
    return root / "training" / fx.IMG[set_name] / sensor / "cone" / "1"


def _ft(root, set_name="homo", sensor="Array-I"):
    return root / "training" / set_name / "force" / sensor / "cone" / "1" / "ft.csv"


def _break(kind, root):
    """Damage one file the way `kind` says; return (sensor, the error line it must give)."""
    c = _contact(root)
    if kind == "missing frame":
        (c / "0002.npy").unlink()
        return "Array-I", f"missing frame {c}/0002.npy"
    if kind == "truncated frame":
        data = (c / "0001.npy").read_bytes()
        (c / "0001.npy").write_bytes(data[:1000])
        return "Array-I", f"frame {c}/0001.npy is truncated or not a .npy array"
    if kind == "wrongly sized frame":
        np.save(c / "0001.npy", np.packbits(np.ones((480, 632), np.uint8)))
        return "Array-I", (f"frame {c}/0001.npy is wrongly sized: uint8 (37920,), expected uint8 (38400,), "
                           "np.packbits of a 480x640 mask")
    if kind == "non-binary frame":
        np.save(c / "0001.npy", np.full((480, 640), 7, np.uint8))
        return "Array-I", f"frame {c}/0001.npy is not binary: values [7] (expected 0/1 or 0/255)"
    if kind == "not a frame":
        (c / "0001.npy").write_bytes(b"hello, world")
        return "Array-I", f"frame {c}/0001.npy is truncated or not a .npy array"
    if kind == "truncated jpg":
        (c / "0000.npy").unlink()
        Image.fromarray(np.zeros((480, 640), np.uint8)).save(c / "0000.jpg")
        (c / "0000.jpg").write_bytes((c / "0000.jpg").read_bytes()[:300])
        return "Array-I", f"frame {c}/0000.jpg is truncated or not a JPEG image"
    if kind == "jpg of another size":
        (c / "0001.npy").unlink()
        Image.fromarray(np.zeros((240, 320), np.uint8)).save(c / "0001.jpg")
        return "Array-I", f"frame {c}/0001.jpg is wrongly sized: 240x320, the sensor's other frames are 480x640"
    if kind == "ft.csv rows":
        lines = _ft(root).read_text().splitlines()
        _ft(root).write_text("\n".join(lines[:-1]) + "\n")
        return "Array-I", f"{_ft(root)} has {len(lines) - 2} rows but {c} holds {len(lines) - 1} frames"
    if kind == "ft.csv header":
        lines = _ft(root).read_text().splitlines()
        _ft(root).write_text("\n".join(lines[1:]) + "\n")
        return "Array-I", f"{_ft(root)} has the header {lines[1]!r}; expected Fx(N),Fy(N),Fz(N),Tx(Nmm),Ty(Nmm),Tz(Nmm)"
    if kind == "last.csv names a missing frame":
        lines = (c / "last.csv").read_text().splitlines()
        lines[1] = lines[1].rsplit("/", 1)[0] + "/0099.npy"
        (c / "last.csv").write_text("\n".join(lines) + "\n")
        n = len(list(c.glob("*.npy")))
        return "Array-I", f"{c}/last.csv names frame 0099, which {c} does not hold (frames 0000-{n - 1:04d})"
    if kind == "last.csv lines":
        lines = (c / "last.csv").read_text().splitlines()
        (c / "last.csv").write_text("\n".join(lines[:2]) + "\n")
        return "Array-I", (f"{c}/last.csv names 2 frame(s); expected 4, the last frame of press, shear out, "
                           "shear back and release")
    if kind == "last.csv order":
        lines = (c / "last.csv").read_text().splitlines()
        (c / "last.csv").write_text("\n".join([lines[1], lines[0], *lines[2:]]) + "\n")
        return "Array-I", f"{c}/last.csv names frames "
    if kind == "depth rows":
        inc = root / "training/hetero/depth/gelsight/cone/1/inc_z.csv"
        lines = inc.read_text().splitlines()
        inc.write_text("\n".join(lines[:-1]) + "\n")
        n = len(_ft(root, "hetero", "gelsight").read_text().splitlines()) - 1
        dec = len((inc.parent / "dec_z.csv").read_text().splitlines())
        return "gelsight", (f"{inc} and dec_z.csv have {len(lines) - 1} + {dec} rows but "
                            f"{_ft(root, 'hetero', 'gelsight')} has {n}")
    raise AssertionError(kind)


BAD = ["missing frame", "truncated frame", "wrongly sized frame", "non-binary frame", "not a frame",
       "truncated jpg", "jpg of another size", "ft.csv rows", "ft.csv header", "last.csv names a missing frame", "last.csv lines", "last.csv order",
       "depth rows"]


@pytest.mark.parametrize("kind", BAD)
def test_bad_input_is_one_line_naming_the_file(small, kind):
    sensor, message = _break(kind, small)
    with pytest.raises(InputError) as err:
        run(small, sensor, size=(48, 64))
    text = str(err.value)
    assert "\n" not in text and text.startswith(message), text


# ------------------------------------------------------------------------- through the CLI

def _cli(*args):
    import os
    import subprocess
    import sys
    from tests.helpers import ROOT
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("PIPELINE_STORE", None)
    return subprocess.run([sys.executable, "-m", "pipeline", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=300)


def test_pipeline_run_ingest_on_the_ci_profile(dataset, tmp_path):
    import json

    from pipeline.artifact import Artifact
    root, truth = dataset
    store = tmp_path / "store"
    data = ["-p", "data.source=authors", "-p", f"data.root={root}", "--profile", "ci", "--store", str(store)]
    p = _cli("run", "ingest", "authors_calibration", *data, "--json")
    assert p.returncode == 0, p.stderr
    nodes = json.loads(p.stdout)["nodes"]
    assert [n["name"] for n in nodes] == [f"ingest[sensor={s}]" for s in truth] + [
        f"authors_calibration[sensor={s}]" for s in ("ratio_6", "ratio_8", "gelsight", "tactip")]
    assert {n["status"] for n in nodes} == {"ran"}
    path = _cli("get", "ingest[sensor=tactip]", *data).stdout.strip()
    with Artifact(path) as art:
        assert art["images"].shape[1:] == (96, 96)                       # the ci profile's render.size
        forces = np.concatenate([c["force"] for c in ordered(truth["tactip"])]).astype(np.float32)
        np.testing.assert_array_equal(art["force"][:], forces)
        assert art.attrs["set"] == "hetero"
    again = _cli("run", "ingest", *data, "--json")
    assert {n["status"] for n in json.loads(again.stdout)["nodes"]} == {"cached"}
    # a damaged frame: one line naming it, exit 2, nothing added to the store
    bad = tmp_path / "bad"
    shutil.copytree(root / "training" / "hetero", bad / "training" / "hetero")
    for tree in ("img", "force", "depth"):                     # gelsight alone, so that nothing else runs
        shutil.rmtree(bad / "training/hetero" / tree / "tactip")
    frame = bad / "training/hetero/img/gelsight/wave/10/0003.npy"
    frame.write_bytes(frame.read_bytes()[:500])
    before = sorted(p.name for p in (store / "objects").iterdir())
    p = _cli("run", "ingest", "-p", "data.source=authors", "-p", f"data.root={bad}", "--profile", "ci",
             "--store", str(store))
    assert p.returncode == 2
    assert p.stderr.startswith(f"pipeline: error: node ingest[sensor=gelsight]: frame {frame} is truncated or "
                               "not a .npy array (") and p.stderr.count("\n") == 1, p.stderr
    assert sorted(p.name for p in (store / "objects").iterdir()) == before
