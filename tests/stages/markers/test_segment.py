"""Marker segmentation: accuracy on realistic frames of both polarities, the scores, errors."""
import numpy as np
import pytest

from marker_looks import gelsight_frame, tactip_frame
from stages.markers.patterns import gelsight_pattern, tactip_pattern
from stages.markers.segment import centroid_error, coarse_markers, iou, segment

LOOKS = {"gelsight": (gelsight_frame, "dark", 56), "tactip": (tactip_frame, "bright", 127)}


@pytest.mark.parametrize("look", LOOKS)
def test_segment_matches_truth(look):
    make, polarity, _ = LOOKS[look]
    for seed in range(3):
        raw, truth = make(seed)
        pred = segment(raw, polarity=polarity)
        assert pred.dtype == np.uint8 and set(np.unique(pred)) == {0, 255}
        assert iou(pred, truth) >= 0.9, (look, seed)
        assert centroid_error(pred, truth) < 1.0, (look, seed)


@pytest.mark.parametrize("look", LOOKS)
def test_coarse_stage_finds_every_marker(look):
    make, polarity, count = LOOKS[look]
    raw, _ = make(5)
    coarse = coarse_markers(raw, polarity=polarity)
    assert len(coarse.centroids) == count
    assert coarse.boxes.shape == (count, 4)


def test_wrong_polarity_finds_no_gelsight_markers():
    """Bright blobs on a GelSight frame are only background highlights, not markers."""
    raw, truth = gelsight_frame(0)
    assert iou(segment(raw, polarity="bright"), truth) < 0.2


@pytest.mark.parametrize("look", LOOKS)
def test_grabcut_option(look):
    make, polarity, _ = LOOKS[look]
    raw, truth = make(1)
    pred = segment(raw, polarity=polarity, method="grabcut")
    assert iou(pred, truth) >= 0.85
    assert centroid_error(pred, truth) < 1.0


def test_gray_input_and_linear_gamma():
    raw, truth = tactip_frame(2)
    assert iou(segment(raw[..., 0], polarity="bright"), truth) >= 0.9
    # decoding a gamma-encoded frame as linear puts the edge too far out on bright pins
    assert iou(segment(raw, polarity="bright", gamma=1.0), truth) < iou(segment(raw, polarity="bright"), truth)


def test_blank_frame_has_no_markers():
    flat = np.full((64, 64, 3), 150, np.uint8)
    assert not segment(flat).any()


def test_iou_values():
    a = np.zeros((10, 10), np.uint8)
    b = np.zeros((10, 10), np.uint8)
    a[0:4, 0:5] = 255            # 20 px
    b[2:6, 0:5] = 1              # 20 px, 10 shared
    assert iou(a, b) == pytest.approx(10 / 30)
    assert iou(a, a) == 1.0
    assert iou(np.zeros((3, 3)), np.zeros((3, 3))) == 1.0
    with pytest.raises(ValueError, match="shapes differ"):
        iou(a, np.zeros((5, 5)))


def _disks(centres, shape=(40, 60), r=2):
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    img = np.zeros(shape, np.uint8)
    for cx, cy in centres:
        img[(xx - cx) ** 2 + (yy - cy) ** 2 <= r * r] = 255
    return img


def test_centroid_error_values():
    truth = _disks([(10, 10), (40, 20)])
    assert centroid_error(truth, truth) == 0.0
    assert centroid_error(_disks([(13, 14), (40, 20)]), truth) == pytest.approx(2.5)   # (5 + 0) / 2
    # a missed marker counts with the distance to the nearest predicted one
    assert centroid_error(_disks([(40, 20)]), truth) == pytest.approx(np.hypot(30, 10) / 2)
    # spurious predictions do not count
    assert centroid_error(_disks([(10, 10), (40, 20), (55, 35)]), truth) == 0.0
    # nothing predicted: every marker scores the cap (default: the image diagonal)
    assert centroid_error(np.zeros_like(truth), truth) == pytest.approx(np.hypot(40, 60))
    assert centroid_error(np.zeros_like(truth), truth, max_px=7.0) == 7.0
    assert centroid_error(truth, np.zeros_like(truth)) == 0.0


def test_bad_arguments():
    raw, _ = gelsight_frame(0)
    with pytest.raises(ValueError, match="polarity must be one of"):
        segment(raw, polarity="white")
    with pytest.raises(ValueError, match="method must be one of"):
        segment(raw, method="sam")
    with pytest.raises(ValueError, match="must be uint8, got float64"):
        segment(raw.astype(float))
    with pytest.raises(ValueError, match=r"\(H,W\) or \(H,W,3\)"):
        segment(raw[..., :2])


def test_rendered_frames():
    """A Mitsuba render of a pressed and sheared pad, both camera looks."""
    pytest.importorskip("mitsuba")
    render = pytest.importorskip("stages.markers.render")
    n = 33
    grid = (np.arange(n) - (n - 1) / 2)
    for look, markers, light, polarity in (
            ("gelsight", gelsight_pattern("A-II"), [[0.95, 0.25, 0.2], [0.25, 0.9, 0.3], [0.2, 0.35, 0.95]], "dark"),
            ("tactip", tactip_pattern(), None, "bright")):
        pad = markers.pad_size_mm[0]
        gx = gy = grid * pad / (n - 1)
        r2 = gx[None, :] ** 2 + gy[:, None] ** 2
        bump = np.exp(-r2 / (2 * (0.15 * pad) ** 2))
        disp = np.stack([0.6 * bump, 0.3 * bump, -0.8 * bump], -1)[None].astype(np.float32)
        out = render.render_frames(disp, gx, gy, np.zeros((n, n)), np.ones((n, n), bool), markers,
                                   look=look, size=(128, 128), spp=4, light=light, noise=3.0)
        pred = segment(out["raw"][0], polarity=polarity)
        assert iou(pred, out["truth"][0]) >= 0.9, look
        assert centroid_error(pred, out["truth"][0]) < 1.0, look
