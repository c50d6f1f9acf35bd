"""Training pairs and the evaluation-frame selection shared by the image-scoring nodes."""
import numpy as np
import pytest

from stages.m2m.data import eval_frame_indices, evenly, frames_of, paired_table, take_rows


def test_eval_frames_are_paired_frames_of_the_eval_indenters(skins):
    art = dict(skins["Array3"])
    art["paired"] = art["paired"].copy()
    art["paired"][1] = False                      # an unpaired frame of the held-out indenter
    rows = eval_frame_indices(art, ["wave"], 5)
    held_out = np.flatnonzero((art["indenter_id"] == 1) & art["paired"])   # 23 rows: 3, 5, ..., 47
    assert held_out.size == 23 and rows.size == 5
    assert np.all(art["indenter_id"][rows] == 1) and 1 not in rows
    np.testing.assert_array_equal(rows, held_out[[2, 6, 11, 16, 20]])      # middles of 5 equal bins
    # every skin on the same trajectory scores the same contact frames
    other = eval_frame_indices(skins["Circle3"], ["wave"], 5)
    assert set(skins["Circle3"]["frame"][other]) <= set(art["frame"][held_out])


def test_eval_frames_errors(skins):
    with pytest.raises(KeyError, match="torus"):
        eval_frame_indices(skins["Array3"], ["torus"], 4)
    art = dict(skins["Array3"], paired=np.zeros(48, bool))
    with pytest.raises(ValueError, match="only 0 evaluation"):
        eval_frame_indices(art, ["wave"], 4)
    with pytest.raises(KeyError, match="indenters"):
        frames_of({k: v for k, v in skins["Array3"].items() if k != "indenters"}, ["wave"])


def test_paired_table_keeps_shared_frames_and_few_pairs(skins):
    a = skins["Array3"]
    b = {k: (v[5:] if k not in ("reference", "indenters") else v) for k, v in skins["Diamond3"].items()}
    frames, rows = paired_table({"A": a, "B": b}, ["A", "B"], ["sphere"])
    assert frames.tolist() == list(range(106, 148, 2))       # seen frames present in both skins
    np.testing.assert_array_equal(a["frame"][rows[0]], frames)
    np.testing.assert_array_equal(b["frame"][rows[1]], frames)
    few, few_rows = paired_table({"A": a, "B": b}, ["A", "B"], ["sphere"], per_skin=3)
    assert few.tolist() == [112, 126, 140] and few_rows.shape == (2, 3)
    with pytest.raises(KeyError, match="C"):
        paired_table({"A": a}, ["A", "C"], ["sphere"])


def test_evenly():
    assert evenly(np.arange(10), 3).tolist() == [1, 5, 8]
    assert evenly(np.arange(2), 5).tolist() == [0, 1]


def test_take_rows_reads_rows_in_any_order_from_a_dataset(tmp_path):
    """take_rows gives arr[rows] for unsorted, repeated rows, from an HDF5 dataset (which
    accepts only increasing rows) as from an array."""
    import h5py
    data = np.arange(40).reshape(10, 4)
    with h5py.File(tmp_path / "a.h5", "w") as f:
        f["x"] = data
    rows = [7, 2, 7, 0, 9]
    with h5py.File(tmp_path / "a.h5", "r") as f:
        np.testing.assert_array_equal(take_rows(f["x"], rows), data[rows])
    np.testing.assert_array_equal(take_rows(data, rows), data[rows])
