"""Flow-warp: the training-free baseline for M2M translation.

For a source frame, the marker displacement field is estimated against the source's own
reference image, then the target's reference image is warped with it:

1. markers: connected-component centroids of the binary image and of the reference;
2. matching: each deformed centroid to its nearest reference centroid, kept when the pair is
   mutual nearest neighbours and closer than half the reference's marker pitch;
3. dense field: the sparse displacements (deformed minus reference position, placed at the
   DEFORMED position, i.e. an Eulerian field) spread by normalised Gaussian splatting
   (Nadaraya-Watson; sigma = one marker pitch), which is smooth, fills the gaps between
   markers and costs two blurs per frame; far from every marker it falls to zero;
4. warp: backward warp of the target reference, out(p) = ref(p - v(p)), with cv2.remap,
   re-binarised at half intensity.

Matching cannot follow a marker that moves more than half a pitch, and markers that merge
under a sharp indenter drop out of the match; both are the baseline's honest limits.  Source
and target are assumed to view the same pad area (image coordinates are normalised when
their sizes differ).  A source frame equal to its reference gives the target reference exactly.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def centroids(image: np.ndarray, min_area: int = 2) -> np.ndarray:
    """(M,2) float (x, y) px centroids of the white connected components of a binary image."""
    import cv2
    n, _, stats, cent = cv2.connectedComponentsWithStats((np.asarray(image) >= 128).astype(np.uint8), 8)
    keep = stats[1:, cv2.CC_STAT_AREA] >= min_area
    return cent[1:][keep].astype(np.float64)


def pitch(points: np.ndarray) -> float:
    """Median nearest-neighbour distance of a marker layout (px)."""
    from scipy.spatial import cKDTree
    if len(points) < 2:
        raise ValueError("need at least 2 markers to measure the marker pitch")
    d, _ = cKDTree(points).query(points, k=2)
    return float(np.median(d[:, 1]))


def match(deformed: np.ndarray, reference: np.ndarray, max_dist: float) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest-neighbour pairs closer than max_dist: (deformed idx, reference idx)."""
    from scipy.spatial import cKDTree
    if len(deformed) == 0 or len(reference) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    d, j = cKDTree(reference).query(deformed, distance_upper_bound=max_dist)
    ok = np.isfinite(d)
    i, j = np.flatnonzero(ok), j[ok]
    _, back = cKDTree(deformed).query(reference[j])
    mutual = back == i
    return i[mutual], j[mutual]


