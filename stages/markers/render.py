"""Marker images of deformed skins, ray traced with Mitsuba 3 (node `render[skin]`).

Geometry (stages.markers.pad_mesh).  The pad surface of a `deform` frame is a triangle mesh on
the solver grid resampled over the pad, plus a margin ring, moved by the frame's displacement;
its texture coordinates are the undeformed material coordinates, so markers move with the
material.

Camera.  The camera sits behind the skin, inside the sensor, on the optical axis at z < 0,
looking along +z with image up = -y: pad x runs along image columns (right) and pad y along
rows (down), so the image is the pad as the pattern images show it and a +x indenter shift moves
markers to +column.  Pressing (uz < 0) brings the surface towards the camera.  It is a pinhole
with a 35 mm lens on a 36 x 27 mm, 640 x 480 px sensor; an output of another aspect ratio is
the largest centred crop of that frame with the output's aspect, resampled to `size` (H, W)
(a square output sees a 27 x 27 mm crop: 42.2 deg).  Its distance is the largest at which the
pad (at its rim, for a dome) still fills the frame, or, with the skin's `view_mm` [x, y], at
which that central region of the pad does (TacTip's camera frames the central 25 mm of its
40 mm dome, so that a mm of contact place is about as many pixels as on the flat pads).

Rendering (deferred shading).  Mitsuba traces one ray per sample through the mesh (the `aov`
integrator: texture coordinates and hit distance; spp samples per pixel on a regular
sqrt(spp) x sqrt(spp) grid, i.e. a film sqrt(spp) x larger, averaged after shading).  All
shading then happens in material coordinates, looked up at each sample's (u, v): the marker
coverage texture (stages.markers.patterns.marker_texture), and, for the camera looks, the
surface normal and position bilinear on the deformed vertex grid (stages.markers.looks).
Every LED therefore counts exactly in every sample (Monte-Carlo light sampling would need
hundreds of samples per pixel for three coloured LEDs), and one ray-tracing pass gives both
the camera image and its truth.

Looks (spec `look`):
  none      the 12 simulation patterns: `truth` only, white markers on black
  gelsight  grey, slightly specular gel with dark markers lit by coloured LEDs low at the sides
            (spec `light`: one RGB per LED, LEDs evenly around the pad starting at -y), so
            indentation slopes tint the image; sRGB-like gamma; Gaussian camera noise
  tactip    white pin tips on a black dome lit softly by a ring of LEDs around the lens
Camera looks give `raw` (H,W,3) uint8 and `truth`, the marker mask of the same samples: the
flat (unlit) render, coverage averaged over each pixel's samples and thresholded at 1/2.
"""
from __future__ import annotations

import time
import zlib
from typing import Mapping

import numpy as np

from stages.common import LABEL_KEYS, check_option
from stages.markers.looks import LOOKS as SHADED
from stages.markers.looks import LedRig, camera_image, shade
from stages.markers.mitsuba_backend import mitsuba, resolve_backend, thread_count
from stages.markers.pad_mesh import PadMesh
from stages.markers.patterns import MarkerSet, marker_texture

NATIVE_SIZE = (480, 640)         # (H, W) px of the sensor the camera model is built on
FILM_WIDTH_MM, FOCAL_MM = 36.0, 35.0
TEXTURE_OVERSAMPLE = 2           # marker texels per film sample at the pad
TEXTURE_MAX = 4096
CHUNK = 32
# Dr.Jit threads while the node renders: a frame's kernels are small, and on 2 cores one thread
# renders 128x128 frames ~1.7x faster than two (no hand-offs) and leaves a core to the rest
THREADS = 1
LOOKS = ("none",) + tuple(SHADED)


def camera_fov_x(size) -> float:
    """Horizontal field of view (deg) of an output of `size` (H, W): the native 640x480
    frame cropped, centred, to the output's aspect ratio."""
    h, w = size
    crop_w = min(NATIVE_SIZE[1], NATIVE_SIZE[0] * w / h)
    return float(np.degrees(2 * np.arctan(FILM_WIDTH_MM * crop_w / NATIVE_SIZE[1] / 2 / FOCAL_MM)))


