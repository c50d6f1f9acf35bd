"""Training the force regressor on contact sequences (the paper's recipe, CPU-sized).

A sample is one contact sequence.  Each step draws ``batch_size`` contacts, crops a random
window of each (half of the windows start at the contact's first frame, where the GRU state
starts from rest in deployment; the rest start anywhere) with a random length up to
``seq_len``, pads the shorter windows with their last frame (image and label: a hold) and
minimises the L1 loss on min-max normalised forces with the ``optimizer``: SGD (momentum 0.9,
the paper's) or AdamW, with ``weight_decay``, a linear warm-up and a cosine decay of the
learning rate; the gradient norm is clipped at 1, which keeps lr 0.1 (the paper's SGD) stable
with batches of a few contacts.  benchmarks/force.py measures the speed beside a bare torch
loop of the same network.

Two-stage schedules (pretrain, then fine-tune) are two :func:`fit` calls, the second with
``init=`` the first's weights and a smaller ``lr``.

A node that trains several fits hands them one :class:`Checkpoint` (the file the engine gives
a node with a `checkpoint` parameter): each fit, named by a label, saves its whole state there
once a minute and its result when it ends, so a node interrupted in its third fit re-runs
neither of the first two and resumes the third where it was, ending with the weights an
uninterrupted run gives.
"""
from __future__ import annotations

import json
import os
import time
import warnings
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import torch
from tqdm import tqdm

from stages.common import load_state, save_state, torch_device, torch_threads
from stages.force.model import ForceRegressor, from_arrays, model_config, prepare, resolve_range, to_arrays


@dataclass
class ContactSequence:
    """One training sample: prepared inputs (T,C,S,S) and forces (T,3) N."""
    inputs: torch.Tensor
    force: np.ndarray


def make_sequences(images_per_contact: Sequence, forces_per_contact: Sequence, reference,
                   config: Mapping) -> list[ContactSequence]:
    """Prepare (resize, subtract/stack the reference) every contact's images once."""
    config = model_config(config)
    out = []
    for images, force in zip(images_per_contact, forces_per_contact):
        force = np.asarray(force, np.float32)
        if len(images) != len(force) or force.shape[1:] != (3,):
            raise ValueError(f"a contact has {len(images)} images but forces of shape {force.shape}")
        out.append(ContactSequence(prepare(images, reference, config), force))
    return out


