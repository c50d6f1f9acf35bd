"""Synthetic marker artifacts for the M2M tests (a module of its own: `conftest` names clash
across test folders)."""
import numpy as np

from stages.markers.patterns import MarkerSet, pattern, rasterize

SIZE = 64
PAD = (20.0, 20.0)
INDENTERS = ["sphere", "wave"]        # id 0 trains, id 1 is held out
SKINS = {"Array3": 1.4, "Diamond3": 1.4, "Circle3": 1.3}   # pattern -> marker enlargement


def displacement(centers, c, amp, direction, sigma=4.0):
    """Shear bump of `amp` mm along `direction` plus an outward push of amp/2, at centre c."""
    d = centers - c
    g = np.exp(-(d ** 2).sum(1) / (2 * sigma ** 2))[:, None]
    radial = d / (np.linalg.norm(d, axis=1, keepdims=True) + 1.0)
    return g * (amp * direction + 0.5 * amp * radial)


def fields(n, seed=0):
    rng = np.random.default_rng(seed)
    ang = rng.uniform(0, 2 * np.pi, n)
    return [(rng.uniform(-5, 5, 2), rng.uniform(0.4, 1.2), np.array([np.cos(a), np.sin(a)])) for a in ang]


def marker_artifact(name, n_frames=48, size=SIZE, seed=0, scale=None):
    base = pattern(name, pad_size_mm=PAD)
    ms = MarkerSet(base.centers, base.axes * (SKINS.get(name, 2.2) if scale is None else scale), base.angles, PAD)
    images = np.stack([rasterize(MarkerSet(ms.centers + displacement(ms.centers, *f), ms.axes, ms.angles, PAD),
                                 size=(size, size)) for f in fields(n_frames, seed)])
    n = n_frames
    return {
        "images": images,
        "reference": rasterize(ms, size=(size, size)),
        "force": np.zeros((n, 3), np.float32),
        "depth": np.linspace(0, 1, n),
        "phase": np.zeros(n, np.int8),
        "contact_id": np.arange(n, dtype=np.int32),
        "indenter_id": (np.arange(n) % 2).astype(np.int16),
        "paired": np.ones(n, bool),
        "frame": np.arange(100, 100 + n, dtype=np.int64),
        "indenters": np.array(INDENTERS),
    }


def true_motion_px(name, frame_index, n_frames=48, size=SIZE, seed=0):
    """Reference marker centres and their true displacement in frame `frame_index`, in px
    (pixel i's centre at i, as cv2 centroids count)."""
    ms = pattern(name, pad_size_mm=PAD)
    f = fields(n_frames, seed)[frame_index]
    px_per_mm = size / PAD[0]
    return (ms.centers + PAD[0] / 2) * px_per_mm - 0.5, displacement(ms.centers, *f) * px_per_mm


def motion_error(out, reference, name, i, moving=1.0):
    """For the target markers that truly move more than `moving` px in frame i: mean
    |measured - true| displacement (px) of those markers in `out`, and their mean motion."""
    from stages.m2m.flow import MarkerFlow
    ref_px, true = true_motion_px(name, i)
    pts, vec = MarkerFlow(reference).sparse(out)
    # the reference marker each matched marker came from
    j = np.linalg.norm((pts - vec)[:, None] - ref_px[None], axis=-1).argmin(1)
    sel = np.linalg.norm(true[j], axis=1) > moving
    return np.linalg.norm(vec - true[j], axis=1)[sel].sum(), np.linalg.norm(true[j], axis=1)[sel].sum(), sel.sum()


def mean_motion_error(images, reference, name, frames=None):
    """Over frames (indices into the artifact, default 0..len(images)-1): mean error and mean
    true motion (px) of the target markers that move, as measured in `images`."""
    frames = range(len(images)) if frames is None else frames
    err, motion, n = np.sum([motion_error(im, reference, name, i) for im, i in zip(images, frames)], 0)
    return err / n, motion / n
