"""Speed of M2M translation, its flow-warp baseline and the FID feature extractor on CPU.

Run: python benchmarks/m2m.py [--size 256] [--widths 8,16] [--threads N] [--quick]
(about 2 minutes at the default 128x128 on a 2-core CPU; --size 256 is the paper profile;
--quick: 5 training steps and 64 images)

Rows per generator width: training steps/s (batch 16, one optimiser step each, the loss and
the data pipeline of stages.m2m.train included),
translated images/s with the one-step generator and with the 4-step sampler (batch 64,
stages.m2m.model.Translator, uint8 in and out); then flow-warp images/s (stages.m2m.flow on
synthetic deformed marker images) and InceptionV3 feature images/s (stages.imagemetrics, batch 32).  Wall time
and, in brackets, CPU time of the process: on a shared machine the CPU column is the one to
compare.
"""
import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np                                                          # noqa: E402
import torch                                                                # noqa: E402

from benchmarks.summary import record                                      # noqa: E402
from stages.imagemetrics import inception_features                         # noqa: E402
from stages.m2m.flow import MarkerFlow, warp                                # noqa: E402
from stages.m2m.model import Translator, build, default_config, device, state_arrays  # noqa: E402
from stages.m2m.train import PairBatches, fit                              # noqa: E402
from stages.markers.patterns import MarkerSet, pattern, rasterize           # noqa: E402


def marker_images(name, n, size, seed=0):
    """A reference and n frames with the markers pushed by a random Gaussian shear bump."""
    ms = pattern(name)
    rng = np.random.default_rng(seed)
    frames = []
    for _ in range(n):
        c, amp, ang = rng.uniform(-5, 5, 2), rng.uniform(0.2, 0.6), rng.uniform(0, 2 * np.pi)
        g = np.exp(-((ms.centers - c) ** 2).sum(1) / 32.0)[:, None]
        moved = MarkerSet(ms.centers + g * amp * np.array([np.cos(ang), np.sin(ang)]), ms.axes, ms.angles,
                          ms.pad_size_mm)
        frames.append(rasterize(moved, size=(size, size), supersample=2))
    return rasterize(ms, size=(size, size)), np.stack(frames)


def timed(fn, repeat=1):
    """(wall seconds, cpu seconds) of the fastest of `repeat` calls."""
    best = (np.inf, np.inf)
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        fn()
        best = min(best, (time.perf_counter() - w, time.process_time() - c))
    return best


def rate(count, seconds):
    w, c = seconds
    return f"{count / w:8.1f} ({count / c:6.1f} cpu)"


def plain_rate(count, seconds):
    """`rate` without its column padding, for the summary table."""
    w, c = seconds
    return f"{count / w:.1f} ({count / c:.1f} cpu)"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--widths", default="16")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    ap.add_argument("--train-steps", type=int, default=20)
    ap.add_argument("--images", type=int, default=256)
    ap.add_argument("--quick", action="store_true", help="5 training steps and 64 images")
    args = ap.parse_args()
    if args.quick:
        args.train_steps, args.images = 5, 64
    if args.threads:
        torch.set_num_threads(args.threads)
    size, n = args.size, args.images
    print(f"M2M on {device()}, {size}x{size}, torch threads {torch.get_num_threads()}")
    refs, frames = zip(*[marker_images(p, 32, size, seed=i) for i, p in enumerate(("Array2", "Circle2"))])
    images = np.stack(frames)
    src = np.concatenate([images[0]] * (n // 32 + 1))[:n]

    print(f"{'width':>5} {'params':>8} {'train steps/s (b16)':>24} {'translate img/s':>24} {'4-step img/s':>24}")
    for width in (int(w) for w in args.widths.split(",")):
        cfg = default_config(size=(size, size), width=width, timesteps=1000)
        torch.manual_seed(0)
        net = build(cfg)
        batches = PairBatches(images, np.stack(refs), seed=0)
        fit(net, cfg, batches, steps=2, batch_size=16, lr=1e-3, seed=0)          # warm-up
        train = timed(lambda: fit(net, cfg, batches, steps=args.train_steps, batch_size=16, lr=1e-3,
                                  seed=0))
        tr = Translator(cfg, state_arrays(net))
        tr.translate(src[:64], refs[0], refs[1])                                  # warm-up
        one = timed(lambda: tr.translate(src, refs[0], refs[1]), repeat=2)
        four = timed(lambda: tr.translate(src[:64], refs[0], refs[1], steps=4))
        params = sum(v.size for v in state_arrays(net).values())
        print(f"{width:>5} {params:>8} {rate(args.train_steps, train):>24} {rate(n, one):>24} {rate(64, four):>24}")
        record("m2m", f"translated img/s, width {width}, {size}px", plain_rate(n, one), None)
        record("m2m", f"4-step translated img/s, width {width}", plain_rate(64, four), None)

    flow = MarkerFlow(refs[0])
    fw = timed(lambda: [warp(refs[1], flow.field(im)) for im in src], repeat=2)
    print(f"flow-warp img/s             {rate(n, fw)}")
    record("m2m", f"flow-warp img/s, {size}px", plain_rate(n, fw), None)
    inception_features(src[:4])                                                   # load + warm-up
    feats = timed(lambda: inception_features(src[:64], batch=32))
    print(f"InceptionV3 features img/s  {rate(64, feats)}")
    record("m2m", f"FID features (InceptionV3) img/s, {size}px", plain_rate(64, feats), None)


if __name__ == "__main__":
    main()
