"""Training the M2M generator on location-paired marker images.

A training example is a paired frame f and two different skins a, b: the input is a's image
at f with the references of a and b, the target is b's image at f.  All skins are held in
memory as uint8 (S, K, H, W): at 128x128, 12 skins x 540 frames is 106 MB.  Every example is
turned by one of the 8 square symmetries (4 when the images are not square), the same for all
four images: the deformation-transfer it teaches is equivariant to them, and it multiplies the
few pairs a fine-tune sees.

Diffusion training: half of each batch is the one-step case (t = T-1, x_T = 0), the rest
draws t uniformly below it with x_t the noised target, so the same weights serve the
one-step generator and the multi-step sampler (model.sample).  The x0 loss
replaces the paper's 5*MSE + LPIPS + 0.5*GAN: binary cross-entropy on the marker logits
(the pixel term, exact for binary targets) plus a soft Dice term on marker probability (the
shape term: it weighs the ~10% of marker pixels as much as the background, which LPIPS did
for the paper's thin dots).  The fine-tune weighs the BCE of the pixels a deformation changed
(change_share, stages.m2m.fit.CHANGE_SHARE): without it a copy of the target reference is
almost free at light contact, where a GelSight contact changes about 1% of the image, and
M2M draws small marker motion too small, which the force model then reads as too little
force.  The weight is set per target skin from the mean share of its pixels the deformation
changes (a 3-axis uSkin contact changes about 12% of its image and is left unweighted).
No adversarial term: outputs are thresholded to binary images, so the blur a GAN fights
does not reach the artifacts.
"""
from __future__ import annotations

import time
from typing import Callable

import numpy as np
import torch
from torch.nn import functional as F

from stages.common import load_state, save_state
from stages.m2m.model import M2MNet, alphas_cumprod, device

ONESTEP_FRACTION = 0.5     # share of each batch trained at the one-step timestep T-1
DICE_WEIGHT = 1.0
WEIGHT_DECAY = 1e-4
WARMUP = 0.03              # share of the steps with a linear learning-rate warm-up


class PairBatches:
    """Random (condition, target) batches from paired images (S,K,H,W) and references (S,H,W):
    the target skin and the frame evenly, the source any other skin, evenly.
    `changed_fraction` (S,): per skin, the mean share of pixels whose binary value differs
    from its reference; `last_b`: the target skins of the last batch drawn (fit's change_share
    reads the two)."""

    def __init__(self, images: np.ndarray, references: np.ndarray, seed: int):
        if images.ndim != 4 or references.shape != (images.shape[0], *images.shape[2:]):
            raise ValueError(f"images (S,K,H,W) and references (S,H,W) expected, got "
                             f"{images.shape} and {references.shape}")
        self.images, self.refs = images, references
        self.rng = np.random.default_rng(seed)
        self.square = images.shape[2] == images.shape[3]
        self.changed_fraction = np.array([float(((im > 127) != (ref > 127)[None]).mean())
                                          for im, ref in zip(images, references)], np.float32)
        self.last_b = None

    def __call__(self, batch: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(condition (B,3,H,W) in [-1,1], binary target (B,1,H,W))."""
        s, k = self.images.shape[:2]
        f = self.rng.integers(0, k, batch)
        a = self.rng.integers(0, s, batch)
        # b != a whenever there are two skins to choose from
        b = (a + self.rng.integers(1, s, batch)) % s if s > 1 else a
        self.last_b = b
        stack = np.stack([self.images[a, f], self.refs[a], self.refs[b], self.images[b, f]], 1)
        stack = np.stack([self._symmetry(x, int(g)) for x, g in
                          zip(stack, self.rng.integers(0, 8 if self.square else 4, batch))])
        x = torch.from_numpy(stack.astype(np.float32)) / 127.5 - 1.0
        return x[:, :3], (x[:, 3:] > 0).float()

    def state(self) -> dict:
        """The random stream's state (fit's checkpoints): restore() continues it exactly."""
        return self.rng.bit_generator.state

    def restore(self, state: dict) -> None:
        self.rng.bit_generator.state = state

    @staticmethod
    def _symmetry(x: np.ndarray, g: int) -> np.ndarray:
        """One of the dihedral group's elements on (C,H,W): flips by g's bits 0-1, transpose by bit 2."""
        if g & 1:
            x = x[:, ::-1]
        if g & 2:
            x = x[:, :, ::-1]
        if g & 4:
            x = x.transpose(0, 2, 1)
        return np.ascontiguousarray(x)


def loss_fn(logits: torch.Tensor, target: torch.Tensor, reference=None, change_share: float = 0.0,
            changed_fraction=None) -> torch.Tensor:
    """BCE on logits + DICE_WEIGHT * (1 - soft Dice) of the marker probability.

    With a target `reference` (binary, like target) and change_share s > 0, the BCE of every
    pixel the deformation changed (target != reference) weighs w = max(1, s/(1-s) * (1-c)/c),
    c = `changed_fraction` (B,): the target skin's mean changed share of pixels (at least one
    pixel's).  At its mean contact a skin's changed pixels then carry the share s of the BCE:
    one whose contacts change 1% of the image gets w ~ 11 at s = 0.1, one whose taxel dots
    change 12% of it w = 1.  Each example's BCE is the w-weighted mean of its pixels; the
    batch's the mean of those."""
    if reference is None or change_share == 0:
        bce = F.binary_cross_entropy_with_logits(logits, target)
    else:
        changed = (target - reference).abs()
        n = changed[0].numel()
        frac = changed_fraction.to(changed).reshape(-1, 1, 1, 1).clamp(min=1.0 / n)
        share = change_share / (1 - change_share) * (1 - frac) / frac
        w = 1.0 + (share.clamp(min=1.0) - 1.0) * changed
        per_pixel = F.binary_cross_entropy_with_logits(logits, target, reduction="none")
        bce = ((per_pixel * w).sum((1, 2, 3)) / w.sum((1, 2, 3))).mean()
    prob = torch.sigmoid(logits)
    inter = (prob * target).sum((1, 2, 3))
    dice = (2 * inter + 1) / (prob.sum((1, 2, 3)) + target.sum((1, 2, 3)) + 1)
    return bce + DICE_WEIGHT * (1 - dice.mean())


