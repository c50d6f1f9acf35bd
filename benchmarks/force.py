"""Speed of the force regressor (stages.force) on CPU: training, batch inference, streaming.

Run: python benchmarks/force.py [--steps 40] [--config '{"input_size": 64}'] [--quick]   (< 2 min, 2 cores;
--quick: 10 training steps, one thread)

Training runs where the pipeline's does (stages.common.torch_device: the GPU when torch sees
one; GENFORCE_DEVICE=cpu on a GPU machine for the CPU figures); prediction runs on the CPU.

Data: 30 contact sequences of 50 frames of 128x128 uint8 0/255 marker-like images (random
dots laid out symmetric about both centre lines, as the twins' markers are, so that
genforce_plus's mirror read reads each frame with its three mirror images, as it does a
GelSight, TacTip or uSkin frame; the speed does not depend on the content otherwise), the
default-profile size.  Columns are torch thread counts.  Rows:
  train samples/s     contact windows per second (the default profile's batch and windows, padded)
  train frames/s      frames through forward + backward per second
  N-step fit (s)      one default-profile training (its force.steps) at that speed
  predict frames/s    predict_contacts over the 1500 frames (contacts batched, state reset)
  stream ms/frame     StreamingPredictor.step latency (median over 200 frames): the plain
                      regressor, as source_only, genforce and genforce_comp read
  x 40 Hz             how many times faster than a 40 Hz sensor (25 ms per frame) streaming is
  plus ms/frame       the same model as genforce_plus reads it: the mirror read (the frame and
                      its three mirror images in one batch)
  plus x 40 Hz        the same against a 40 Hz sensor
  cpu/wall            process CPU time over wall time while training: about the thread count
                      on an idle machine, lower when other processes share the cores
  bare frames/s       the same network, batch shape and optimiser in a bare torch loop (fixed
                      full-length windows drawn from tensors already in memory; no window
                      sampling, padding, gradient clipping, learning-rate schedule or
                      progress bar), timed in the same run
  fit / bare          train frames/s over bare frames/s: what stages.force.train.fit's recipe
                      costs beside the network itself
"""
import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np                                                              # noqa: E402
import torch                                                                    # noqa: E402

from benchmarks.summary import record                                           # noqa: E402
from stages.force.model import (StreamingPredictor, from_arrays,   # noqa: E402
                                model_config, predict_contacts, to_arrays)
from stages.common import torch_device, torch_threads                           # noqa: E402
from stages.force.train import fit, make_sequences                              # noqa: E402

SENSOR_HZ = 40.0


def _profile_recipe() -> tuple[int, int, int, dict]:
    """The default profile's training: steps, batch size, window length and the optimiser's
    keyword arguments of stages.force.train.fit (params.yaml `force`)."""
    from pathlib import Path

    from pipeline.params import get, load
    from stages.force.fit import recipe, split_config
    params = load(Path(__file__).resolve().parents[1] / "params.yaml")
    _, train = split_config(get(params, "force.config"))
    fit_kw = recipe(train)
    seq_len = fit_kw.pop("seq_len")
    fit_kw["lr"] = float(get(params, "force.lr"))
    return int(get(params, "force.steps")), int(get(params, "force.batch_size")), seq_len, fit_kw


FIT_STEPS, BATCH, SEQ_LEN, FIT_KW = _profile_recipe()      # the default profile's training