def splat(points: np.ndarray, vectors: np.ndarray, shape, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Normalised Gaussian splatting of sparse vectors: (field (H,W,2), weight (H,W))."""
    import cv2
    h, w = shape
    num = np.zeros((h, w, 2), np.float32)
    den = np.zeros((h, w), np.float32)
    if len(points):
        x, y = points[:, 0], points[:, 1]
        x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
        for dx in (0, 1):          # bilinear splat keeps sub-pixel positions
            for dy in (0, 1):
                wgt = (1 - np.abs(x - x0 - dx)) * (1 - np.abs(y - y0 - dy))
                xi, yi = x0 + dx, y0 + dy
                ok = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
                np.add.at(den, (yi[ok], xi[ok]), wgt[ok])
                np.add.at(num, (yi[ok], xi[ok]), wgt[ok, None] * vectors[ok])
    k = int(2 * np.ceil(3 * sigma) + 1)
    num = cv2.GaussianBlur(num, (k, k), sigma, borderType=cv2.BORDER_CONSTANT)
    den = cv2.GaussianBlur(den, (k, k), sigma, borderType=cv2.BORDER_CONSTANT)
    # a small floor pulls the field to zero where no marker is within a few sigma
    floor = 1e-2 / (2 * np.pi * sigma ** 2)
    return num / (den[..., None] + floor), den


@dataclass
class MarkerFlow:
    """Displacement fields of deformed frames against one reference image."""
    reference: np.ndarray

    def __post_init__(self):
        self.ref_points = centroids(self.reference)
        self.pitch = pitch(self.ref_points)

    def _matched(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pts = centroids(image)
        i, j = match(pts, self.ref_points, 0.5 * self.pitch)
        return pts[i], j

    def sparse(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Matched markers: (deformed positions (M,2), displacements (M,2)) in px."""
        pts, j = self._matched(image)
        return pts, pts - self.ref_points[j]

    def displacements(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Matched markers: (their indices into ref_points (M,), displacements (M,2)) in px."""
        pts, j = self._matched(image)
        return j, pts - self.ref_points[j]

    def field(self, image: np.ndarray, sigma: float | None = None) -> np.ndarray:
        """Dense Eulerian displacement field (H,W,2) px: v(p) = how far the material now at
        p has moved from its reference position."""
        pts, vec = self.sparse(image)
        return splat(pts, vec, image.shape, self.pitch if sigma is None else sigma)[0]


def motion_error(images, truth, reference, moving_px: float = 1.0) -> tuple[float, float, int]:
    """How well `images` keep a deformation that `truth` shows (both (N,H,W) marker images in
    the style of `reference`, paired row by row: the same contact).

    Over the reference's markers that move more than `moving_px` in the true frames: the mean
    |displacement in images - displacement in truth| in px (a marker that images lost counts
    as not moved), their mean true displacement, and how many markers that is.  The reference
    itself, which keeps none of the deformation, scores error == motion."""
    images, truth = np.asarray(images, np.uint8), np.asarray(truth, np.uint8)
    reference = np.asarray(reference, np.uint8)
    if images.shape != truth.shape or truth.shape[1:] != reference.shape:
        raise ValueError(f"motion_error: images {images.shape} and truth {truth.shape} must be (N,H,W) "
                         f"frames of the reference's size {reference.shape}")
    flow = MarkerFlow(reference)
    m = len(flow.ref_points)
    err = motion = 0.0
    count = 0
    for im, tr in zip(images, truth):
        jt, vt = flow.displacements(tr)
        keep = np.linalg.norm(vt, axis=1) > moving_px
        jt, vt = jt[keep], vt[keep]
        jo, vo = flow.displacements(im)
        got, have = np.zeros((m, 2)), np.zeros(m, bool)
        got[jo], have[jo] = vo, True
        size = np.linalg.norm(vt, axis=1)
        err += float(np.where(have[jt], np.linalg.norm(got[jt] - vt, axis=1), size).sum())
        motion += float(size.sum())
        count += len(jt)
    if not count:
        return float("nan"), float("nan"), 0
    return err / count, motion / count, count


def warp(image: np.ndarray, field: np.ndarray) -> np.ndarray:
    """Backward warp of a binary image by an Eulerian field (resampled to the image's size),
    re-binarised: out(p) = image(p - v(p))."""
    import cv2
    h, w = image.shape
    fh, fw = field.shape[:2]
    if (fh, fw) != (h, w):
        field = cv2.resize(field, (w, h), interpolation=cv2.INTER_LINEAR) * np.array([w / fw, h / fh], np.float32)
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    out = cv2.remap(np.ascontiguousarray(image, np.uint8), gx - field[..., 0], gy - field[..., 1],
                    cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return np.where(out >= 128, 255, 0).astype(np.uint8)


def flow_warp(images: np.ndarray, source_reference: np.ndarray, target_reference: np.ndarray) -> np.ndarray:
    """Source frames (N,H,W) -> target reference warped by each frame's marker flow, (N,H',W')."""
    flow = MarkerFlow(np.asarray(source_reference, np.uint8))
    target_reference = np.asarray(target_reference, np.uint8)
    return np.stack([warp(target_reference, flow.field(im)) for im in np.asarray(images, np.uint8)]) \
        if len(images) else np.zeros((0, *target_reference.shape), np.uint8)
