import numpy as np
import pytest

from stages.sim.indenters import ALL_INDENTERS, INDENTERS, SEEN
from stages.sim.trajectory import (calibration_trajectory, collection_trajectory,
                                   sim_grid_trajectory, surface_points)


def _frame_fields_consistent(tr):
    n = tr["depth"].shape[0]
    for key in ("position", "depth", "shift", "phase", "contact_id", "indenter_id", "paired"):
        assert tr[key].shape[0] == n, key
    assert tr["phase"].dtype == np.int8 and tr["contact_id"].dtype == np.int32
    assert tr["indenter_id"].dtype == np.int16 and tr["paired"].dtype == bool
    np.testing.assert_allclose(tr["position"][:, 2], -tr["depth"])
    assert np.all(np.diff(tr["contact_id"]) >= 0) and tr["contact_id"][0] == 0
    assert list(tr["indenters"]) == list(ALL_INDENTERS)


def test_sim_grid_counts_and_values():
    tr = sim_grid_trajectory()
    _frame_fields_consistent(tr)
    assert tr["depth"].size == 810
    counts = np.bincount(tr["indenter_id"], minlength=18)
    assert np.all(counts == 45)
    assert np.array_equal(np.unique(tr["indenter_id"]), np.arange(18))
    assert len(np.unique(tr["contact_id"])) == 18 * 9
    np.testing.assert_allclose(np.unique(tr["depth"]), [0.3, 0.6, 0.9, 1.2, 1.5])
    np.testing.assert_allclose(np.unique(tr["position"][:, :2]), [-4, 0, 4])
    assert np.all(tr["shift"] == 0) and np.all(tr["phase"] == 0)
    for cid in (0, 77, 161):  # each contact: one (x, y), depths ascending
        m = tr["contact_id"] == cid
        assert len(np.unique(tr["position"][m, :2], axis=0)) == 1
        assert np.all(np.diff(tr["depth"][m]) > 0)
    # every indenter visits all 9 grid points
    sphere = tr["indenter_id"] == INDENTERS.index("sphere")
    assert len(np.unique(tr["position"][sphere, :2], axis=0)) == 9


def test_sim_grid_subset():
    tr = sim_grid_trajectory(indenters=("torus", "cone"))
    assert tr["depth"].size == 90
    assert tr["indenter_id"][0] == INDENTERS.index("torus")
    assert tr["indenter_id"][-1] == INDENTERS.index("cone")


def test_surface_points():
    np.testing.assert_allclose(surface_points(5, 3.0),
                               [[0, 0], [3, 0], [0, 3], [-3, 0], [0, -3]], atol=1e-12)


@pytest.fixture(scope="module")
def coll():
    return collection_trajectory(indenters=("sphere", "line"))


def test_collection_structure(coll):
    tr = coll
    _frame_fields_consistent(tr)
    assert tr["depth"].max() == pytest.approx(1.0, abs=1e-12)
    assert tr["depth"].min() >= 0
    np.testing.assert_allclose(np.unique(tr["depth_level"]), [0.25, 0.5, 0.75, 1.0])
    # movements: per (indenter, point): 4 levels x (1 press + 8 out + 8 back + 1 release)
    mv = tr["movement_id"]
    assert np.all(np.diff(mv) >= 0)
    first = np.r_[True, np.diff(mv) > 0]
    phases = tr["phase"][first]
    n_groups = 2 * 5
    assert np.bincount(phases, minlength=4).tolist() == [4 * n_groups, 32 * n_groups,
                                                         32 * n_groups, 4 * n_groups]
    assert len(np.unique(tr["contact_id"])) == 4 * n_groups  # one contact per press cycle
    # x, y = surface point + shift
    pts = tr["points"][tr["point_id"]]
    np.testing.assert_allclose(tr["position"][:, :2], pts + tr["shift"])
    # time on a uniform 40 Hz clock
    np.testing.assert_allclose(np.diff(tr["time"]), 1 / 40.0)