CHECKPOINT_EVERY_S = 60.0   # fit(checkpoint=...): seconds between saves of the training state


def _load_checkpoint(path: str, *, steps: int, batch_size: int) -> dict | None:
    """The state saved by fit at `path`, or None when there is none; one that cannot be read or
    was saved by a fit of another length or batch is renamed <path>.bad with a warning."""
    def check(state: dict) -> None:
        if (int(state["steps"]), int(state["batch_size"])) != (int(steps), int(batch_size)):
            raise ValueError(f"saved for {state['steps']} steps of {state['batch_size']}, "
                             f"not {steps} of {batch_size}")
        if not 0 < int(state["step"]) < int(steps):
            raise ValueError(f"step {state['step']} is outside 1..{steps - 1}")
    return load_state(path, check, stacklevel=3)


def noisy_input(target: torch.Tensor, config, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """(x_t, t) for a batch: one-step examples at T-1 with x_T = 0 (model.sample's first
    step), the rest at a uniform t < T-1 with x_t = sqrt(abar) x0 + sqrt(1 - abar) noise."""
    T = int(config["timesteps"])
    b = target.shape[0]
    t = torch.randint(0, max(T - 1, 1), (b,), generator=gen)
    onestep = torch.rand(b, generator=gen) < ONESTEP_FRACTION
    t[onestep] = T - 1
    abar = alphas_cumprod(config)[t][:, None, None, None]
    eps = torch.randn(target.shape, generator=gen)
    x_t = abar.sqrt() * (2 * target - 1) + (1 - abar).sqrt() * eps
    x_t[onestep] = 0.0
    return x_t, t


def fit(net: M2MNet, config, batches: Callable, *, steps: int, batch_size: int, lr: float,
        seed: int, progress: str = "m2m", change_share: float = 0.0,
        checkpoint: str | None = None, checkpoint_every_s: float = CHECKPOINT_EVERY_S) -> dict:
    """AdamW with warm-up and cosine decay; `batches(b)` gives (condition, target) as
    PairBatches does.  change_share > 0: the loss weighs the changed pixels (loss_fn; the
    target reference is the condition's third channel, the target skin's changed fraction
    PairBatches' changed_fraction of its last_b).

    `checkpoint`: a file where the whole training state (weights, optimiser, schedule, step,
    losses and every random stream, `batches.state()` included) is saved at the end of a step
    every `checkpoint_every_s` seconds, so an interrupted fit (Ctrl-C, a killed job, a lost
    machine) loses at most that much; a fit that finds one resumes from it and ends with the
    weights an uninterrupted fit gives.  A checkpoint that cannot be read, or that
    belongs to another run length, is set aside with a warning and the fit starts over.
    Returns {"loss": (steps,) float32, "seconds", "steps_per_s", "resumed_at"}."""
    from tqdm import tqdm
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    dev = device()
    net.to(dev)
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=WEIGHT_DECAY)
    warm = max(1, int(WARMUP * steps))
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda i: float(min(1.0, (i + 1) / warm) * 0.5 * (1 + np.cos(np.pi * min(i, steps) / max(steps, 1)))))
    losses = np.zeros(steps, np.float32)
    start, before = 0, 0.0
    if checkpoint:
        state = _load_checkpoint(checkpoint, steps=steps, batch_size=batch_size)
        if state is not None:
            net.load_state_dict(state["net"])
            opt.load_state_dict(state["opt"])
            sched.load_state_dict(state["sched"])
            gen.set_state(state["gen"])
            torch.set_rng_state(state["torch"])
            batches.restore(state["batches"])
            start, before = int(state["step"]), float(state["seconds"])
            losses[:start] = state["loss"][:start].numpy()

    def save(i: int) -> None:
        save_state(checkpoint, {
            "steps": int(steps), "batch_size": int(batch_size), "step": i,
            "seconds": before + time.perf_counter() - t0, "loss": torch.from_numpy(losses.copy()),
            "net": net.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(),
            "gen": gen.get_state(), "torch": torch.get_rng_state(), "batches": batches.state()})

    net.train()
    t0 = last = time.perf_counter()
    for i in tqdm(range(start, steps), desc=progress, disable=None, initial=start, total=steps):
        cond, target = batches(batch_size)
        x_t, t = noisy_input(target, config, gen)
        cond, target, x_t, t = cond.to(dev), target.to(dev), x_t.to(dev), t.to(dev)
        if change_share:
            frac = torch.from_numpy(batches.changed_fraction[batches.last_b])
            loss = loss_fn(net(x_t, cond, t), target, (cond[:, 2:3] > 0).float(), change_share, frac)
        else:
            loss = loss_fn(net(x_t, cond, t), target)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        losses[i] = loss.item()
        if checkpoint and i + 1 < steps and time.perf_counter() - last >= checkpoint_every_s:
            save(i + 1)      # at a step's end: every random stream is where step i + 1 starts
            last = time.perf_counter()
    seconds = before + time.perf_counter() - t0
    net.cpu().eval()
    return {"loss": losses, "seconds": seconds, "steps_per_s": (steps - start) / max(seconds - before, 1e-9),
            "resumed_at": start}
