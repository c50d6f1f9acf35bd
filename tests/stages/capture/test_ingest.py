"""Node `ingest` on datasets written in the authors' layout by write_example_dataset."""
import os

import cv2
import numpy as np
import pytest

from stages.capture.ingest import infer_phase, ingest, paired_frames, write_example_dataset
from stages.common import InputError
from stages.sim.indenters import ALL_INDENTERS
from tests.helpers import drain


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("published")
    write_example_dataset(root, "gelsight", indenters=("sphere", "prism"), contacts=2, frames=18, seed=3)
    return root


def _files(root, sensor="gelsight"):
    """(indenter, contact folder) in ingest order: ALL_INDENTERS order, natural contact order."""
    base = root / sensor
    names = sorted(os.listdir(base / "sphere"), key=int)
    return [(n, base / n / c) for n in ("prism", "sphere") for c in names]


def test_round_trip_keeps_forces_depths_and_images(dataset):
    chunks, final = drain(ingest(root=str(dataset), sensor="gelsight", size=(480, 640)))
    assert len(chunks) == 4 and final["attrs"]["frames"] == 72
    for cid, (chunk, (name, folder)) in enumerate(zip(chunks, _files(dataset))):
        bits = np.unpackbits(np.load(folder / "markers.npy"), axis=-1)
        np.testing.assert_array_equal(chunk["images"], bits * 255)
        ft = np.loadtxt(folder / "ft.csv", delimiter=",", skiprows=1)
        depth = np.loadtxt(folder / "depth.csv", delimiter=",", skiprows=1)
        np.testing.assert_array_equal(chunk["force"], ft[:, :3].astype(np.float32))
        np.testing.assert_array_equal(chunk["torque"], ft[:, 3:].astype(np.float32))
        np.testing.assert_array_equal(chunk["depth"], depth[:, 0])
        np.testing.assert_array_equal(chunk["position"], np.column_stack([depth[:, 1:], -depth[:, 0]]))
        np.testing.assert_array_equal(chunk["shift"], depth[:, 1:] - depth[:1, 1:])
        # press 6 frames, shear out 3, back 3, release 6; the last 4 of each movement paired
        np.testing.assert_array_equal(chunk["phase"], [0] * 6 + [1] * 3 + [2] * 3 + [3] * 6)
        np.testing.assert_array_equal(chunk["paired"], [0, 0, 1, 1, 1, 1] + [1] * 6 + [0, 0, 1, 1, 1, 1])
        assert set(chunk["contact_id"]) == {cid} and set(chunk["indenter_id"]) == {ALL_INDENTERS.index(name)}
        np.testing.assert_array_equal(chunk["frame"], np.arange(18 * cid, 18 * cid + 18))
    assert list(final["indenters"][:len(ALL_INDENTERS)]) == list(ALL_INDENTERS)
    deepest = max(c["depth"].max() for c in chunks)
    assert final["attrs"]["max_depth_mm"] == deepest and max(c["normalised_depth"].max() for c in chunks) == 1.0
    ref = np.unpackbits(np.load(dataset / "gelsight" / "reference.npy"), axis=-1) * 255
    np.testing.assert_array_equal(final["reference"], ref)
    assert not np.array_equal(chunks[0]["images"][5], ref)      # pressed markers moved


def test_resize_is_area_average_rebinarised(dataset):
    chunks, final = drain(ingest(root=str(dataset), sensor="gelsight", size=(60, 80)))
    bits = np.unpackbits(np.load(_files(dataset)[0][1] / "markers.npy"), axis=-1).astype(np.float32)
    expect = np.stack([cv2.resize(b, (80, 60), interpolation=cv2.INTER_AREA) >= 0.5 for b in bits]) * 255
    np.testing.assert_array_equal(chunks[0]["images"], expect)
    assert chunks[0]["images"].dtype == np.uint8 and final["reference"].shape == (60, 80)
    assert 0.02 < (chunks[0]["images"] > 0).mean() < 0.2


