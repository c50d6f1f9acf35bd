"""Speed and memory of the Mitsuba marker renderer (stages.markers.render).

Run: python benchmarks/render.py [--quick]   (about 2-3 minutes on a 2-core CPU; --quick ~40 s)

Input: a synthetic contact sequence on the sim pad's solver grid (65 x 65, 0.3125 mm): a
Hertz-like press (dip with radially outward ux, uy) that deepens to 1.5 mm and then drags
+x, cycling over 24 distinct fields; pattern Array2 (look none) and GelSight C-II (look
gelsight, 25 mm pad).  No engine needed.

Table 1, images/s per backend x look x size:
  node   render_sequence drained after its first chunk (chunks of 8 here), i.e. once the scene
         is built (vertex resampling, ray tracing, texture lookups, shading, chunking, labels);
  bare   the same Mitsuba scene in a bare loop: set vertex_positions, params.update(),
         mi.render, copy to numpy - vertex buffers prepared before timing; for a camera look
         (gelsight) the bare loop also calls the look's deferred shading (looks.shade and
         camera_image on the traced samples, normals and positions prepared before timing),
         because Mitsuba alone gives no camera image of this look (its own light sampling
         needs hundreds of samples per pixel for three coloured LEDs; see render.py);
  ratio  node / bare (the cost of everything the node adds to rendering: vertex resampling,
         texture lookup, hole filling, truth masks, chunking, labels);
  trace  for camera looks, the bare trace alone (no shading) and node / trace, so the
         shading's own cost stays visible;
  cpu ms CPU time per frame (all threads): on a busy machine a steadier measure than img/s.
Table 2, segmentation images/s (stages.markers.segment, the params.yaml defaults: otsu and
grabcut) on raw GelSight frames rendered here, with the IoU against their truth masks.
Table 3: peak Python-heap memory (tracemalloc: numpy buffers included, Mitsuba's own
allocations not) while draining the node over 100 and 1000 frames; it must not grow.
"""
import argparse
import os
import sys
import time
import tracemalloc
from collections.abc import Mapping

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np                                                              # noqa: E402

import stages.markers.looks as looks                                            # noqa: E402
import stages.markers.render as render                                          # noqa: E402
from benchmarks.summary import drain, record                                    # noqa: E402
from stages.markers.mitsuba_backend import llvm_usable, mitsuba, thread_count   # noqa: E402
from stages.markers.patterns import gelsight_pattern, pattern                   # noqa: E402
from stages.common import LABEL_KEYS                                             # noqa: E402
from stages.markers.render import Renderer, render_sequence                     # noqa: E402

GRID = 65
DISTINCT = 24


