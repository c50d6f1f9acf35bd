"""Reference marker patterns: geometry first, pixels second.

Every pattern is a :class:`MarkerSet` of ellipses in millimetres on the skin's
undeformed surface (x right, y down, origin at the pad centre). Images are only
made by :func:`rasterize` / :func:`marker_texture`, so the same geometry can
later be used as a rendering texture or deformed point set.

The 12 simulation patterns reproduce the marker counts and marker areas the
authors' reference images have (FACTS: areas in px at a 568x568 rendering of
the pad). Layouts are built in pad-normalised units (pad half-width = 1) and
scaled uniformly by min(pad)/2, so a 568x568 rendering looks the same for any
square pad size. Where a regular lattice cannot hit the count exactly (e.g.
Diamond1 245, Diamond4 81), the outermost shell is partly filled with evenly
spaced markers, which is how the count is met exactly.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PATTERNS = ("Array1", "Array2", "Array3", "Array4",
            "Circle1", "Circle2", "Circle3", "Circle4",
            "Diamond1", "Diamond2", "Diamond3", "Diamond4")

# name -> (marker count, marker area in px at 568x568), from FACTS.
PATTERN_SPECS = {
    "Array1": (225, 114), "Array2": (100, 223), "Array3": (80, 362), "Array4": (99, 302),
    "Circle1": (320, 115), "Circle2": (115, 222), "Circle3": (111, 363), "Circle4": (124, 246),
    "Diamond1": (245, 115), "Diamond2": (103, 218), "Diamond3": (81, 365), "Diamond4": (81, 251),
}
REF_RENDER_PX = 568          # side of the reference rendering the areas refer to
CIRCLE4_ASPECT = 1.6         # major/minor axis ratio of Circle4's ellipses
CIRCLE4_TILT = np.pi / 4     # ellipse tilt relative to the radial direction

GELSIGHT_PAD_MM = (25.0, 25.0)
GELSIGHT_TWINS = ("A-I", "A-II", "C-I", "C-II", "D-I")
GELSIGHT_MARKER_R_MM = 0.35  # ~0.7 mm printed dots, typical of GelSight gels
TACTIP_DIAMETER_MM = 40.0
TACTIP_CURVATURE_MM = 41.5
TACTIP_PIN_R_MM = 0.75       # pin-tip radius as seen by the camera
USKIN_PAD_MM = (24.6, 22.6)


@dataclass(frozen=True)
class MarkerSet:
    """Elliptical markers; angles rotate the first semi-axis from +x towards +y."""
    centers: np.ndarray      # (M, 2) mm
    axes: np.ndarray         # (M, 2) semi-axes, mm
    angles: np.ndarray       # (M,) radians
    pad_size_mm: tuple       # (w, h)

    def __post_init__(self):
        c = np.asarray(self.centers, float).reshape(-1, 2)
        a = np.broadcast_to(np.asarray(self.axes, float), c.shape).copy()
        t = np.broadcast_to(np.asarray(self.angles, float), c.shape[:1]).copy()
        object.__setattr__(self, "centers", c)
        object.__setattr__(self, "axes", a)
        object.__setattr__(self, "angles", t)
        object.__setattr__(self, "pad_size_mm", tuple(float(v) for v in self.pad_size_mm))

    def __len__(self):
        return len(self.centers)

    def transformed(self, shift_mm=(0.0, 0.0), rot_rad=0.0) -> "MarkerSet":
        """Rigid motion about the pad centre (marker orientations rotate too)."""
        c, s = np.cos(rot_rad), np.sin(rot_rad)
        rot = np.array([[c, -s], [s, c]])
        return MarkerSet(self.centers @ rot.T + np.asarray(shift_mm, float),
                         self.axes, self.angles + rot_rad, self.pad_size_mm)


# ---------------------------------------------------------------- layouts
# All layout helpers return (N, 2) centres in pad-normalised units.

def _take_shells(pts, norm, n):
    """The n lattice points smallest in `norm` (the region's shape norm).
    A partly needed outer shell is filled nearest-to-centre first (edge middles
    before corners, keeping the outline convex); the last tied group contributes
    points evenly spaced by angle so the residue stays as symmetric as possible."""
    rad = np.round(np.hypot(pts[:, 0], pts[:, 1]), 9)
    key = np.round(norm, 9)
    order = np.lexsort((rad, key))
    pts, key, rad = pts[order], key[order], rad[order]
    groups = np.flatnonzero(np.r_[True, (key[1:] != key[:-1]) | (rad[1:] != rad[:-1])])
    bounds = np.r_[groups, len(pts)]
    if n > len(pts):
        raise ValueError(f"lattice too small for {n} points")
    g = np.searchsorted(bounds, n, side="right") - 1   # group holding the n-th point
    if bounds[g] == n:
        return pts[:n]
    grp = pts[bounds[g]:bounds[g + 1]]
    grp = grp[np.argsort(np.round(np.mod(np.arctan2(grp[:, 1], grp[:, 0]), 2 * np.pi), 9), kind="stable")]
    left = n - bounds[g]
    idx = np.floor((np.arange(left) + 0.5) * len(grp) / left).astype(int)
    return np.concatenate([pts[:bounds[g]], grp[idx]])


def _grid(cols, rows, half_w=0.85, half_h=0.85):
    xs = np.linspace(-half_w, half_w, cols)
    ys = np.linspace(-half_h, half_h, rows)
    return np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)


def _staggered(cols, rows, half=0.85):
    """Rows of `cols` markers; odd rows shifted by half a pitch (brick layout)."""
    px = 2 * half / (cols - 0.5)
    ys = np.linspace(-half, half, rows)
    pts = [(-half + (i + 0.5 * (r % 2)) * px, y) for r, y in enumerate(ys) for i in range(cols)]
    return np.array(pts)


def _ring_counts(n):
    """Centre marker + K rings, ring k holding ~c*k markers (equal arc spacing);
    K chosen so arc spacing ~ ring spacing, counts by largest remainder."""
    k_rings = max(1, int(round((-1 + np.sqrt(1 + 4 * (n - 1) / np.pi)) / 2)))
    ideal = (n - 1) * np.arange(1, k_rings + 1) / (k_rings * (k_rings + 1) / 2)
    counts = np.floor(ideal).astype(int)
    counts[np.argsort(-(ideal - counts), kind="stable")[: n - 1 - counts.sum()]] += 1
    return counts


def _rings(n, outer=0.85):
    counts = _ring_counts(n)
    pts, tang = [(0.0, 0.0)], [0.0]
    for k, m in enumerate(counts, 1):
        phase = np.pi / m * (k % 2)          # stagger neighbouring rings
        th = phase + 2 * np.pi * np.arange(m) / m
        rad = outer * k / len(counts)
        pts += list(zip(rad * np.cos(th), rad * np.sin(th)))
        tang += list(th)
    return np.array(pts), np.array(tang)


def _diamond(n, half_offset, l1_radius=0.9):
    """Square lattice rotated 45 deg, filled shell by shell (shells are diamonds)."""
    k = int(np.ceil(np.sqrt(n))) + 2
    o = 0.5 if half_offset else 0.0
    u, v = np.meshgrid(np.arange(-k, k + 1) + o, np.arange(-k, k + 1) + o)
    uv = np.stack([u.ravel(), v.ravel()], -1)
    sel = _take_shells(uv, np.abs(uv).max(1), n)
    xy = np.stack([sel[:, 0] - sel[:, 1], sel[:, 0] + sel[:, 1]], -1) / np.sqrt(2)
    return xy * l1_radius / np.abs(xy).sum(1).max()


def _hex_lattice(n, radius):
    """Hexagonal lattice filled in hexagonal shells; outermost centre at `radius`."""
    k = int(np.ceil(np.sqrt(n))) + 2
    i, j = np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1))
    i, j = i.ravel(), j.ravel()
    pts = np.stack([i + 0.5 * j, j * np.sqrt(3) / 2], -1)
    hexnorm = np.maximum.reduce([np.abs(i), np.abs(j), np.abs(i + j)])
    sel = _take_shells(pts, hexnorm, n)
    return sel * radius / np.hypot(*sel.T).max()


def _layout(name):
    """(centres, angles, axis ratio) in normalised units for a simulation pattern."""
    n = PATTERN_SPECS[name][0]
    zero = np.zeros(n)
    if name == "Array1":
        return _grid(15, 15), zero, 1.0
    if name == "Array2":
        return _grid(10, 10), zero, 1.0
    if name == "Array3":
        return _grid(10, 8), zero, 1.0       # sparse: 10 columns x 8 rows
    if name == "Array4":
        return _staggered(9, 11), zero, 1.0  # 11 staggered rows of 9
    if name in ("Circle1", "Circle2", "Circle3"):
        return _rings(n)[0], zero, 1.0
    if name == "Circle4":
        pts, tang = _rings(n)
        return pts, tang + CIRCLE4_TILT, CIRCLE4_ASPECT
    if name in ("Diamond1", "Diamond2"):
        # half-offset lattice keeps Diamond1 a nearly full 16x16 diamond (256-11);
        # Diamond2 = 10x10 diamond + 3 outer markers.
        return _diamond(n, half_offset=True), zero, 1.0
    if name == "Diamond3":
        return _diamond(n, half_offset=False), zero, 1.0   # full 9x9 diamond
    if name == "Diamond4":
        return _hex_lattice(n, 0.85), zero, 1.0            # 61-hexagon + 20 of next shell
    raise KeyError(f"unknown pattern {name!r}; expected one of {PATTERNS}")


def _rigid_jitter(seed, max_shift_mm=0.3, max_rot_deg=3.0):
    """Small nonzero rigid motion (fabrication/long-term drift), reproducible from
    seed (an int or a list of ints)."""
    rng = np.random.default_rng(seed)
    shift = rng.uniform(0.3, 1.0) * max_shift_mm
    direc = rng.uniform(0, 2 * np.pi)
    rot = rng.uniform(1 / 3, 1.0) * max_rot_deg * rng.choice([-1.0, 1.0])
    return shift * np.array([np.cos(direc), np.sin(direc)]), np.deg2rad(rot)


def pattern(name: str, *, pad_size_mm=(20.0, 20.0), seed: int = 0) -> MarkerSet:
    """One of the 12 simulation patterns (see PATTERNS).

    seed=0 gives the reference pattern; any other seed applies a small rigid
    motion (<= 0.3 mm, <= 3 deg), a fabrication variant like GelSight A-I.
    """
    pts, ang, aspect = _layout(name)
    scale = min(pad_size_mm) / 2.0
    area = PATTERN_SPECS[name][1] * (2.0 / REF_RENDER_PX) ** 2   # normalised units^2
    minor = np.sqrt(area / (np.pi * aspect))
    ms = MarkerSet(pts * scale, np.array([minor * aspect, minor]) * scale, ang, pad_size_mm)
    if seed:
        ms = ms.transformed(*_rigid_jitter(seed))
    return ms


def gelsight_pattern(twin: str, *, seed: int = 0) -> MarkerSet:
    """Marker layouts of the five real GelSight twins on the 25x25 mm gel.

    All use 56 markers (the paper's real GelSight count): A = 8x7 grid, C = centre
    + 4 rings (6/11/16/22), D = 45-deg diamond (8x8 less 8 corner-most). A-I / C-I are
    A-II / C-II moved rigidly by <= 0.3 mm and <= 3 deg (nonzero) drawn from seed;
    seed does not affect the -II twins or D-I.
    """
    if twin not in GELSIGHT_TWINS:
        raise KeyError(f"unknown GelSight twin {twin!r}; expected one of {GELSIGHT_TWINS}")
    n = 56
    family = twin[0]
    if family == "A":
        pts = _grid(8, 7, 0.75, 0.65)
    elif family == "C":
        pts = _rings(n, 0.75)[0]
    else:
        pts = _diamond(n, half_offset=True, l1_radius=0.85)
    scale = min(GELSIGHT_PAD_MM) / 2.0
    ms = MarkerSet(pts * scale, GELSIGHT_MARKER_R_MM, 0.0, GELSIGHT_PAD_MM)
    if twin.endswith("-I") and family != "D":
        ms = ms.transformed(*_rigid_jitter([seed, ord(family)]))  # A-I, C-I drift independently
    return ms


def tactip_pattern() -> MarkerSet:
    """127 TacTip pins: a 6-shell hexagonal lattice laid out in geodesic distance
    on the dome (radius of curvature 41.5 mm) and projected onto the base plane,
    so centres are (x, y) in the 40x40 mm square around the 40 mm footprint.
    Pins therefore crowd slightly towards the rim, as seen by the camera."""
    geo = _hex_lattice(127, 1.0)
    s = np.hypot(*geo.T)
    s_max = 0.85 * TACTIP_CURVATURE_MM * np.arcsin(TACTIP_DIAMETER_MM / 2 / TACTIP_CURVATURE_MM)
    rho = TACTIP_CURVATURE_MM * np.sin(s * s_max / TACTIP_CURVATURE_MM)
    with np.errstate(invalid="ignore", divide="ignore"):
        fac = np.where(s > 0, rho / s, 0.0)
    pad = (TACTIP_DIAMETER_MM, TACTIP_DIAMETER_MM)
    return MarkerSet(geo * fac[:, None], TACTIP_PIN_R_MM, 0.0, pad)


def uskin_pattern() -> MarkerSet:
    """The 4x4 uSkin taxels, one at the centre of each cell of the 24.6x22.6 mm
    patch; dot radius 0.2 x the smaller pitch (the signal-to-marker base size)."""
    w, h = USKIN_PAD_MM
    xs = (np.arange(4) - 1.5) * w / 4
    ys = (np.arange(4) - 1.5) * h / 4
    pts = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
    return MarkerSet(pts, 0.2 * min(w, h) / 4, 0.0, USKIN_PAD_MM)


# ---------------------------------------------------------------- raster

def _coverage(markers: MarkerSet, size, supersample):
    """Fraction of each pixel covered by markers, from ss x ss point samples.
    The image spans the pad exactly; pixel centres sit at (i + 0.5) / W."""
    h, w = (int(v) for v in size)
    ss = int(supersample)
    pw, ph = markers.pad_size_mm
    sx, sy = w * ss / pw, h * ss / ph            # hi-res samples per mm
    hi = np.zeros((h * ss, w * ss), bool)
    for (cx, cy), (a, b), th in zip(markers.centers, markers.axes, markers.angles):
        r = max(a, b)
        x0 = max(int(np.floor((cx - r + pw / 2) * sx)), 0)
        x1 = min(int(np.ceil((cx + r + pw / 2) * sx)) + 1, w * ss)
        y0 = max(int(np.floor((cy - r + ph / 2) * sy)), 0)
        y1 = min(int(np.ceil((cy + r + ph / 2) * sy)) + 1, h * ss)
        if x0 >= x1 or y0 >= y1:
            continue
        dx = (np.arange(x0, x1) + 0.5) / sx - pw / 2 - cx
        dy = (np.arange(y0, y1) + 0.5) / sy - ph / 2 - cy
        c, s = np.cos(th), np.sin(th)
        u = dx[None, :] * c + dy[:, None] * s
        v = -dx[None, :] * s + dy[:, None] * c
        hi[y0:y1, x0:x1] |= (u / a) ** 2 + (v / b) ** 2 <= 1.0
    return hi.reshape(h, ss, w, ss).mean(axis=(1, 3), dtype=np.float32)


def rasterize(markers: MarkerSet, *, size=(568, 568), supersample: int = 4) -> np.ndarray:
    """Binary (0/255 uint8) image of white markers on black, size=(H, W);
    a pixel is white when at least half of its area is marker."""
    cov = _coverage(markers, size, supersample)
    return np.where(cov >= 0.5, 255, 0).astype(np.uint8)


def marker_texture(markers: MarkerSet, *, size=(568, 568), supersample: int = 4) -> np.ndarray:
    """Antialiased float32 coverage in [0, 1], for use as a rendering texture."""
    return _coverage(markers, size, supersample)


def reference_set(names, *, size, gelsight_twins=GELSIGHT_TWINS, seed: int = 0, files=None) -> dict:
    """Node `patterns`: reference marker images of the simulation patterns and sensor twins.

    Per pattern: `images/<name>` (H,W) uint8 0/255 and `markers/<name>/centers|axes|angles`
    in mm on the undeformed pad.  files (stages.markers.pattern_files.pattern_files): name ->
    {path, pad_mm, polarity} of the patterns read from image files (stages.markers.pattern_image),
    which replace a drawing of the same name (patterns.dir) or join the set.
    """
    from stages.common import InputError
    from stages.figures import contact_sheet, png
    if len(size) != 2 or not all(isinstance(v, int) and v >= 32 for v in size):
        raise InputError(f"patterns.image_size must be [height, width] in pixels, each >= 32, got {size!r}")
    sets = {n: pattern(n, seed=0) for n in names}
    sets.update({f"gelsight-{t}": gelsight_pattern(t, seed=seed) for t in gelsight_twins})
    sets["tactip"] = tactip_pattern()
    sets["uskin"] = uskin_pattern()
    if files:
        from stages.markers.pattern_image import load_pattern
        for name, f in files.items():
            sets[name] = load_pattern(f["path"], pad_size_mm=tuple(f["pad_mm"]), polarity=f["polarity"])
    h, w = size
    images = {n: rasterize(m, size=(h, w)) for n, m in sets.items()}
    return {
        "names": list(sets),
        "images": images,
        "markers": {n: {"centers": m.centers, "axes": m.axes, "angles": m.angles,
                        "pad_size_mm": np.asarray(m.pad_size_mm, float)} for n, m in sets.items()},
        "figures": {"patterns": png(contact_sheet(list(images.values()), cols=6))},
        "attrs": {"image_size": [h, w],
                  **({"files": {n: {"path": f["path"], "sha256": f["sha256"]} for n, f in files.items()}}
                     if files else {})},
    }