def test_reference_defaults_to_the_first_frame(tmp_path):
    base = write_example_dataset(tmp_path, "tactip", indenters=("cone",), contacts=1, frames=6, seed=1)
    os.remove(os.path.join(base, "reference.npy"))
    chunks, final = drain(ingest(root=str(tmp_path), sensor="tactip", size=(480, 640)))
    np.testing.assert_array_equal(final["reference"], chunks[0]["images"][0])


def test_phase_inference_holds_and_shears():
    depth = [0.2, 0.4, 0.4, 0.4, 0.4, 0.4, 0.4, 0.2, 0.0]
    x = [0.0, 0.0, 0.0, 0.5, 1.0, 0.5, 0.5, 0.5, 0.5]
    phase = infer_phase(depth, np.column_stack([x, np.zeros(9)]))
    np.testing.assert_array_equal(phase, [0, 0, 0, 1, 1, 2, 2, 3, 3])   # holds keep their phase
    np.testing.assert_array_equal(paired_frames(phase, 2), [0, 1, 1, 1, 1, 1, 1, 1, 1])
    np.testing.assert_array_equal(infer_phase([0.3, 0.3, 0.1]), [0, 0, 3])


def test_broken_datasets_name_the_file(tmp_path):
    """Each is the user's InputError (one line, exit 2 from the engine), naming the file."""
    base = write_example_dataset(tmp_path, "s", indenters=("sphere",), contacts=2, frames=6, seed=0)
    with pytest.raises(InputError, match=r"no folder .*/nope \(expected"):
        drain(ingest(root=str(tmp_path), sensor="nope", size=(48, 64)))
    contact = os.path.join(base, "sphere", "2")
    np.save(os.path.join(contact, "markers.npy"), np.zeros((6, 480, 640), np.uint8))
    with pytest.raises(InputError, match=r"sphere/2/markers\.npy holds uint8 \(6, 480, 640\); "
                                         r"expected uint8 \(N, 480, 80\)"):
        drain(ingest(root=str(tmp_path), sensor="s", size=(48, 64)))
    np.save(os.path.join(contact, "markers.npy"), np.zeros((5, 480, 80), np.uint8))
    with pytest.raises(InputError, match=r"sphere/2/markers\.npy has 5 frames but .*sphere/2/depth\.csv has 6 rows"):
        drain(ingest(root=str(tmp_path), sensor="s", size=(48, 64)))
    with open(os.path.join(contact, "ft.csv"), "w") as f:
        f.write("Fx,Fy,Fz\n0,0,0\n")
    with pytest.raises(InputError, match=r"sphere/2/ft\.csv lacks column\(s\) Tx, Ty, Tz"):
        drain(ingest(root=str(tmp_path), sensor="s", size=(48, 64)))
    os.remove(os.path.join(contact, "ft.csv"))
    with pytest.raises(InputError, match=r"missing file .*sphere/2/ft\.csv"):
        drain(ingest(root=str(tmp_path), sensor="s", size=(48, 64)))


def test_unreadable_values_and_files_name_the_file(tmp_path):
    base = write_example_dataset(tmp_path, "s", indenters=("sphere",), contacts=2, frames=6, seed=0)
    contact = os.path.join(base, "sphere", "1")
    for size in ([48], [0, 64], [48.0, 64]):
        with pytest.raises(InputError, match=r"ingest.size must be \[height, width\] in pixels, each >= 8"):
            drain(ingest(root=str(tmp_path), sensor="s", size=size))
    depth = os.path.join(contact, "depth.csv")
    rows = open(depth).read().splitlines()
    rows[3] = ",".join(["nan"] + rows[3].split(",")[1:])
    open(depth, "w").write("\n".join(rows) + "\n")
    with pytest.raises(InputError, match=r"sphere/1/depth\.csv row 4 holds a value that is not a finite number"):
        drain(ingest(root=str(tmp_path), sensor="s", size=(48, 64)))
    write_example_dataset(tmp_path, "s", indenters=("sphere",), contacts=2, frames=6, seed=0)
    with open(os.path.join(contact, "markers.npy"), "r+b") as f:
        f.truncate(100)
    with pytest.raises(InputError, match=r"sphere/1/markers\.npy is not a readable \.npy array"):
        drain(ingest(root=str(tmp_path), sensor="s", size=(48, 64)))
    assert InputError("x").user_error is True
