"""Speed and memory of ingesting the authors' released dataset (stages.capture.ingest).

Run: python benchmarks/ingest.py [--quick]   (--quick: 500 and 2,000 frames instead of 1,000
and 10,000)

Input: one homo sensor written in the authors' layout into a temporary folder: contacts of
60 frames (the released homo set averages about that), each frame np.save(np.packbits(mask))
of a 480 x 640 marker mask, with ft.csv and last.csv.  Images go to the default profile's
128 x 128.  For each frame count:
  node   the ingest node run by the engine's worker (pipeline.worker.execute): labels read and
         checked, frames decoded, resized and appended to an HDF5 artifact in a temporary store;
  bare   a bare loop: np.load, np.unpackbits(f).reshape(480, 640), cv2.resize INTER_AREA to
         128 x 128 and the >= 0.5 threshold, the result dropped;
with frames/s and the peak Python-heap memory (tracemalloc: numpy buffers included, HDF5's own
not), each the faster of two interleaved runs.  Ratios: node / bare frames/s at the larger count, and the node's peak at the larger
count over the smaller (streaming: it must not grow with the frames).
"""
import argparse
import os
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np                                                        # noqa: E402

from benchmarks.summary import record                                     # noqa: E402
from pipeline.hashing import ENGINE_VERSION                               # noqa: E402
from pipeline.worker import execute                                       # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FRAMES_PER_CONTACT = 60
SIZE = (128, 128)
SENSOR = "Array-I"
REPEATS = 2                     # each measured twice, interleaved: a shared machine's noise


def write_sensor(root: Path, n_frames: int) -> None:
    """n_frames of one homo sensor in the authors' layout (few distinct masks, saved per frame)."""
    rng = np.random.default_rng(0)
    masks = [np.packbits((rng.random((480, 640)) < 0.08).astype(np.uint8)) for _ in range(8)]
    img = root / "training/homo/img/npy"
    img.mkdir(parents=True)
    np.save(img / f"{SENSOR}_ref.npy", masks[0])
    done, point = 0, 0
    while done < n_frames:
        point += 1
        n = min(FRAMES_PER_CONTACT, n_frames - done)
        folder, force = img / SENSOR / "cone" / str(point), root / "training/homo/force" / SENSOR / "cone" / str(point)
        folder.mkdir(parents=True)
        force.mkdir(parents=True)
        for k in range(n):
            np.save(folder / f"{k:04d}.npy", masks[k % len(masks)])
        ends = [n // 4, n // 2, 3 * n // 4, n - 1]
        np.savetxt(folder / "last.csv", [f"/x/{e:04d}.npy" for e in ends], fmt="%s")
        rows = "\n".join(",".join(f"{v:.4f}" for v in r) for r in rng.normal(0, 1, (n, 6)))
        (force / "ft.csv").write_text("Fx(N),Fy(N),Fz(N),Tx(Nmm),Ty(Nmm),Tz(Nmm)\n" + rows + "\n")
        done += n


def files(root: Path) -> list[Path]:
    img = root / "training/homo/img/npy" / SENSOR / "cone"
    return [f for p in sorted(img.iterdir(), key=lambda p: int(p.name)) for f in sorted(p.glob("*.npy"))]


def bare(paths) -> None:
    import cv2
    for p in paths:
        bits = np.unpackbits(np.load(p)).reshape(480, 640)
        small = cv2.resize(bits.astype(np.float32), SIZE[::-1], interpolation=cv2.INTER_AREA)
        np.where(small >= 0.5, 255, 0).astype(np.uint8)


def node(root: Path, store: Path) -> dict:
    task = {"store": str(store), "key": f"bench{time.time_ns()}", "func": "stages.capture.ingest:ingest",
            "roots": [ROOT], "node": "ingest", "instance": f"ingest[sensor={SENSOR}]",
            "params": {"root": str(root), "size": list(SIZE), "modulus_depth_mm": 1.0},
            "grid": {"sensor": SENSOR}, "inputs": {}, "input_digests": {}, "code": "bench",
            "engine": ENGINE_VERSION, "force": True}
    out = execute(task)
    if "error" in out:
        raise SystemExit(f"ingest failed: {out['error']}\n{out.get('traceback', '')}")
    return out["record"]


def measure(run):
    tracemalloc.start()
    t = time.perf_counter()
    run()
    seconds = time.perf_counter() - t
    peak = tracemalloc.get_traced_memory()[1] / 2 ** 20
    tracemalloc.stop()
    return seconds, peak


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="500 and 2,000 frames")
    args = ap.parse_args()
    counts = (500, 2000) if args.quick else (1000, 10000)
    import cv2  # noqa: F401 - imported before timing, by both
    import stages.capture.ingest  # noqa: F401
    print(f"{'frames':>7s} {'node fr/s':>10s} {'bare fr/s':>10s} {'node/bare':>9s} "
          f"{'node MiB':>9s} {'bare MiB':>9s}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in counts:
            root = Path(tmp) / f"d{n}"
            write_sensor(root, n)
            paths = files(root)
            for p in paths:                                        # both read from the page cache
                p.read_bytes()
            bare(paths[:50])
            runs = [(measure(lambda: bare(paths)), measure(lambda: node(root, Path(tmp) / f"store{n}")))
                    for _ in range(REPEATS)]                      # interleaved; the faster of each
            (b_s, b_mb), (n_s, n_mb) = (min(r[i] for r in runs) for i in (0, 1))
            rows.append((n, n / n_s, n / b_s, n_mb, b_mb))
            print(f"{n:>7d} {n / n_s:>10.1f} {n / b_s:>10.1f} {b_s / n_s:>9.2f} {n_mb:>9.2f} {b_mb:>9.2f}",
                  flush=True)
    (n0, _, _, p0, _), (n1, node_rate, bare_rate, p1, _) = rows
    record("ingest", f"node / bare numpy loop, {n1} frames", f"{node_rate:.0f} / {bare_rate:.0f} frames/s",
           node_rate / bare_rate, ">= 0.7")
    record("ingest", f"node peak memory, {n1} vs {n0} frames", f"{p1:.1f} / {p0:.1f} MiB", p1 / p0, "<= 1.1")
    print(f"node / bare at {n1} frames: {node_rate / bare_rate:.2f}; node peak {n1} / {n0} frames: {p1 / p0:.2f}")


if __name__ == "__main__":
    main()