def test_every_contact_starts_on_the_untouched_surface(coll):
    """A contact's first frame is the press's start at depth 0 (the authors' frame 0000), not
    paired (M2M pairs the last frames of each movement); the next frames press in."""
    first = np.flatnonzero(np.r_[True, np.diff(coll["contact_id"]) != 0])
    assert first.size == len(np.unique(coll["contact_id"])) == 40
    assert np.all(coll["depth"][first] == 0) and np.all(coll["phase"][first] == 0)
    assert not coll["paired"][first].any()
    assert np.all(coll["depth"][first + 1] > 0)
    # the 0.25 mm press: start, then ceil(0.25 / (1.5 / 40)) = 7 samples, the last at the level
    level = coll["depth_level"][first] == 0.25
    press = (coll["movement_id"] == coll["movement_id"][first[level][0]])
    np.testing.assert_allclose(coll["depth"][press], np.arange(8) / 7 * 0.25)


def test_collection_press_and_release_have_no_shift(coll):
    still = np.isin(coll["phase"], (0, 3))
    assert np.all(coll["shift"][still] == 0)
    assert np.all(coll["direction_id"][still] == -1)
    shear = ~still
    np.testing.assert_allclose(coll["depth"][shear], coll["depth_level"][shear])


def test_collection_shear_directions(coll):
    tr = coll
    out = (tr["phase"] == 1)
    ends = out & np.r_[np.diff(tr["movement_id"]) > 0, True]  # last sample of each shear-out
    s = tr["shift"][ends]
    np.testing.assert_allclose(np.linalg.norm(s, axis=1), 1.0, atol=1e-12)
    ang = np.degrees(np.arctan2(s[:, 1], s[:, 0])) % 360
    np.testing.assert_allclose(ang, tr["direction_id"][ends] * 45.0, atol=1e-9)
    assert sorted(np.unique(np.round(ang, 6))) == [0, 45, 90, 135, 180, 225, 270, 315]
    assert np.all(np.linalg.norm(tr["shift"], axis=1) <= 1.0 + 1e-12)
    back = (tr["phase"] == 2) & np.r_[np.diff(tr["movement_id"]) > 0, True]
    assert np.all(tr["shift"][back] == 0)


def test_collection_paired_frames(coll):
    tr = coll
    mv = tr["movement_id"]
    per_move = np.bincount(mv, weights=tr["paired"]).astype(int)
    assert np.all(per_move == 4)
    # the paired frames are the last four of each movement, ending at the target
    last = np.r_[np.diff(mv) > 0, True]
    idx = np.nonzero(last)[0]
    for off in range(4):
        assert np.all(tr["paired"][idx - off])
    assert not np.any(tr["paired"][idx - 4][tr["movement_id"][idx - 4] == mv[idx]])


def test_collection_seen_paired_count_matches_paper():
    tr = collection_trajectory(indenters=SEEN)
    assert int(tr["paired"].sum()) == 17280


def test_collection_speed_and_dwell():
    tr = collection_trajectory(indenters=("cone",), n_points=1, speed_mm_s=2.0,
                               dwell_samples=3)
    step = np.linalg.norm(np.diff(np.column_stack([tr["shift"], tr["depth"]]), axis=0), axis=1)
    same = np.diff(tr["movement_id"]) == 0
    assert step[same].max() <= 2.0 / 40 + 1e-9  # never faster than commanded
    last = np.r_[np.diff(tr["movement_id"]) > 0, True]
    idx = np.nonzero(last)[0]
    np.testing.assert_allclose(tr["shift"][idx - 3], tr["shift"][idx])  # dwell at target
    assert np.all(tr["paired"][idx - 3])


def test_collection_tactip_and_pressing_variant():
    tt = collection_trajectory(indenters=("cone",), depth_step_mm=1.125, max_depth_mm=4.5,
                               rate_hz=20.0)
    np.testing.assert_allclose(np.unique(tt["depth_level"]), [1.125, 2.25, 3.375, 4.5])
    np.testing.assert_allclose(np.diff(tt["time"]), 0.05)
    v = collection_trajectory(indenters=("cone",), n_points=1, shear_every_depth=False)
    assert np.all(v["contact_id"] == 0)
    shear = np.isin(v["phase"], (1, 2))
    assert np.all(v["depth"][shear] == 1.0)
    press = v["phase"] == 0
    assert np.all(np.diff(v["depth"][press]) > 0)


