"""uSkin (XELA uSPa44): simulated raw taxel signals and their marker-image representation.

The sensor is a 4x4 grid of 3-axis magnetic taxels under a 24.6 x 22.6 x 5 mm cover.  Taxels
are numbered row-major, row = y (y grows downwards in images, as in patterns.py), so taxel
k = 4 * row + col sits at the centre of cell (row, col) of the pad split 4 x 4.

Raw signal model (`taxel_signals`): each taxel reads the displacement of the pad surface
averaged over its cell (or Gaussian-weighted around its centre), converted to counts around
the XELA mid-scale 32768:
    x = 32768 + offset_x + gain_x * u_x,   y = 32768 + offset_y + gain_y * u_y,
    z = 32768 + offset_z + gain_z * (-u_z)      (u_z < 0 presses into the pad)
so pressing raises z and a surface moving +x raises x, plus Gaussian noise, rounded and
clipped to uint16.  Default gains (GAINS, counts/mm): 10000 laterally, 8000 normally, so a
uniform 1 mm press reads 8000 counts and a 0.1 mm slide 1000.  On the twin's collection
protocol (1 mm presses, 1 mm shears; ci profile) the cell-mean lateral displacement peaks at
0.34 mm and the indentation at 0.2 mm, i.e. about 3400 and 1600 counts: well inside uint16,
and with s_xy = 4000 counts per grid unit (inside the FACTS range 1500..20000) the strongest
shear just reaches the 0.8 grid-unit clip.

Signal-to-marker (`signal_to_marker`, FACTS): every taxel is a white elliptical dot on a black
canvas spanning the pad; the dot starts at its cell centre and moves
    clip((raw_xy - baseline_xy) / s_xy, -max_offset, max_offset)  grid units
(one grid unit = one taxel pitch, pad / 4 along each axis; +x right, +y down), and its area is
    clip(base_area + (raw_z - baseline_z) / s_z, min_area, max_area)   mm^2 on the pad,
so pressing (z above baseline) grows the dot.  min_area defaults to base_area: pulling never
shrinks a dot.  A z-only skin sets it below base_area, so that a taxel the pad lifts away
(z below baseline) shrinks its dot: under shear the pad sinks behind the contact and rises
before it, and that signed pattern is all a z-only skin knows of the shear.
Areas are in mm^2 of pad surface, so an image is the same at any output size; a dot is a
circle in mm, drawn with the pad-to-pixel scale of each axis (as patterns.rasterize does), and
base_area = BASE_AREA = pi (0.2 * 22.6 / 4)^2 = 4.01 mm^2 reproduces the `uskin` reference
pattern exactly.  The skin's s_xy and s_z (params.yaml) are set so that no training frame
reaches the offset or the area clip: a clipped dot no longer tells its force.

Captured frames (stages.capture.xela parses the XELA server's messages) enter the same path.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from stages.common import LABEL_KEYS, check_option
from stages.markers.patterns import USKIN_PAD_MM, MarkerSet, rasterize

TAXELS = (4, 4)                      # rows (y), cols (x)
MID_SCALE = 32768                    # XELA raw reading at rest
GAINS = (10000.0, 10000.0, 8000.0)   # counts per mm of surface displacement (x, y, -z)
VARIANTS = ("3axis", "z")
CHUNK = 256                          # frames per streamed chunk
BASE_AREA = float(np.pi * (0.2 * min(USKIN_PAD_MM) / 4) ** 2)   # mm^2, the `uskin` pattern's dots


def taxel_centres(pad_mm=USKIN_PAD_MM) -> np.ndarray:
    """(16, 2) mm centres of the taxel cells, row-major (row = y), origin at the pad centre."""
    w, h = (float(v) for v in pad_mm)
    rows, cols = TAXELS
    xs = (np.arange(cols) - (cols - 1) / 2) * w / cols
    ys = (np.arange(rows) - (rows - 1) / 2) * h / rows
    return np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)


def taxel_weights(grid_x, grid_y, *, pad_mm=USKIN_PAD_MM, sigma_mm: float = 0.0) -> np.ndarray:
    """(16, h*w) weights, rows summing to 1, that average the surface grid into taxel readings.

    sigma_mm = 0: the plain mean over the taxel's cell (grid points on the cell's lower edge
    belong to it, on its upper edge to the next); sigma_mm > 0: a Gaussian of that width around
    the cell centre, over the whole pad (the cover spreads a press to neighbouring taxels).
    """
    gx, gy = np.asarray(grid_x, float), np.asarray(grid_y, float)
    w, h = (float(v) for v in pad_mm)
    rows, cols = TAXELS
    px, py = np.meshgrid(gx, gy)                              # (h, w) each
    inside = (np.abs(px) <= w / 2) & (np.abs(py) <= h / 2)
    if sigma_mm > 0:
        c = taxel_centres(pad_mm)
        d2 = (px.ravel()[None] - c[:, :1]) ** 2 + (py.ravel()[None] - c[:, 1:]) ** 2
        weights = np.exp(-d2 / (2 * sigma_mm ** 2)) * inside.ravel()[None]
    else:
        col = np.clip(np.floor((px + w / 2) / (w / cols)), 0, cols - 1).astype(int)
        row = np.clip(np.floor((py + h / 2) / (h / rows)), 0, rows - 1).astype(int)
        cell = np.where(inside, row * cols + col, -1).ravel()
        weights = (cell[None, :] == np.arange(rows * cols)[:, None]).astype(float)
    total = weights.sum(1, keepdims=True)
    if np.any(total == 0):
        raise ValueError(f"taxel_weights: the grid ({gx.size}x{gy.size} points) leaves a taxel "
                         f"cell of the {w}x{h} mm pad empty; use a finer grid or sigma_mm > 0")
    return weights / total


def taxel_signals(displacement, grid_x, grid_y, *, pad_mm=USKIN_PAD_MM, gains=GAINS,
                  noise: float = 5.0, seed=0, variant: str = "3axis", sigma_mm: float = 0.0,
                  offset=None) -> np.ndarray:
    """Raw counts (N, 16, 3) int32 of the taxels for surface displacements (N, h, w, 3) mm.

    grid_x (w,), grid_y (h,): the displacement grid's coordinates, mm, pad centre at 0.
    gains: counts per mm (x, y, z; z counts indentation -u_z).  noise: Gaussian noise std,
    counts, drawn from numpy's default_rng(seed) (seed an int or a sequence of ints).
    variant "3axis", or "z": x and y carry no signal (baseline + noise only).  sigma_mm: see
    taxel_weights.  offset: (16, 3) per-taxel rest offsets, counts (default none).
    """
    if variant not in VARIANTS:
        raise ValueError(f"taxel_signals: variant must be one of {VARIANTS}, got {variant!r}")
    disp = np.asarray(displacement, np.float64)
    if disp.ndim != 4 or disp.shape[-1] != 3:
        raise ValueError(f"taxel_signals: displacement must be (N,h,w,3), got {disp.shape}")
    n, h, w, _ = disp.shape
    if (len(grid_y), len(grid_x)) != (h, w):
        raise ValueError(f"taxel_signals: grid ({len(grid_y)}, {len(grid_x)}) does not match the "
                         f"displacement grid ({h}, {w})")
    weights = taxel_weights(grid_x, grid_y, pad_mm=pad_mm, sigma_mm=sigma_mm)
    mean = np.einsum("tp,npc->ntc", weights, disp.reshape(n, h * w, 3))
    mean[..., 2] *= -1.0                                      # indentation, positive pressing
    signal = mean * np.asarray(gains, float)
    if variant == "z":
        signal[..., :2] = 0.0
    rest = MID_SCALE + (np.zeros((16, 3)) if offset is None else np.asarray(offset, float))
    raw = rest + signal + np.random.default_rng(seed).normal(0.0, float(noise), signal.shape)
    return np.clip(np.rint(raw), 0, 65535).astype(np.int32)


def _dots(raw, baseline, *, pad_mm, s_xy, s_z, base_area, max_area, max_offset, z_only,
          min_area=None):
    """(N, 16, 2) dot centres, mm, and (N, 16) dot areas, mm^2."""
    delta = np.asarray(raw, float) - np.asarray(baseline, float)
    rows, cols = TAXELS
    pitch = np.array([pad_mm[0] / cols, pad_mm[1] / rows])
    offset = np.clip(delta[..., :2] / float(s_xy), -max_offset, max_offset)
    if z_only:
        offset = np.zeros_like(offset)
    centres = taxel_centres(pad_mm) + offset * pitch
    low = base_area if min_area is None else min_area
    area = np.clip(base_area + delta[..., 2] / float(s_z), low, max_area)
    return centres, area


def signal_to_marker(raw, baseline, *, size=(128, 128), pad_mm=USKIN_PAD_MM, s_xy: float = 4000.0,
                     s_z: float = 150.0, base_area: float = BASE_AREA, max_area: float = 16.0,
                     max_offset: float = 0.8, z_only: bool = False,
                     min_area: float | None = None, supersample: int = 4) -> np.ndarray:
    """Marker images (N, H, W) uint8 0/255 of raw taxel counts (N, 16, 3) (or one (16, 3)
    reading -> (H, W)), relative to the rest reading `baseline` (16, 3).

    s_xy: counts per grid unit of dot motion; s_z: counts per mm^2 of dot area; base_area: the
    dot area at rest, min_area (default base_area) .. max_area its range, mm^2 on the pad;
    max_offset: grid units; z_only: dots stay at their cell centres (z-only uSkin).  See the
    module docstring for the conventions.
    """
    data = np.asarray(raw)
    single = data.ndim == 2
    data = data[None] if single else data
    if data.shape[1:] != (16, 3) or np.shape(baseline) != (16, 3):
        raise ValueError(f"signal_to_marker: raw must be (N,16,3) and baseline (16,3), got "
                         f"{np.shape(raw)} and {np.shape(baseline)}")
    if not 0 < base_area <= max_area:
        raise ValueError(f"signal_to_marker: need 0 < base_area <= max_area, got {base_area}, {max_area}")
    if min_area is not None and not 0 < min_area <= base_area:
        raise ValueError(f"signal_to_marker: need 0 < min_area <= base_area, got {min_area}, {base_area}")
    pad = tuple(float(v) for v in pad_mm)
    centres, area = _dots(data, baseline, pad_mm=pad, s_xy=s_xy, s_z=s_z, base_area=base_area,
                          max_area=max_area, max_offset=max_offset, z_only=z_only,
                          min_area=min_area)
    out = _draw(centres, area, size=size, pad_mm=pad, supersample=supersample)
    return out[0] if single else out


def _draw(centres, area, *, size, pad_mm, supersample: int = 4) -> np.ndarray:
    """(N, H, W) uint8 0/255 images of round dots at centres (N, 16, 2) mm with areas (N, 16) mm^2."""
    h, w = (int(v) for v in size)
    out = np.empty((len(centres), h, w), np.uint8)
    for i, (c, a) in enumerate(zip(centres, area)):
        r = np.sqrt(a / np.pi)[:, None]
        out[i] = rasterize(MarkerSet(c, np.hstack([r, r]), 0.0, tuple(pad_mm)), size=(h, w),
                           supersample=supersample)
    return out


def _spec_float(spec: Mapping, key: str, default: float) -> float:
    return float(spec.get(key, default))


def taxel_sequence(*, deform: Mapping, skin: str, spec: Mapping):
    """Node `taxels[skin]`: raw uSkin counts along a deform[sensor=uskin] contact sequence.

    Yields chunks of `signals` (n, 16, 3) int32 and the label keys (copied); returns
    `baseline` (16, 3) int32, the noiseless rest reading, and attrs.  spec keys (all optional
    but `variant`): variant ("3axis" or "z"), gains ([x, y, z] counts/mm, default GAINS),
    noise (counts std, 5), seed (0), sigma_mm (0 = cell mean), offset_std (per-taxel rest
    offsets' std, counts, 0), pad_mm (default: the deform artifact's, else 24.6 x 22.6).
    Noise is drawn per chunk of CHUNK frames from seed and the chunk's first frame, so the
    signals do not depend on how the node is run.
    """
    from tqdm import tqdm
    variant = spec.get("variant", "3axis")
    check_option(f"sensors.{skin}.variant", variant, VARIANTS)
    attrs = getattr(deform, "attrs", {}) or {}
    pad = tuple(float(v) for v in spec.get("pad_mm", attrs.get("pad_mm", USKIN_PAD_MM)))
    gains = [float(g) for g in spec.get("gains", GAINS)]
    noise, seed = _spec_float(spec, "noise", 5.0), int(spec.get("seed", 0))
    sigma, offset_std = _spec_float(spec, "sigma_mm", 0.0), _spec_float(spec, "offset_std", 0.0)
    offset = np.random.default_rng([seed, 1]).normal(0.0, offset_std, (16, 3))
    grid_x, grid_y = np.asarray(deform["grid_x"]), np.asarray(deform["grid_y"])
    n = len(deform["displacement"])
    labels = [k for k in LABEL_KEYS if k in deform]
    for start in tqdm(range(0, n, CHUNK), desc=f"taxels[{skin}]", unit="chunk", disable=None,
                      leave=False):
        stop = min(start + CHUNK, n)
        signals = taxel_signals(deform["displacement"][start:stop], grid_x, grid_y, pad_mm=pad,
                                gains=gains, noise=noise, seed=[seed, 0, start], variant=variant,
                                sigma_mm=sigma, offset=offset)
        yield {"signals": signals, **{k: np.asarray(deform[k][start:stop]) for k in labels}}
    baseline = np.clip(np.rint(MID_SCALE + offset), 0, 65535).astype(np.int32)
    out = {"baseline": baseline,
           "attrs": {"skin": skin, "variant": variant, "gains": gains, "noise": noise, "seed": seed,
                     "sigma_mm": sigma, "offset_std": offset_std, "pad_mm": list(pad),
                     "frames": int(n)}}
    if "indenters" in deform:
        out["indenters"] = np.asarray(deform["indenters"]).astype(str)
    return out