def fields(pad_mm: float) -> np.ndarray:
    """DISTINCT displacement fields (press to 1.5 mm, then a 1 mm drag along +x)."""
    g = (np.arange(GRID) - (GRID - 1) / 2) * pad_mm / (GRID - 1)
    x, y = np.meshgrid(g, g)
    out = []
    for k in range(DISTINCT):
        depth = 1.5 * min(1.0, (k + 1) / (DISTINCT // 2))
        shift = max(0, k - DISTINCT // 2) / (DISTINCT // 2)
        cx = shift
        r2 = (x - cx) ** 2 + y ** 2
        bump = np.exp(-r2 / 18.0)
        drag = np.exp(-r2 / 40.0)
        out.append(np.stack([0.25 * depth * (x - cx) / 3 * bump + shift * drag,
                             0.25 * depth * y / 3 * bump, -depth * bump], -1))
    return np.asarray(out, np.float32)


class LazyFrames:
    """Frames made on slicing, like an artifact's LazyArray: the input holds no sequence."""

    def __init__(self, base: np.ndarray, n: int):
        self.base, self.n = base, n

    def __len__(self):
        return self.n

    def __getitem__(self, item):
        rows = np.arange(self.n)[item]
        return self.base[rows % len(self.base)]


class SyntheticDeform(Mapping):
    """A deform artifact stand-in with n frames."""

    def __init__(self, n: int, pad_mm: float):
        g = (np.arange(GRID) - (GRID - 1) / 2) * pad_mm / (GRID - 1)
        depth = np.resize(np.linspace(0.1, 1.5, DISTINCT), n)
        self.data = {"grid_x": g, "grid_y": g, "surface_z": np.zeros((GRID, GRID)),
                     "on_pad": np.ones((GRID, GRID), bool),
                     "displacement": LazyFrames(fields(pad_mm), n),
                     "depth": depth, "normalised_depth": (depth / 1.5).astype(np.float32)}
        self.data.update({k: LazyFrames(np.zeros((DISTINCT, 3), np.float32), n)
                          for k in LABEL_KEYS if k not in self.data})

    def __getitem__(self, k):
        return self.data[k]

    def __iter__(self):
        return iter(self.data)

    def __len__(self):
        return len(self.data)


SKINS = {"none": ("Array2", pattern("Array2"), 20.0),
         "gelsight": ("gelsight-C-II", gelsight_pattern("C-II"), 25.0)}


def patterns_input(name, ms):
    return {f"markers/{name}/{k}": v for k, v in (("centers", ms.centers), ("axes", ms.axes),
                                                  ("angles", ms.angles),
                                                  ("pad_size_mm", np.asarray(ms.pad_size_mm)))}


def node_rate(look, size, backend, n, spp):
    name, ms, pad = SKINS[look]
    spec = {"sensor": "synthetic", "pattern": name, "look": look, "noise": 2.0}
    kwargs = dict(patterns=patterns_input(name, ms), skin=name, spec=spec, size=size, spp=spp,
                  backend=backend)
    drain(render_sequence(deform=SyntheticDeform(4, pad), **kwargs))       # compile kernels
    gen = render_sequence(deform=SyntheticDeform(n, pad), **kwargs)
    first = len(next(gen)["truth"])                 # the scene is built: time from here
    t, cpu = time.perf_counter(), time.process_time()
    drain(gen)
    frames = n - first
    return frames / (time.perf_counter() - t), 1e3 * (time.process_time() - cpu) / frames


def bare_rate(look, size, backend, n, spp, shaded=True):
    """Bare loop over the same scene; with `shaded` (camera looks), plus the look's shading."""
    _, ms, pad = SKINS[look]
    d = SyntheticDeform(1, pad)
    r = Renderer(d["grid_x"], d["grid_y"], d["surface_z"], d["on_pad"], ms, look=look,
                 size=size, spp=spp, backend=backend, noise=2.0)
    positions = [r.mesh.positions(f) for f in fields(pad)]
    buffers = [r.vertex_buffer(p) for p in positions]
    mi = mitsuba(r.backend)
    shade = shaded and look != "none"
    if shade:      # per field: channel-first unit normals and positions on the vertex grid
        import cv2
        grids = [np.concatenate([r.mesh.normals(p), p], -1).astype(np.float32) for p in positions]
        rng = np.random.default_rng(0)

    def frame(k):
        r.params["pad.vertex_positions"] = buffers[k % len(buffers)]
        r.params.update()
        samples = np.array(mi.render(r.scene, spp=1))
        if not shade:
            return samples
        th, tw = r.texture.shape
        cov = cv2.remap(r.texture, samples[..., 0] * tw - 0.5, samples[..., 1] * th - 0.5,
                        cv2.INTER_LINEAR)
        x = (samples[..., 0] - 0.5) * r.mesh.pad[0]
        y = (samples[..., 1] - 0.5) * r.mesh.pad[1]
        at = cv2.remap(grids[k % len(grids)], *[v.astype(np.float32) for v in r.mesh.grid_index(x, y)],
                       cv2.INTER_LINEAR)
        at = np.ascontiguousarray(at.transpose(2, 0, 1))
        at[:3] /= np.sqrt((at[:3] ** 2).sum(0))
        radiance = looks.shade(r.shading, r.leds, at[:3], at[3:], cov, r.eye)
        return looks.camera_image(radiance.transpose(1, 2, 0), r.noise, rng)

    with thread_count(render.THREADS):                # as the node runs
        frame(0)
        t, cpu = time.perf_counter(), time.process_time()
        for k in range(n):
            frame(k)
        return n / (time.perf_counter() - t), 1e3 * (time.process_time() - cpu) / n


def segmentation_rate(size, backend, method, budget):
    """(images/s, mean IoU) of segment() on raw GelSight C-II frames of `size`."""
    from stages.markers.segment import iou, segment
    name, ms, pad = SKINS["gelsight"]
    spec = {"sensor": "synthetic", "pattern": name, "look": "gelsight", "noise": 2.0}
    frames = [c for c in render_sequence(deform=SyntheticDeform(DISTINCT, pad),
                                         patterns=patterns_input(name, ms), skin=name, spec=spec,
                                         size=size, spp=1, backend=backend)]
    raw = np.concatenate([c["raw"] for c in frames])
    truth = np.concatenate([c["truth"] for c in frames])
    segment(raw[0], polarity="dark", method=method, min_area=3, box_margin=3)
    t, n, scores = time.perf_counter(), 0, []
    while n < len(raw) or time.perf_counter() - t < budget:
        k = n % len(raw)
        mask = segment(raw[k], polarity="dark", method=method, min_area=3, box_margin=3)
        if n < len(raw):
            scores.append(iou(mask, truth[k]))
        n += 1
    return n / (time.perf_counter() - t), float(np.mean(scores))


def peak_mb(n, size, backend):
    name, ms, pad = SKINS["none"]
    spec = {"sensor": "synthetic", "pattern": name, "look": "none"}
    deform = SyntheticDeform(n, pad)
    tracemalloc.start()
    drain(render_sequence(deform=deform, patterns=patterns_input(name, ms), skin=name, spec=spec,
                          size=size, spp=1, backend=backend))
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak / 2 ** 20


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer frames and sizes")
    args = ap.parse_args()
    backends = ["llvm", "scalar"] if llvm_usable() else ["scalar"]
    sizes = [(128, 128), (256, 256)] if args.quick else [(128, 128), (256, 256), (480, 640)]
    budget = 0.5 if args.quick else 1.5                    # seconds of frames per measurement
    print(f"backends: {', '.join(backends)}" + ("" if llvm_usable() else "  (llvm unusable here)")
          + f"; Dr.Jit threads while rendering: {render.THREADS}; load average "
          + " ".join(f"{v:.1f}" for v in os.getloadavg()))
    chunk, render.CHUNK = render.CHUNK, 8                 # time the node from its 9th frame
    print(f"{'backend':8s} {'look':9s} {'size':>8s} {'spp':>3s} {'frames':>6s} {'node img/s':>10s} "
          f"{'bare img/s':>10s} {'ratio':>6s} {'node cpu ms':>11s} {'bare cpu ms':>11s} "
          f"{'trace img/s':>11s} {'node / trace':>12s}")
    for backend in backends:
        for look in ("none", "gelsight"):
            for size in sizes:
                spp = 1
                probe, _ = bare_rate(look, size, backend, 4, spp)
                n = int(np.clip(budget * probe, 24, 400))
                bare, bare_cpu = bare_rate(look, size, backend, n, spp)
                node, node_cpu = node_rate(look, size, backend, n, spp)
                trace = bare_rate(look, size, backend, n, spp, shaded=False)[0] if look != "none" else None
                print(f"{backend:8s} {look:9s} {size[0]:>3d}x{size[1]:<4d} {spp:>3d} {n:>6d} "
                      f"{node:>10.1f} {bare:>10.1f} {node / bare:>6.2f} {node_cpu:>11.2f} "
                      f"{bare_cpu:>11.2f}" + (f" {trace:>11.1f} {node / trace:>12.2f}" if trace else ""),
                      flush=True)
                what = "bare Mitsuba" + (" + shading" if look != "none" else "")
                record("render", f"node / {what}, {backend} {look} {size[0]}x{size[1]}",
                       f"{node:.1f} / {bare:.1f} img/s", node / bare, ">= 0.85")
                if trace:
                    record("render", f"node / bare trace (shading cost), {backend} {look} "
                           f"{size[0]}x{size[1]}", f"{node:.1f} / {trace:.1f} img/s", node / trace, "info")
    render.CHUNK = chunk
    print(f"\nsegmentation of raw GelSight frames ({backends[0]} renders):")
    print(f"{'method':8s} {'size':>8s} {'img/s':>8s} {'IoU':>6s}")
    for method in ("otsu", "grabcut"):
        for size in sizes[:2]:
            rate, score = segmentation_rate(size, backends[0], method, budget)
            print(f"{method:8s} {size[0]:>3d}x{size[1]:<4d} {rate:>8.1f} {score:>6.3f}", flush=True)
            record("render", f"segmentation {method} {size[0]}x{size[1]}",
                   f"{rate:.1f} img/s, IoU {score:.3f}", None, "")
    counts = (50, 200) if args.quick else (100, 1000)
    print(f"\npeak memory of render_sequence (look none, 128x128, {backends[0]}), tracemalloc:")
    peaks = []
    for n in counts:
        peaks.append(peak_mb(n, (128, 128), backends[0]))
        print(f"  {n:5d} frames: {peaks[-1]:7.2f} MiB", flush=True)
    record("render", f"peak memory, {counts[1]} vs {counts[0]} frames",
           f"{peaks[1]:.2f} / {peaks[0]:.2f} MiB", peaks[1] / peaks[0], "<= 1.1")


if __name__ == "__main__":
    main()