def test_calibration_trajectory():
    tr = calibration_trajectory()
    _frame_fields_consistent(tr)
    d = tr["depth"]
    assert d.max() == pytest.approx(1.4)
    assert int(np.sum(np.isclose(d, 1.4))) == 3
    peaks = np.nonzero((d[1:-1] > d[:-2]) & (d[1:-1] >= d[2:]))[0] + 1
    assert len(peaks) == 3
    assert np.all(tr["contact_id"][peaks] == [0, 1, 2])
    assert np.all(tr["indenter_id"] == ALL_INDENTERS.index("calib_prism"))
    for c in range(3):
        m = tr["contact_id"] == c
        dc, load = d[m], tr["loading"][m]
        assert np.all(np.diff(dc[load]) > 0) and np.all(np.diff(dc[~load]) < 0)
        assert dc[-1] == 0.0 and dc[load][-1] == pytest.approx(1.4)
    np.testing.assert_array_equal(tr["phase"], np.where(tr["loading"], 0, 3))
    np.testing.assert_allclose(tr["normalised_depth"].max(), 1.0)


@pytest.mark.parametrize("make,kwargs,message", [
    (sim_grid_trajectory, {"indenters": ["sphere", "spere"]}, "unknown indenter 'spere' (known: cone, "),
    (sim_grid_trajectory, {"indenters": []}, "the trajectory names no indenters"),
    (sim_grid_trajectory, {"depths_mm": []}, "depths_mm must be a non-empty list of depths > 0 mm, got []"),
    (sim_grid_trajectory, {"depths_mm": [0.3, -0.1]}, "depths_mm must be a non-empty list of depths > 0 mm"),
    (collection_trajectory, {"indenters": ["nosuch"]}, "unknown indenter 'nosuch'"),
    (collection_trajectory, {"rate_hz": 0}, "rate_hz, speed_mm_s, n_paired must be positive"),
])
def test_unusable_values_are_the_users_one_line_errors(make, kwargs, message):
    """A param of the right type that names nothing usable is bad input (the engine prints it
    in one line, exit 2), not a crash of the node."""
    from stages.common import InputError
    with pytest.raises(InputError) as err:
        make(**kwargs)
    assert message in str(err.value) and err.value.user_error is True


def test_calibration_shear_leg():
    """With shear_mm the calibration shears at d_max, out along x and back, then along y, before
    it releases: what the sensor's shear-to-normal ratio is read from."""
    tr = calibration_trajectory(n_steps=5, repetitions=2, shear_mm=1.0, shear_steps=4)
    _frame_fields_consistent(tr)
    one = tr["contact_id"] == 0
    phase, shift, depth = tr["phase"][one], tr["shift"][one], tr["depth"][one]
    assert phase.tolist() == [0] * 5 + ([1] * 4 + [2] * 4) * 2 + [3] * 5
    np.testing.assert_allclose(shift[5:13, 0], [0.25, 0.5, 0.75, 1.0, 0.75, 0.5, 0.25, 0.0])
    np.testing.assert_allclose(shift[13:21, 1], [0.25, 0.5, 0.75, 1.0, 0.75, 0.5, 0.25, 0.0])
    assert np.all(shift[13:21, 0] == 0) and np.all(shift[5:13, 1] == 0)
    assert np.all(depth[4:21] == pytest.approx(1.4)) and depth[-1] == 0.0
    assert tr["loading"][one].tolist() == (phase != 3).tolist()
    np.testing.assert_array_equal(tr["phase"][~one], phase)
    plain = calibration_trajectory(n_steps=5, repetitions=2)
    assert plain["depth"].size == 20 and not plain["shift"].any()