def camera_distance(size, pad_size_mm) -> float:
    """Distance (mm) from the camera to the plane where the pad just fills the frame."""
    h, w = size
    tan_x = np.tan(np.radians(camera_fov_x(size)) / 2)
    return float(min(pad_size_mm[0] / 2 / tan_x, pad_size_mm[1] / 2 / (tan_x * h / w)))


def _view(view_mm) -> tuple[float, float]:
    """A skin's `view_mm` as (x, y) mm, or a one-line error naming it."""
    try:
        view = tuple(float(v) for v in view_mm)
    except (TypeError, ValueError):
        view = ()
    if len(view) != 2 or not all(np.isfinite(v) and v > 0 for v in view):
        raise ValueError(f"render view_mm {view_mm!r}: expected two positive lengths [x, y] in mm")
    return view


_NEIGHBOURS = [(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj]


def _fill_holes(samples: np.ndarray) -> np.ndarray:
    """Samples whose ray slipped through a shared triangle edge take the mean of their hit
    neighbours (in place).  A hole is a miss with more than half of its (in-image) neighbours
    hit; a miss beside a convex outline (the dome's rim) has at most 3 of 8, so outlines stay.
    Misses are few, so only their neighbourhoods are visited."""
    hit = samples[..., 2] > 0
    h, w = hit.shape
    i, j = np.divmod(np.flatnonzero(~hit), w)
    if not i.size:
        return samples
    hits, near = np.zeros(i.size), np.zeros(i.size)
    total = np.zeros((i.size, samples.shape[-1]))
    for di, dj in _NEIGHBOURS:
        ii, jj = i + di, j + dj
        inside = (ii >= 0) & (ii < h) & (jj >= 0) & (jj < w)
        ii, jj = np.clip(ii, 0, h - 1), np.clip(jj, 0, w - 1)
        valid = inside & hit[ii, jj]
        near += inside
        hits += valid
        total += samples[ii, jj] * valid[:, None]
    hole = 2 * hits > near
    samples[i[hole], j[hole]] = total[hole] / hits[hole][:, None]
    return samples


class Renderer:
    """One skin's Mitsuba scene, built once; `render` moves the vertices and shades a frame.

    light: LED colours, one RGB (relative strengths) per LED, default the look's (see
    looks.LedRig: the exposure is automatic); noise: Gaussian camera noise sigma in grey
    levels, seeded by (seed, frame index); upsample: vertices per solver cell and axis;
    view_mm: the (x, y) mm of the pad around its centre that the frame shows (the camera moves
    closer, as a crop of the native frame would; default: the whole pad fills the frame).
    """

    def __init__(self, grid_x, grid_y, surface_z, on_pad, markers: MarkerSet, *, look: str = "none",
                 size=(128, 128), spp: int = 1, backend: str = "auto", light=None,
                 noise: float = 0.0, seed: int = 0, upsample: float = 1.0, view_mm=None):
        if look not in LOOKS:
            raise ValueError(f"render look {look!r}: expected one of {', '.join(LOOKS)}")
        self.ss = int(round(np.sqrt(spp)))
        if spp < 1 or self.ss * self.ss != spp:
            raise ValueError(f"render spp {spp}: must be a square (1, 4, 9, 16) - samples "
                             "lie on a regular grid in each pixel")
        self.size = tuple(int(v) for v in size)
        if len(self.size) != 2 or min(self.size) < 1:
            raise ValueError(f"render size {size!r}: expected (H, W)")
        self.look, self.spp, self.noise, self.seed = look, int(spp), float(noise), int(seed)
        self.backend = resolve_backend(backend)
        self.mesh = PadMesh(grid_x, grid_y, surface_z, on_pad, markers.pad_size_mm, upsample)
        self.fov_x = camera_fov_x(self.size)
        self.view = None if view_mm is None else _view(view_mm)
        self.distance = camera_distance(self.size, self.mesh.pad if self.view is None else self.view)
        self.eye = np.array([0.0, 0.0, self.mesh.fill_z - self.distance], np.float32)
        self._texture(markers)
        if look != "none":
            self.shading = SHADED[look]
            centre = self.mesh.base[self.mesh.shape[0] // 2, self.mesh.shape[1] // 2]
            self.leds = LedRig(self.shading, self.shading.light if light is None else light,
                               self.mesh.pad, centre)
        self._scene()

    # -- set-up -------------------------------------------------------------------------
    def _texture(self, markers: MarkerSet):
        h, w = self.size
        tan_x = np.tan(np.radians(self.fov_x) / 2)
        seen = 2 * self.distance * np.array([tan_x, tan_x * h / w])    # mm of pad in view
        per_mm = TEXTURE_OVERSAMPLE * self.ss * max(w / seen[0], h / seen[1])
        tw, th = (min(int(np.ceil(per_mm * p)), TEXTURE_MAX) for p in self.mesh.pad)
        self.texture = marker_texture(markers, size=(th, tw), supersample=4 if max(th, tw) <= 1024 else 2)

    def _scene(self):
        mi = mitsuba(self.backend)
        h, w = self.size
        mesh = mi.Mesh("pad", int(np.prod(self.mesh.shape)), len(self.mesh.faces),
                       has_vertex_normals=False, has_vertex_texcoords=True)
        mp = mi.traverse(mesh)
        mp["vertex_positions"] = type(mp["vertex_positions"])(self.mesh.base.astype(np.float32).ravel())
        mp["faces"] = type(mp["faces"])(self.mesh.faces.ravel())
        mp["vertex_texcoords"] = type(mp["vertex_texcoords"])(self.mesh.uv.astype(np.float32).ravel())
        mp.update()
        eye = [float(v) for v in self.eye]
        self.scene = mi.load_dict({
            "type": "scene",
            "integrator": {"type": "aov", "aovs": "uv:uv,t:depth"},
            "sensor": {"type": "perspective", "fov": self.fov_x, "fov_axis": "x",
                       "to_world": mi.ScalarTransform4f().look_at(
                           origin=eye, target=[eye[0], eye[1], eye[2] + 1.0], up=[0, -1, 0]),
                       "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
                       "film": {"type": "hdrfilm", "width": w * self.ss, "height": h * self.ss,
                                "rfilter": {"type": "box"}, "pixel_format": "rgb"}},
            "pad": mesh})
        self.params = mi.traverse(self.scene)
        self.params.keep(["pad.vertex_positions"])
        self._buffer = type(self.params["pad.vertex_positions"])

    # -- per frame ------------------------------------------------------------------------
    def vertex_buffer(self, positions: np.ndarray):
        """Vertex positions (ny, nx, 3) as the Mitsuba buffer of `pad.vertex_positions`."""
        return self._buffer(np.ascontiguousarray(positions, np.float32).ravel())

    def trace(self, positions: np.ndarray) -> np.ndarray:
        """(H*s, W*s, 3) samples (u, v, hit distance; 0 = no hit) of deformed vertex positions."""
        mi = mitsuba(self.backend)
        self.params["pad.vertex_positions"] = self.vertex_buffer(positions)
        self.params.update()
        return _fill_holes(np.array(mi.render(self.scene, spp=1)))

    def _pool(self, a: np.ndarray) -> np.ndarray:
        """Mean over each pixel's s x s samples."""
        if self.ss == 1:
            return a
        h, w = self.size
        return a.reshape(h, self.ss, w, self.ss, *a.shape[2:]).mean(axis=(1, 3))

    def render(self, displacement: np.ndarray, index: int = 0) -> dict:
        """`truth` (H,W) uint8 0/255 and, for camera looks, `raw` (H,W,3) uint8 of one frame;
        index seeds the camera noise."""
        import cv2
        positions = self.mesh.positions(displacement)
        samples = self.trace(positions)
        hit = (samples[..., 2] > 0).astype(np.float32)
        grid = None
        if self.mesh.bounded or self.look != "none":       # (col, row) on the vertex grid
            x = (samples[..., 0] - 0.5) * self.mesh.pad[0]
            y = (samples[..., 1] - 0.5) * self.mesh.pad[1]
            grid = [v.astype(np.float32) for v in self.mesh.grid_index(x, y)]
        if self.mesh.bounded:
            hit *= cv2.remap(self.mesh.on_pad, *grid, cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_REPLICATE) >= 0.5
        th, tw = self.texture.shape
        cov = cv2.remap(self.texture, samples[..., 0] * tw - 0.5, samples[..., 1] * th - 0.5,
                        cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        if not hit.all():
            cov *= hit
        out = {"truth": (self._pool(cov) >= 0.5).view(np.uint8) * np.uint8(255)}
        if self.look != "none":
            out["raw"] = self._shade(positions, grid, hit, cov, index)
        return out

    def _shade(self, positions, grid, hit, cov, index) -> np.ndarray:
        """The camera image: normals and positions of the deformed vertex grid at each sample
        (channel-first), shaded, averaged per pixel, gamma and noise (seeded by the index)."""
        import cv2
        grids = np.concatenate([self.mesh.normals(positions), positions], -1).astype(np.float32)
        at = cv2.remap(grids, *grid, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        at = np.ascontiguousarray(at.transpose(2, 0, 1))
        normal, position = at[:3], at[3:]
        normal /= np.sqrt(np.maximum((normal * normal).sum(0), 1e-18))
        radiance = shade(self.shading, self.leds, normal, position, cov, self.eye) * hit
        rng = np.random.default_rng((self.seed, index + 1)) if self.noise > 0 else None
        return camera_image(self._pool(radiance.transpose(1, 2, 0)), self.noise, rng)


def render_frames(displacement, grid_x, grid_y, surface_z, on_pad, markers: MarkerSet, *, look: str,
                  size, spp: int = 1, backend: str = "auto", light=None, noise: float = 0.0,
                  seed: int = 0) -> dict:
    """Render N displacement fields (N, h, w, 3): `truth` (N,H,W) and, for camera looks,
    `raw` (N,H,W,3); frame i's noise is seeded by (seed, i)."""
    r = Renderer(grid_x, grid_y, surface_z, on_pad, markers, look=look, size=size, spp=spp,
                 backend=backend, light=light, noise=noise, seed=seed)
    frames = [r.render(d, i) for i, d in enumerate(np.asarray(displacement))]
    if not frames:
        raise ValueError("render_frames: no displacement fields (N = 0)")
    return {k: np.stack([f[k] for f in frames]) for k in frames[0]}


# -- node -----------------------------------------------------------------------------------

def _get(art: Mapping, path: str):
    """A dataset by its path: flat ('markers/x/centers', artifacts) or nested (plain dicts)."""
    if path in art:
        return np.asarray(art[path])
    node = art
    for part in path.split("/"):
        if not isinstance(node, Mapping) or part not in node:
            raise KeyError(f"{path!r} is not in the input")
        node = node[part]
    return np.asarray(node)


def marker_set(patterns: Mapping, name: str) -> MarkerSet:
    """The MarkerSet stored as markers/<name>/centers|axes|angles|pad_size_mm (a pattern
    image file's under its stages.markers.pattern_files.image_pattern_name)."""
    from stages.markers.pattern_files import image_pattern_name, is_image_path
    if is_image_path(name):
        name = image_pattern_name(name)
    try:
        parts = {k: _get(patterns, f"markers/{name}/{k}")
                 for k in ("centers", "axes", "angles", "pad_size_mm")}
    except KeyError:
        from stages.common import InputError
        drawn = ([str(n.decode() if isinstance(n, bytes) else n) for n in np.asarray(patterns["names"])]
                 if "names" in patterns else sorted({k.split("/")[1] for k in patterns if k.startswith("markers/")}))
        raise InputError(f"sensors: pattern {name!r} is not drawn (stages.markers.patterns.reference_set "
                         f"draws {', '.join(drawn)})") from None
    return MarkerSet(parts["centers"], parts["axes"], parts["angles"], tuple(parts["pad_size_mm"]))


def _sheet_frames(depth: np.ndarray | None, n: int, k: int = 4) -> list[int]:
    """Up to k frames for the contact sheet: the deepest frame of each of k equal stretches."""
    if n == 0:
        return []
    bounds = np.linspace(0, n, min(k, n) + 1).astype(int)
    if depth is None:
        return [int(a) for a in bounds[:-1]]
    return [int(a + np.argmax(depth[a:b])) for a, b in zip(bounds[:-1], bounds[1:])]


def render_sequence(*, deform: Mapping, patterns: Mapping, skin: str, spec: Mapping, size,
                    spp: int, backend: str):
    """Node `render[skin]`: marker images of a deform artifact's frames, in chunks of 32.

    spec (the skin's params): `sensor` (the deform instance), `pattern` (a name in the
    patterns artifact), `look` (none, gelsight, tactip), optional `light` (RGB per LED),
    `noise` (sigma, grey levels; default 0), `seed` (noise seed; default from the skin name),
    `upsample` (vertices per solver cell and axis; default 1), `view_mm` ([x, y] mm of the pad
    around its centre the frame shows; default the whole pad).
    Yields `truth` (n,H,W) uint8 0/255, `raw` (n,H,W,3) uint8 for camera looks, and the label
    keys copied from deform.  Returns `truth_reference` (H,W) (zero displacement), for camera
    looks `raw_reference` (H,W,3), figures/frames (a few deep frames: raw above truth), and
    attrs.
    """
    from tqdm import tqdm
    from stages.figures import contact_sheet, png

    look = spec.get("look", "none")
    check_option(f"sensors.{skin}.look (rendered)", look, LOOKS)
    markers = marker_set(patterns, spec["pattern"])
    seed = int(spec.get("seed", zlib.crc32(skin.encode())))
    renderer = Renderer(deform["grid_x"], deform["grid_y"], deform["surface_z"], deform["on_pad"],
                        markers, look=look, size=size, spp=spp, backend=backend,
                        light=spec.get("light"), noise=float(spec.get("noise", 0.0)), seed=seed,
                        upsample=float(spec.get("upsample", 1.0)), view_mm=spec.get("view_mm"))
    displacement = deform["displacement"]
    n = len(displacement)
    labels = [k for k in LABEL_KEYS if k in deform]
    picks = _sheet_frames(np.asarray(deform["depth"]) if "depth" in deform else None, n)
    sheet, seconds = {}, 0.0
    with thread_count(THREADS), tqdm(total=n, desc=f"render[{skin}]", unit="frame", disable=None,
                                     leave=False) as bar:
        for a in range(0, n, CHUNK):
            block = np.asarray(displacement[a:a + CHUNK])
            t0 = time.perf_counter()
            frames = [renderer.render(d, a + i) for i, d in enumerate(block)]
            seconds += time.perf_counter() - t0
            chunk = {k: np.stack([f[k] for f in frames]) for k in frames[0]}
            chunk.update({k: np.asarray(deform[k][a:a + len(block)]) for k in labels})
            sheet.update({i: [frames[i - a].get("raw"), frames[i - a]["truth"]]
                          for i in picks if a <= i < a + len(block)})
            bar.update(len(block))
            yield chunk
        reference = renderer.render(np.zeros(np.shape(deform["surface_z"]) + (3,), np.float32), -1)
    out = {"truth_reference": reference["truth"]}
    if "indenters" in deform:                  # the names indenter_id indexes
        out["indenters"] = np.asarray(deform["indenters"]).astype(str)
    if "raw" in reference:
        out["raw_reference"] = reference["raw"]
    rows = [[sheet[i][k] for i in picks] for k in (0, 1) if picks and sheet[picks[0]][k] is not None]
    rows = rows or [[reference["truth"]]]                   # raw frames above their truth masks
    out["figures"] = {"frames": png(contact_sheet([img for row in rows for img in row], cols=len(rows[0])))}
    out["attrs"] = {"backend": renderer.backend, **({"target": backend["target"]} if isinstance(
                        backend, Mapping) and "target" in backend else {}), "spp": int(spp), "size": list(renderer.size),
                    "look": look, "pattern": str(spec["pattern"]), "sensor": str(spec.get("sensor", "")),
                    "fov_x_deg": renderer.fov_x, **({} if renderer.view is None else
                                                    {"view_mm": list(renderer.view)}),
                    "camera_distance_mm": renderer.distance, "texture_size": list(renderer.texture.shape),
                    "noise": renderer.noise, "seed": seed, "threads": THREADS}
    out["timing"] = {"seconds_per_frame": seconds / n if n else 0.0}
    return out
