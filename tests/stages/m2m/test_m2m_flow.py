"""The flow-warp baseline: identity, and that it carries the source's marker motion over."""
import numpy as np
import pytest
from m2m_synthetic import SIZE, marker_artifact, mean_motion_error

from stages.m2m.flow import MarkerFlow, centroids, flow_warp, match, motion_error, pitch, splat, warp


def test_identity_returns_the_target_reference(skins):
    a, b = skins["Array3"], skins["Circle3"]
    out = flow_warp(np.stack([a["reference"]] * 2), a["reference"], b["reference"])
    assert out.shape == (2, SIZE, SIZE) and out.dtype == np.uint8
    np.testing.assert_array_equal(out[0], b["reference"])
    np.testing.assert_array_equal(out[1], b["reference"])


def test_warped_markers_follow_the_source_motion(skins):
    """Flow-warp is checked (rather than a tiny trained model) because its accuracy is a
    property of the method, not of a training budget: the target's markers must move by the
    true synthetic field.  Centroids of 3-px rasterised markers are themselves only good to
    ~0.5 px, so the bound is set against the error measured on the true target images."""
    a, b = skins["Array3"], skins["Diamond3"]
    out = flow_warp(a["images"], a["reference"], b["reference"])
    err, motion = mean_motion_error(out, b["reference"], "Diamond3")
    floor, _ = mean_motion_error(b["images"], b["reference"], "Diamond3")
    assert motion > 1.5                       # moving markers travel 1.8 px on average
    assert err < 0.35 * motion                # 0.54 px
    assert err < floor + 0.1                  # the true images measure 0.56 px


def test_motion_error_of_the_truth_the_reference_and_flow_warp(skins):
    """motion_error measures against the target's own frames: they score 0, the undeformed
    reference scores the markers' mean motion (which agrees with the synthetic field's), and
    flow-warp, which carries the motion over, scores the error measured against that field."""
    a, b = skins["Array3"], skins["Diamond3"]
    truth, ref = b["images"], b["reference"]
    err, motion, n = motion_error(truth, truth, ref)
    assert err == 0.0 and n > 100
    _, true_motion = mean_motion_error(truth, ref, "Diamond3")
    assert motion == pytest.approx(true_motion, abs=0.15)          # 1.8 px on the moving markers
    still, motion_again, _ = motion_error(np.broadcast_to(ref, truth.shape), truth, ref)
    assert still == pytest.approx(motion) and motion_again == motion
    warped, _, _ = motion_error(flow_warp(a["images"], a["reference"], ref), truth, ref)
    assert 0.1 < warped < 0.5 * motion
    with pytest.raises(ValueError, match=r"motion_error: images \(48, 10, 64\) and truth \(48, 64, 64\)"):
        motion_error(truth[:, :10], truth, ref)


def test_centroids_pitch_and_match():
    img = np.zeros((20, 30), np.uint8)
    img[2:5, 3:6] = 255          # centre (4, 3)
    img[10:13, 20:23] = 255      # centre (21, 11)
    img[0, 29] = 255             # a 1-px speck is ignored
    c = centroids(img)
    np.testing.assert_allclose(c, [[4, 3], [21, 11]])
    assert pitch(c) == pytest.approx(np.hypot(17, 8))
    i, j = match(c + [[1.0, 0.0], [9.0, 0.0]], c, max_dist=2.0)
    assert i.tolist() == [0] and j.tolist() == [0]


def test_splat_reproduces_a_uniform_field_and_warp_shifts():
    pts = np.stack(np.meshgrid(np.arange(4, 60, 6.0), np.arange(4, 60, 6.0)), -1).reshape(-1, 2)
    field, weight = splat(pts, np.tile([1.5, -0.5], (len(pts), 1)), (128, 128), sigma=6.0)
    np.testing.assert_allclose(field[16:48, 16:48], np.broadcast_to([1.5, -0.5], (32, 32, 2)), atol=0.02)
    assert weight[30, 30] > 0.02 and weight[110, 110] < 1e-6
    assert abs(field[110, 110]).max() < 1e-3       # zero far from every marker
    img = np.zeros((64, 64), np.uint8)
    img[30:33, 30:33] = 255
    moved = warp(img, np.broadcast_to(np.float32([2.0, -1.0]), (64, 64, 2)).copy())
    np.testing.assert_allclose(centroids(moved)[0], [33.0, 30.0])
    # a field of another size is resampled and scaled to the image
    small = warp(img, np.broadcast_to(np.float32([1.0, -0.5]), (32, 32, 2)).copy())
    np.testing.assert_array_equal(small, moved)


def test_other_target_size():
    a = marker_artifact("Array3", n_frames=4)
    b = marker_artifact("Diamond3", n_frames=4, size=96)
    out = flow_warp(a["reference"][None], a["reference"], b["reference"])
    np.testing.assert_array_equal(out[0], b["reference"])
