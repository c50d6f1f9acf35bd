"""Marker segmentation of camera-based tactile images into binary marker images.

Two stages, after the authors' pipeline (FACTS, "Segmentation"), with the box-prompted
segmenter replaced by its classical analogue:

coarse  the intensity I (luma by default, or HSV value = max of R, G, B) is lightly smoothed
        and compared with a wide Gaussian blur of itself, the local background: a pixel is a
        marker candidate when it differs from the background by more than `threshold` grey
        levels (darker for polarity "dark", brighter for "bright"), OR when its HSV value is
        extreme (dark: V < value_threshold; bright: V > 255 - value_threshold).  An opening
        removes specks; connected components with area in [min_area, max_area] are the markers.
fine    every marker's bounding box, grown by `box_margin`, is segmented on its own, on the
        unsmoothed intensity: method "otsu" (default) splits the box at Otsu's level, then
        re-thresholds it halfway (edge_level 0.5) between the background level and the marker
        level, each the mean of its class's core (the class eroded by a pixel, so half-covered
        rim pixels do not bias it), in linear light (camera values decoded with `gamma`, 2.2
        for sRGB-like cameras).  That puts the edge where a pixel is half covered, as the
        ground-truth rasterisation does; Otsu alone, or class-mean midpoints of gamma-encoded
        values, misplace the edge of markers only a few pixels across by a pixel.  Method
        "grabcut" runs OpenCV GrabCut seeded by that threshold.  Fine pixels count only within
        `box_margin` of the coarse mask, so a box never picks up noise far from a marker.

Both polarities: GelSight (dark markers on a bright, coloured, shaded gel) and TacTip (bright
pins on a dark dome).  Sizes are in pixels; defaults of None scale with the image
(blur_sigma = min(H, W) / 32, max_area = H*W / 50) so one set of defaults works at 128x128
and at 640x480.

`iou` and `centroid_error` score a segmentation against the ground-truth mask.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.common import check_option

POLARITIES = ("dark", "bright")
METHODS = ("otsu", "grabcut")
CHANNELS = ("value", "gray")
_CROSS = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8)


def _channels(raw: np.ndarray, channel: str) -> tuple[np.ndarray, np.ndarray]:
    """(intensity the segmentation works on, HSV value) of a uint8 frame, both (H,W) uint8."""
    img = np.asarray(raw)
    if img.dtype != np.uint8:
        raise ValueError(f"segment: raw image must be uint8, got {img.dtype}")
    if img.ndim == 2:
        return img, img
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"segment: raw image must be (H,W) or (H,W,3), got shape {img.shape}")
    value = np.maximum(np.maximum(img[..., 0], img[..., 1]), img[..., 2])   # HSV V, fast
    if channel == "value":
        return value, value
    import cv2
    return cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY), value


def _disk(size: int) -> np.ndarray:
    import cv2
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))


def _box_marker(patch: np.ndarray, linear: np.ndarray, polarity: str, edge_level: float,
                iterations: int, gamma: float) -> np.ndarray:
    """Marker pixels (uint8 0/1) of one box: Otsu's split, then `iterations` times re-thresholded
    at background + edge_level * (marker - background) in linear light (`linear`, the patch
    decoded with `gamma`), where the marker level is the mean of its class's core (the class
    eroded by one pixel, so half-covered rim pixels do not dilute it) and the background level
    the mean of the other class's core."""
    import cv2
    kind = cv2.THRESH_BINARY_INV if polarity == "dark" else cv2.THRESH_BINARY
    _, marker = cv2.threshold(patch, 0, 1, kind + cv2.THRESH_OTSU)
    for _ in range(iterations):
        n = cv2.countNonZero(marker)
        if n == 0 or n == marker.size:
            break
        core, rest = cv2.erode(marker, _CROSS), cv2.erode(1 - marker, _CROSS)
        level = cv2.mean(linear, core if cv2.countNonZero(core) else marker)[0]
        back = cv2.mean(linear, rest if cv2.countNonZero(rest) else 1 - marker)[0]
        edge = max(back + edge_level * (level - back), 0.0)
        _, marker = cv2.threshold(patch, 255.0 * edge ** (1.0 / gamma), 1, kind)
    return marker