def marker_like(rng, n, size=128):
    """n random binary dot images (T,size,size) uint8 and a reference symmetric about both
    centre lines."""
    quarter = rng.random((size // 16, size // 16)) < 0.5
    base = np.block([[quarter, quarter[:, ::-1]], [quarter[::-1], quarter[::-1, ::-1]]])
    ref = np.kron(base, np.ones((8, 8), bool)).astype(np.uint8) * 255
    shift = rng.integers(-2, 3, (n, 2))
    return np.stack([np.roll(ref, tuple(s), (0, 1)) for s in shift]), ref


def step_ms(predictor, images) -> float:
    """Median latency (ms) of predictor.step over the frames, the first 10 left out (warm-up)."""
    lat = []
    for img in images:
        t = time.perf_counter()
        predictor.step(img)
        lat.append(time.perf_counter() - t)
    return 1e3 * float(np.median(lat[10:]))


def bare_loop(threads, config, steps, seqs) -> float:
    """Frames/s of a bare training loop of the same network: full SEQ_LEN windows of BATCH
    contacts, the profile's optimiser (torch's SGD with momentum 0.9, or AdamW), L1 loss."""
    from stages.force.model import ForceRegressor
    cfg = {**config, "force_min": [-5.0, -5.0, -20.0], "force_max": [5.0, 5.0, 5.0]}
    with torch_threads(threads):
        torch.manual_seed(0)
        model = ForceRegressor(cfg).to(torch_device()).train()
        if FIT_KW["optimizer"] == "sgd":
            opt = torch.optim.SGD(model.parameters(), lr=FIT_KW["lr"], momentum=0.9,
                                  weight_decay=FIT_KW["weight_decay"])
        else:
            opt = torch.optim.AdamW(model.parameters(), lr=FIT_KW["lr"], weight_decay=FIT_KW["weight_decay"])
        x = torch.stack([s.inputs[:SEQ_LEN] for s in seqs[:BATCH]]).to(torch_device())
        y = torch.rand(BATCH, SEQ_LEN, 3, device=x.device)

        def step():
            loss = torch.nn.functional.l1_loss(model(x)[0], y)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            return loss
        for _ in range(3):
            step()                                                           # warm-up
        t = time.perf_counter()
        for _ in range(steps):
            step().item()
        return steps * BATCH * SEQ_LEN / (time.perf_counter() - t)


def bench(threads, config, steps, contacts=30, length=50):
    """(the mirror images the model reads a frame with, {row: figure})."""
    rng = np.random.default_rng(0)
    images, ref = marker_like(rng, contacts * length)
    forces = rng.uniform(-4, 0, (contacts * length, 3)).astype(np.float32)
    seqs = make_sequences(np.split(images, contacts), np.split(forces, contacts), ref, config)
    kw = dict(batch_size=BATCH, seq_len=SEQ_LEN, threads=threads, **FIT_KW)
    fit(seqs, config, steps=3, **kw)                                          # warm-up
    cpu, wall = time.process_time(), time.perf_counter()
    model, hist = fit(seqs, config, steps=steps, **kw)
    cpu_ratio = (time.process_time() - cpu) / (time.perf_counter() - wall)
    bare = bare_loop(threads, config, steps, seqs)
    model.set_reference(ref)
    with torch_threads(threads):
        cid = np.repeat(np.arange(contacts), length)
        predict_contacts(model, images[:length], cid[:length])
        t = time.perf_counter()
        predict_contacts(model, images, cid)
        predict_fps = len(images) / (time.perf_counter() - t)
        # genforce_plus: the mirror read on the same weights
        plus = from_arrays(to_arrays(model), {**model.config, "mirror_read": "auto"})
        ms = step_ms(StreamingPredictor(model), images[:200])
        ms_plus = step_ms(StreamingPredictor(plus, ref), images[:200])
    return plus.mirrors_for(ref), {"train samples/s": hist["samples_per_s"], "train frames/s": hist["frames_per_s"],
            f"{FIT_STEPS}-step fit (s)": FIT_STEPS * hist["seconds"] / steps, "predict frames/s": predict_fps,
            "stream ms/frame": ms, "x 40 Hz": 1e3 / SENSOR_HZ / ms,
            "plus ms/frame": ms_plus, "plus x 40 Hz": 1e3 / SENSOR_HZ / ms_plus, "cpu/wall": cpu_ratio,
            "bare frames/s": bare, "fit / bare": hist["frames_per_s"] / bare}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=40, help="timed training steps per column")
    ap.add_argument("--config", default="{}", help="force-model config overrides (JSON)")
    ap.add_argument("--threads", default="1,2", help="torch thread counts to compare")
    ap.add_argument("--quick", action="store_true", help="10 timed training steps, one thread")
    args = ap.parse_args()
    if args.quick:
        args.steps, args.threads = 10, "1"
    config = model_config(json.loads(args.config))
    threads = [int(t) for t in args.threads.split(",")]
    print(f"config: {json.dumps(config)}")
    print(f"torch {torch.__version__}, {os.cpu_count()} CPUs, training on {torch_device()}")
    runs = {t: bench(t, config, args.steps) for t in threads}
    cols = {t: row for t, (_, row) in runs.items()}
    mirrors = next(iter(runs.values()))[0]
    print(f"genforce_plus reads each frame and its mirror images {list(mirrors)} in one batch")
    rows = list(next(iter(cols.values())))
    print(f"{'':20s}" + "".join(f"{f'threads={t}':>12s}" for t in threads))
    for r in rows:
        print(f"{r:20s}" + "".join(f"{cols[t][r]:12.1f}" if cols[t][r] >= 10 else f"{cols[t][r]:12.2f}"
                                   for t in threads))
    for t in threads:
        record("force", f"training frames/s vs a bare torch loop, threads={t}",
               f"{cols[t]['train frames/s']:.0f} vs {cols[t]['bare frames/s']:.0f} frames/s",
               cols[t]["fit / bare"], ">= 0.8")
        fps, ms = cols[t]["predict frames/s"], cols[t]["stream ms/frame"]
        record("force", f"batch predict vs 40 Hz, threads={t}", f"{fps:.0f} frames/s", fps / SENSOR_HZ, ">= 1")
        record("force", f"streaming vs 40 Hz, threads={t}", f"{ms:.2f} ms/frame", cols[t]["x 40 Hz"], ">= 1")
        ms_plus = cols[t]["plus ms/frame"]
        record("force", f"genforce_plus streaming vs 40 Hz, threads={t}", f"{ms_plus:.2f} ms/frame",
               cols[t]["plus x 40 Hz"], ">= 1")


if __name__ == "__main__":
    main()
