"""Marker patterns from image files: a CAD export, the authors' pattern images, or a no-contact
frame captured from the real sensor.

The image spans the sensor's pad (as the drawn patterns' rasters do: stages.markers.patterns),
whatever its size.  It is segmented as the looks' frames are (stages.markers.segment.segment:
background difference, per-marker threshold), markers white on black (`bright`, the default)
or dark on light (`dark`: a lit GelSight gel), and every connected marker becomes the ellipse
with the same centroid and second moments, in mm on the pad (a marker the image's border cuts to
less than half the typical size is left out).  So a pattern image is geometry
like a drawn pattern: the renderer deforms it, and `rasterize` redraws it at any size.
"""
from __future__ import annotations

import os

import numpy as np

from stages.common import InputError
from stages.markers.patterns import MarkerSet


def read_image(path: str) -> np.ndarray:
    """The image as (H,W) or (H,W,3) RGB uint8, or a one-line InputError naming the file."""
    import cv2
    if not os.path.isfile(path):
        raise InputError(f"pattern image {path}: no such file")
    img = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise InputError(f"pattern image {path}: unreadable (not a PNG or JPEG, or truncated)")
    if img.dtype != np.uint8:           # 16-bit PNGs: to 8 bits
        img = (img.astype(np.float64) * 255.0 / max(float(np.iinfo(img.dtype).max), 1.0)).round().astype(np.uint8)
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2RGB)
    return img


def markers_from_image(img: np.ndarray, *, pad_size_mm, polarity: str = "bright",
                       what: str = "pattern image", min_area: int = 3) -> MarkerSet:
    """The MarkerSet of an image of a pad: one ellipse per segmented marker, with the
    marker's centroid and second moments, the image spanning `pad_size_mm` (w, h)."""
    import cv2
    from stages.markers.segment import segment
    img = np.asarray(img)
    gray = img if img.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
    if int(gray.max()) - int(gray.min()) < 16:
        raise InputError(f"{what}: blank (grey levels {int(gray.min())}..{int(gray.max())}): no markers to see")
    mask = segment(img, polarity=polarity, min_area=min_area) > 0
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.view(np.uint8), connectivity=8)
    h, w = mask.shape
    pw, ph = (float(v) for v in pad_size_mm)
    sx, sy = pw / w, ph / h                               # mm per px along x and y
    centers, axes, angles = [], [], []
    x0, y0, bw, bh, area = (stats[1:, i] for i in range(5))
    edge = (x0 == 0) | (y0 == 0) | (x0 + bw == w) | (y0 + bh == h)
    typical = float(np.median(area)) if len(area) else 0.0
    for k in range(1, n):
        if area[k - 1] < min_area or (edge[k - 1] and area[k - 1] < 0.5 * typical):
            continue                     # noise, or a marker the image's border cuts
        ys, xs = np.nonzero(labels == k)
        x, y = (xs + 0.5) * sx - pw / 2, (ys + 0.5) * sy - ph / 2
        cx, cy = x.mean(), y.mean()
        # a filled ellipse of semi-axes a, b has second moments a^2/4, b^2/4 along its axes;
        # each pixel adds its own spread (1/12 px^2) to them
        cov = np.cov(np.stack([x, y]), bias=True) + np.diag([sx * sx, sy * sy]) / 12.0
        vals, vecs = np.linalg.eigh(cov)
        a, b = 2.0 * np.sqrt(np.maximum(vals[::-1], 1e-12))
        major = vecs[:, 1]
        centers.append((cx, cy))
        axes.append((a, b))
        angles.append(np.arctan2(major[1], major[0]))
    if not centers:
        raise InputError(f"{what}: no markers found ({'white on black' if polarity == 'bright' else 'dark on light'}; "
                         "set the sensor's pattern_polarity if they are the other way)")
    order = np.lexsort((np.asarray(centers)[:, 0], np.asarray(centers)[:, 1]))    # rows, then columns
    return MarkerSet(np.asarray(centers)[order], np.asarray(axes)[order], np.asarray(angles)[order],
                     (pw, ph))


def load_pattern(path: str, *, pad_size_mm, polarity: str = "bright") -> MarkerSet:
    """The MarkerSet of a pattern image file (see the module docstring)."""
    return markers_from_image(read_image(path), pad_size_mm=pad_size_mm, polarity=polarity,
                              what=f"pattern image {path}")