def _grabcut(image: np.ndarray, seed: np.ndarray, iterations: int) -> np.ndarray:
    """GrabCut in one box, seeded by the threshold result: its core is certain marker, the
    rest of it probable marker, and the box border outside it certain background."""
    import cv2
    if not seed.any():
        return seed
    mask = np.where(seed, cv2.GC_PR_FGD, cv2.GC_PR_BGD).astype(np.uint8)
    mask[cv2.erode(seed.view(np.uint8), _CROSS).view(bool)] = cv2.GC_FGD
    border = np.ones_like(seed)
    border[1:-1, 1:-1] = False
    mask[border & ~seed] = cv2.GC_BGD
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    try:
        cv2.grabCut(image, mask, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:          # too few samples in a tiny box to fit its colour models
        return seed
    return (mask == cv2.GC_FGD) | (mask == cv2.GC_PR_FGD)


@dataclass(frozen=True)
class Coarse:
    """The coarse stage's result: the intensity it worked on (H,W) uint8, the kept markers'
    mask (H,W) uint8 0/1, their boxes (M,4) x, y, w, h, areas (M,) px and centroids (M,2) x, y."""
    intensity: np.ndarray
    mask: np.ndarray
    boxes: np.ndarray
    areas: np.ndarray
    centroids: np.ndarray


def coarse_markers(raw: np.ndarray, *, polarity: str = "dark", channel: str = "gray",
                   smooth_sigma: float = 0.7, blur_sigma: float | None = None,
                   threshold: float = 20.0, value_threshold: float = 40.0, open_size: int = 2,
                   min_area: int = 3, max_area: int | None = None) -> Coarse:
    """Coarse stage: background-difference OR extreme-value candidates, opening, connected
    components kept by area (parameters as in `segment`)."""
    import cv2
    check_option("segmentation polarity", polarity, POLARITIES)
    check_option("segmentation channel", channel, CHANNELS)
    intensity, value = _channels(raw, channel)
    h, w = intensity.shape
    sigma = float(blur_sigma) if blur_sigma is not None else min(h, w) / 32.0
    top = float(max_area) if max_area is not None else h * w / 50.0
    img = intensity.astype(np.float32)
    smooth = cv2.GaussianBlur(img, (0, 0), smooth_sigma) if smooth_sigma > 0 else img
    background = cv2.GaussianBlur(img, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    if polarity == "dark":
        mask = (background - smooth > threshold) | (value < value_threshold)
    else:
        mask = (smooth - background > threshold) | (value > 255 - value_threshold)
    mask = mask.view(np.uint8)
    if open_size > 1:
        mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, _disk(int(open_size)))
    _, labels, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
    area = stats[:, cv2.CC_STAT_AREA]
    keep = (area >= min_area) & (area <= top)
    keep[0] = False                                   # the background component
    return Coarse(intensity, keep.view(np.uint8)[labels], stats[keep, :4], area[keep],
                  centroids[keep])


def segment(raw: np.ndarray, *, polarity: str = "dark", method: str = "otsu",
            channel: str = "gray", smooth_sigma: float = 0.7, blur_sigma: float | None = None,
            threshold: float = 20.0, value_threshold: float = 40.0, open_size: int = 2,
            min_area: int = 3, max_area: int | None = None, box_margin: int = 3,
            edge_level: float = 0.5, gamma: float = 2.2, refine_iterations: int = 2,
            grabcut_iterations: int = 3) -> np.ndarray:
    """Binary marker image (H,W) uint8, 255 = marker, of one raw camera frame.

    raw: (H,W,3) RGB or (H,W) uint8.  polarity: "dark" (GelSight) or "bright" (TacTip).
    method: "otsu" or "grabcut" (see the module docstring).  channel: the intensity worked on,
    "gray" (luma; it saturates later than V on brightly lit gels) or "value" (HSV V).
    Coarse stage: smooth_sigma, px, pre-smoothing against pixel noise; blur_sigma, px, the
    background blur (None: min(H,W)/32); threshold, grey levels a marker differs from the
    background by; value_threshold, the absolute HSV-value test's margin from black / white
    (0 turns it off); open_size, px, the opening's kernel (<= 1 off); min_area / max_area, px,
    the marker area range (max None: H*W/50).  Fine stage: box_margin, px added around each
    marker's box; edge_level, where the edge lies between background (0) and marker (1) levels
    in linear light (0.5 = half coverage); gamma, the camera's encoding gamma, which decodes
    intensities to linear light (1 for linear images); refine_iterations of that threshold;
    grabcut_iterations.
    """
    import cv2
    check_option("segmentation method", method, METHODS)
    coarse = coarse_markers(raw, polarity=polarity, channel=channel, smooth_sigma=smooth_sigma,
                            blur_sigma=blur_sigma, threshold=threshold,
                            value_threshold=value_threshold, open_size=open_size,
                            min_area=min_area, max_area=max_area)
    intensity = coarse.intensity
    h, w = intensity.shape
    out = np.zeros((h, w), np.uint8)
    linear = ((np.arange(256) / 255.0) ** float(gamma)).astype(np.float32)[intensity]
    m = int(box_margin)
    near = (cv2.dilate(coarse.mask, _disk(2 * m + 1)) if m > 0 else coarse.mask).view(bool)
    if method == "grabcut":
        img = np.asarray(raw)
        colour = np.ascontiguousarray(img[..., ::-1] if img.ndim == 3 else np.dstack([img] * 3))
    for x, y, bw, bh in coarse.boxes:
        x0, y0, x1, y1 = max(x - m, 0), max(y - m, 0), min(x + bw + m, w), min(y + bh + m, h)
        fine = _box_marker(intensity[y0:y1, x0:x1], linear[y0:y1, x0:x1], polarity, edge_level,
                           int(refine_iterations), float(gamma)).view(bool)
        if method == "grabcut":
            fine = _grabcut(colour[y0:y1, x0:x1], fine, int(grabcut_iterations))
        out[y0:y1, x0:x1][fine & near[y0:y1, x0:x1]] = 255
    return out


def iou(pred: np.ndarray, truth: np.ndarray) -> float:
    """Intersection over union of the marker pixels (> 0) of two masks; 1 when both are empty."""
    p, t = np.asarray(pred) > 0, np.asarray(truth) > 0
    if p.shape != t.shape:
        raise ValueError(f"iou: shapes differ, {p.shape} vs {t.shape}")
    union = np.count_nonzero(p | t)
    return 1.0 if union == 0 else np.count_nonzero(p & t) / union


def _centroids(mask: np.ndarray) -> np.ndarray:
    import cv2
    n, _, _, c = cv2.connectedComponentsWithStats((np.asarray(mask) > 0).astype(np.uint8),
                                                  connectivity=8)
    return c[1:]


def centroid_error(pred: np.ndarray, truth: np.ndarray, *, max_px: float | None = None) -> float:
    """Mean distance, px, from each ground-truth marker centroid to the nearest predicted one.

    Markers are 8-connected components.  Each truth marker is matched to its nearest
    predicted centroid independently, so a missed marker counts with the distance to the
    nearest other predicted marker (about a marker pitch), and spurious predictions do not
    count (IoU penalises those).  Distances are capped at max_px (None: the image diagonal),
    which is also what every truth marker scores when nothing is predicted.  0 when the truth
    has no marker.
    """
    t, p = _centroids(truth), _centroids(pred)
    cap = float(max_px) if max_px is not None else float(np.hypot(*np.shape(truth)[:2]))
    if len(t) == 0:
        return 0.0
    if len(p) == 0:
        return cap
    d = np.sqrt(((t[:, None, :] - p[None, :, :]) ** 2).sum(-1)).min(1)
    return float(np.minimum(d, cap).mean())
