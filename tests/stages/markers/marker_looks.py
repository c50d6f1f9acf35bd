"""Synthetic camera frames with known ground truth, for the segmentation tests.

GelSight look: a gel lit by coloured side lights (red from the left, green from below, blue
from the right) whose shading also follows the slope of a pressed bump, dark elliptical
markers, a slight optical blur, sRGB-like gamma 2.2 and Gaussian noise.  TacTip look: bright
pins, brighter at their centres, on a black dome with a faint glow, blur, gamma and noise.  Markers move with a smooth
deformation field (bulge + shear) and vary in size and eccentricity, so no frame is the
undeformed pattern.  Truth = the same ellipses rasterised at >= half coverage.
"""
from __future__ import annotations

import cv2
import numpy as np

GAMMA = 2.2

from stages.markers.patterns import (MarkerSet, gelsight_pattern, marker_texture, rasterize,
                                     tactip_pattern)


def _deformed(ms: MarkerSet, rng, *, bulge_mm, shear_mm, aspect=1.3) -> MarkerSet:
    """Markers moved by a Gaussian bulge around a random centre plus a uniform shear."""
    w, h = ms.pad_size_mm
    centre = rng.uniform(-0.25, 0.25, 2) * (w, h)
    d = ms.centers - centre
    r2 = (d ** 2).sum(1, keepdims=True)
    width = 0.2 * min(w, h)
    move = bulge_mm * d / width * np.exp(-r2 / (2 * width ** 2)) + rng.uniform(-1, 1, 2) * shear_mm
    grow = rng.uniform(1.0, aspect, (len(ms), 1))
    axes = ms.axes * np.hstack([grow, np.ones_like(grow)]) * rng.uniform(0.9, 1.2, (len(ms), 1))
    return MarkerSet(ms.centers + move, axes, rng.uniform(0, np.pi, len(ms)), ms.pad_size_mm)


def _finish(linear: np.ndarray, rng, noise: float, blur: float) -> np.ndarray:
    """Linear radiance in [0, 1] -> optical blur -> sRGB-like gamma 2.2 -> noise -> uint8."""
    img = cv2.GaussianBlur(linear.astype(np.float32), (0, 0), blur)
    img = 255.0 * np.clip(img, 0, 1) ** (1 / GAMMA) + rng.normal(0.0, noise, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def gelsight_frame(seed: int, size=(128, 128), *, noise=3.0, blur=0.5, supersample=8):
    """(raw (H,W,3) uint8, truth (H,W) 0/255) of a GelSight-look frame."""
    rng = np.random.default_rng(seed)
    ms = _deformed(gelsight_pattern("A-II"), rng, bulge_mm=0.6, shear_mm=0.5)
    cov = marker_texture(ms, size=size, supersample=supersample)[..., None]
    truth = rasterize(ms, size=size, supersample=supersample)
    h, w = size
    yy, xx = np.mgrid[0:h, 0:w] / np.array([h - 1, w - 1])[:, None, None]
    # slope of a pressed bump: the lights catch its flanks
    cx, cy = rng.uniform(0.3, 0.7, 2)
    bump = np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * 0.12 ** 2))
    gy, gx = np.gradient(bump)
    light = np.stack([0.1 + 0.6 * (1 - xx) - 4 * gx,         # red from the left
                      0.08 + 0.55 * yy + 4 * gy,             # green from below
                      0.1 + 0.5 * xx + 4 * gx], -1)          # blue from the right
    marker = np.array([0.03, 0.025, 0.035]) * rng.uniform(0.7, 1.3)
    raw = light * (1 - cov) + marker * cov
    return _finish(raw, rng, noise, blur), truth


def tactip_frame(seed: int, size=(128, 128), *, noise=4.0, blur=0.5, supersample=8):
    """(raw (H,W,3) uint8, truth (H,W) 0/255) of a TacTip-look frame."""
    rng = np.random.default_rng(seed)
    ms = _deformed(tactip_pattern(), rng, bulge_mm=1.2, shear_mm=0.8, aspect=1.2)
    h, w = size
    cov = marker_texture(ms, size=size, supersample=supersample)
    truth = rasterize(ms, size=size, supersample=supersample)
    # brightness inside each pin falls towards its rim (a lit rounded tip)
    centres = (ms.centers / np.asarray(ms.pad_size_mm) + 0.5) * (w, h)
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    near = np.full((h, w), np.inf)
    for cx, cy in centres:
        near = np.minimum(near, (xx - cx) ** 2 + (yy - cy) ** 2)
    radius_px = ms.axes.max() * w / ms.pad_size_mm[0]
    tip = 0.85 - 0.25 * np.clip(near / radius_px ** 2, 0, 1)
    r = np.hypot(xx / w - 0.5, yy / h - 0.5)
    dome = 0.002 + 0.02 * np.exp(-r ** 2 / 0.05) * (r < 0.5)
    raw = dome * (1 - cov) + tip * cov
    tint = np.array([1.0, 0.97, 0.92])
    return _finish(raw[..., None] * tint, rng, noise, blur), truth