def _window(rng: np.random.Generator, length: int, seq_len: int) -> tuple[int, int]:
    """A random crop (start, stop) of a contact of `length` frames."""
    hi = min(length, seq_len)
    n = int(rng.integers(max(1, hi // 2), hi + 1))
    start = 0 if rng.random() < 0.5 else int(rng.integers(0, length - n + 1))
    return start, start + n


def _batch(rng, seqs: list[ContactSequence], targets: list[torch.Tensor], batch_size: int, seq_len: int):
    picks = rng.integers(0, len(seqs), batch_size)
    crops = [(int(i),) + _window(rng, len(seqs[i].force), seq_len) for i in picks]
    length = max(b - a for _, a, b in crops)
    xs, ys = [], []
    for i, a, b in crops:
        pad = length - (b - a)
        x, y = seqs[i].inputs[a:b], targets[i][a:b]
        if pad:
            x = torch.cat([x, x[-1:].expand((pad,) + tuple(x.shape[1:]))])
            y = torch.cat([y, y[-1:].expand(pad, 3)])
        xs.append(x)
        ys.append(y)
    return torch.stack(xs), torch.stack(ys)


def _lr_at(step: int, steps: int, lr: float) -> float:
    warm = max(1, steps // 20)
    if step < warm:
        return lr * (step + 1) / warm
    return lr * 0.5 * (1.0 + np.cos(np.pi * (step - warm) / max(1, steps - warm)))


CHECKPOINT_EVERY_S = 60.0   # Checkpoint: seconds between saves of a fit's training state


def _check_fits(state: dict) -> None:
    if not isinstance(state.get("done"), dict) or "current" not in state:
        raise ValueError("not a force-fit checkpoint")


class Checkpoint:
    """One file holding a node's training progress: the result of every fit that ended (by
    label: weights, config, history) and the whole state of the fit in progress (weights,
    SGD momenta, step, losses so far, the batch sampler's and torch's random streams).

    The file is rewritten whole (a temporary file renamed over it, so a kill mid-write leaves
    the previous one) and loads with torch.load(weights_only=True): tensors and plain values,
    no code.  One that cannot be read is renamed <path>.bad with a warning and the node's
    fits start over.  ``resumed`` maps the label of a fit that continued a saved state to the
    step it continued from (a node's timing, outside its content).
    """

    def __init__(self, path: str | os.PathLike, every_s: float | None = None):
        self.path = os.fspath(path)
        self.every_s = float(CHECKPOINT_EVERY_S if every_s is None else every_s)
        self.resumed: dict[str, int] = {}
        self.state = load_state(self.path, _check_fits, stacklevel=2) or {"done": {}, "current": None}

    def finished(self, label: str) -> tuple[ForceRegressor, dict] | None:
        """The model and history of the fit `label` when it ended before, else None."""
        done = self.state["done"].get(label)
        if done is None:
            return None
        arrays = {k: v.numpy() for k, v in done["weights"].items()}
        return from_arrays(arrays, json.loads(done["config"])), json.loads(done["history"])

    def finish(self, label: str, model: ForceRegressor, history: Mapping) -> None:
        self.state["done"][label] = {"weights": {k: torch.from_numpy(v) for k, v in to_arrays(model).items()},
                                     "config": json.dumps(model.config),
                                     "history": json.dumps(history)}
        self.state["current"] = None
        save_state(self.path, self.state)

    def saved(self, label: str, steps: int, batch_size: int) -> dict | None:
        """The saved state of fit `label` if it was saved by a fit of that length and batch."""
        cur = self.state["current"]
        if cur is None or cur["label"] != label:
            return None
        if (int(cur["steps"]), int(cur["batch_size"])) != (int(steps), int(batch_size)):
            warnings.warn(f"checkpoint {self.path}: fit '{label}' was saved for {cur['steps']} steps "
                          f"of {cur['batch_size']}, not {steps} of {batch_size}; it starts over",
                          stacklevel=3)
            return None
        self.resumed[label] = int(cur["step"])
        return cur

    def progress(self, state: dict) -> None:
        self.state["current"] = state
        save_state(self.path, self.state)


def fit(sequences: list[ContactSequence], config: Mapping | None = None, *, steps: int,
        batch_size: int, lr: float, seed: int = 0, seq_len: int = 32, init: Mapping | None = None,
        momentum: float = 0.9, weight_decay: float = 5e-4, optimizer: str = "sgd",
        threads: int | None = None, desc: str = "force fit", checkpoint: Checkpoint | None = None,
        label: str = "fit") -> tuple[ForceRegressor, dict]:
    """Train a regressor; returns (model in eval mode, on the CPU, history).  It trains on
    stages.common.torch_device (the GPU when torch sees one).

    ``init`` is a :func:`to_arrays` dict to start from (fine-tuning); its config must equal
    ``config``.  An "auto" force range is set from the sequences' labels (model.resolve_range).
    history: loss (per step, normalised L1), seconds, samples_per_s (contact windows),
    frames_per_s, clipped_fraction (labels outside the force range), contacts and frames (of
    `sequences`).
    ``checkpoint``: where the fit named ``label`` saves its state every checkpoint.every_s
    seconds (at a step's end) and its result at its end; a fit that finds its result there
    returns it, one that finds its state resumes from it (:class:`Checkpoint`).
    """
    if not sequences:
        raise ValueError("fit: no training contact sequences")
    if steps < 0 or batch_size < 1 or seq_len < 1:
        raise ValueError(f"fit: steps {steps}, batch_size {batch_size}, seq_len {seq_len} out of range")
    if checkpoint is not None and (done := checkpoint.finished(label)) is not None:
        return done
    given = (len(sequences), int(sum(len(s.force) for s in sequences)))
    all_force = np.concatenate([s.force for s in sequences])
    config = resolve_range(config, all_force)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    model = from_arrays(init, config) if init is not None else ForceRegressor(config)
    lo, hi = np.asarray(config["force_min"]), np.asarray(config["force_max"])
    clipped = float(np.mean(np.any((all_force < lo) | (all_force > hi), axis=1)))
    targets = [model.normalise(s.force) for s in sequences]
    dev = torch_device()
    model.to(dev)
    if optimizer == "sgd":
        opt = torch.optim.SGD(model.parameters(), lr=lr, momentum=momentum, weight_decay=weight_decay)
    elif optimizer == "adamw":
        opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=weight_decay)
    else:
        raise ValueError(f"fit: optimizer {optimizer!r} is not sgd or adamw")
    losses, frames, start, before = [], 0, 0, 0.0
    saved = checkpoint.saved(label, steps, batch_size) if checkpoint is not None else None
    if saved is not None:
        model.load_state_dict(saved["model"])
        opt.load_state_dict(saved["opt"])
        rng.bit_generator.state = saved["rng"]
        torch.set_rng_state(saved["torch"])
        start, frames, before = int(saved["step"]), int(saved["frames"]), float(saved["seconds"])
        losses = saved["loss"].tolist()

    def save(step: int) -> None:
        checkpoint.progress({
            "label": label, "steps": int(steps), "batch_size": int(batch_size), "step": step,
            "frames": frames, "seconds": before + time.perf_counter() - t0,
            "loss": torch.tensor(losses, dtype=torch.float64), "model": model.state_dict(),
            "opt": opt.state_dict(), "rng": rng.bit_generator.state, "torch": torch.get_rng_state()})

    t0 = last = time.perf_counter()
    with torch_threads(threads):
        model.train()
        for step in tqdm(range(start, steps), desc=desc, disable=None, leave=False,
                         initial=start, total=steps):
            for group in opt.param_groups:
                group["lr"] = float(_lr_at(step, steps, lr))
            x, y = _batch(rng, sequences, targets, batch_size, seq_len)
            x, y = x.to(dev), y.to(dev)
            pred, _ = model(x)
            loss = torch.nn.functional.l1_loss(pred, y)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            opt.step()
            losses.append(loss.item())
            frames += x.shape[0] * x.shape[1]
            if checkpoint is not None and step + 1 < steps and \
                    time.perf_counter() - last >= checkpoint.every_s:
                save(step + 1)   # at a step's end: every random stream is where step + 1 starts
                last = time.perf_counter()
    seconds = before + time.perf_counter() - t0
    model.cpu().eval()
    history = {"loss": losses, "seconds": seconds, "steps": int(steps),
               "samples_per_s": steps * batch_size / seconds if seconds > 0 else 0.0,
               "frames_per_s": frames / seconds if seconds > 0 else 0.0,
               "clipped_fraction": clipped, "contacts": given[0], "frames": given[1]}
    if checkpoint is not None:
        checkpoint.finish(label, model, history)
    return model, history


def fit_two_stage(sequences: list[ContactSequence], config: Mapping | None = None, *, steps: int,
                  finetune_steps: int, batch_size: int, lr: float, seed: int = 0,
                  seq_len: int = 32, finetune_lr_factor: float = 0.1, optimizer: str = "sgd",
                  weight_decay: float = 5e-4,
                  init: Mapping | None = None, desc: str = "force fit", checkpoint: Checkpoint | None = None,
                  label: str = "fit") -> tuple[ForceRegressor, dict]:
    """Pretrain (`steps` at `lr`), then fine-tune the result (`finetune_steps` at
    `lr * finetune_lr_factor`) on the same sequences: the paper's two stages (0.1, then 1e-3).
    With a `checkpoint`, the stages are the fits `<label>/pretrain` and `<label>/finetune`."""
    model, hist = fit(sequences, config, steps=steps, batch_size=batch_size, lr=lr, seed=seed,
                      seq_len=seq_len, init=init, desc=f"{desc} (pretrain)", optimizer=optimizer,
                      weight_decay=weight_decay,
                      checkpoint=checkpoint, label=f"{label}/pretrain")
    history = {"pretrain": hist}
    if finetune_steps > 0:
        model, hist2 = fit(sequences, model.config, steps=finetune_steps, batch_size=batch_size,
                           lr=lr * finetune_lr_factor, seed=seed + 1, seq_len=seq_len,
                           init=to_arrays(model), desc=f"{desc} (fine-tune)", optimizer=optimizer,
                           weight_decay=weight_decay,
                           checkpoint=checkpoint, label=f"{label}/finetune")
        history["finetune"] = hist2
    return model, history


def loss_figure(histories: Mapping[str, Mapping], title: str):
    """PNG bytes: training loss per step for each named history (two-stage runs joined)."""
    from matplotlib.figure import Figure

    from stages.figures import figure_png
    fig = Figure(figsize=(5, 3.2))
    ax = fig.add_subplot()
    for name, hist in histories.items():
        stages = [hist[k] for k in ("pretrain", "finetune") if k in hist] or [hist]
        loss = np.concatenate([np.asarray(s["loss"], float) for s in stages])
        if loss.size:
            k = max(1, loss.size // 50)
            smooth = np.convolve(loss, np.ones(k) / k, mode="valid")
            ax.plot(np.arange(smooth.size) + k - 1, smooth, label=name)
        if len(stages) == 2:
            ax.axvline(len(stages[0]["loss"]) - 0.5, color="0.6", lw=0.8, ls=":")
    ax.set(xlabel="step", ylabel="L1 (normalised force)", title=title, yscale="log")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return figure_png(fig)
