"""The M2M generator: one image-conditioned network for every source -> target pair.

The paper's M2M is a one-step diffusion model (SD-Turbo at a fixed timestep) conditioned on
the target sensor's reference image.  This is a CPU-sized version of the same idea:

* Input channels [x_t, source image, source reference, target reference], images scaled to
  [-1, 1].  Conditioning on the source reference as well lets the network read the source's
  deformation as (image - reference) rather than having to know every source pattern.
* A compact UNet: pixel-unshuffle by 2 (so the first level runs at H/2 with 16 channels
  instead of H with 4), three levels of `width`, 2x`width`, 4x`width` channels, GroupNorm,
  SiLU, residual blocks with a scale-shift timestep embedding, skip connections,
  pixel-shuffle back to full resolution.  Its receptive field (~100 px through the bottom level)
  spans several marker pitches, enough to carry the displacement of a neighbourhood of
  source markers onto the target markers in between.
* It predicts the target marker image x0 as logits (probability = sigmoid); binary 0/255
  images are the probability thresholded at 0.5.  The logits are a residual on the target
  reference (ref_gain x reference + network output), so the network learns the edits the
  deformation makes to the target's markers rather than first learning to copy them.
* Diffusion: a DDPM linear beta schedule over `timesteps` steps.  The one-step generator
  (the paper's formulation) evaluates the network once at the fixed timestep T-1 on
  x_T = 0, the mean of pure noise: deterministic, and trained exactly that way (feeding a
  noise sample instead makes a small network spend its budget learning to ignore it).  The
  optional multi-step sampler re-noises the x0 estimate to smaller timesteps and predicts
  again, as SD-Turbo's multi-step mode does; its noise maps are fixed-seed and shared by all
  images, so a translation never depends on batching.

Weights are stored as a flat mapping parameter name -> numpy array; `config` (JSON-able)
rebuilds the network.  `load_translator` turns a model artifact into a `Translator`.
Training and translation run on the GPU when torch sees one (the paper profile), else on the
CPU; weights always come back to the CPU as float32 arrays.
"""
from __future__ import annotations

import math
from typing import Mapping

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from stages.common import attrs_of, marker_images, torch_device

NOISE_SEED = 1234          # seed of the multi-step sampler's noise maps (NOISE_SEED + step)


def device() -> torch.device:
    """Where the networks run: the GPU when torch sees one (paper profile), else the CPU
    (stages.common.torch_device: $GENFORCE_DEVICE chooses)."""
    return torch_device()


def default_config(*, size=(128, 128), width: int = 16, timesteps: int = 1000) -> dict:
    """Everything needed to rebuild the network (stored in the model artifact's attrs)."""
    return {"size": [int(v) for v in size], "width": int(width), "mults": [1, 2, 4],
            "timesteps": int(timesteps), "beta_start": 1e-4, "beta_end": 2e-2}


def _groups(c: int) -> int:
    return math.gcd(8, c)


class ResBlock(nn.Module):
    def __init__(self, c_in: int, c_out: int, emb: int):
        super().__init__()
        self.norm1, self.conv1 = nn.GroupNorm(_groups(c_in), c_in), nn.Conv2d(c_in, c_out, 3, padding=1)
        self.emb = nn.Linear(emb, 2 * c_out)
        self.norm2, self.conv2 = nn.GroupNorm(_groups(c_out), c_out), nn.Conv2d(c_out, c_out, 3, padding=1)
        self.skip = nn.Conv2d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x, emb):
        h = self.conv1(F.silu(self.norm1(x)))
        scale, shift = self.emb(emb)[:, :, None, None].chunk(2, dim=1)
        h = self.norm2(h) * (1 + scale) + shift
        return self.skip(x) + self.conv2(F.silu(h))


class M2MNet(nn.Module):
    """x0-predicting UNet; forward(x_t, cond, t) -> logits (B,1,H,W).
    cond = (source image, source reference, target reference) stacked on channels, in [-1, 1]."""

    def __init__(self, config: Mapping):
        super().__init__()
        w, mults = int(config["width"]), list(config["mults"])
        if len(mults) != 3:
            raise ValueError(f"mults must have 3 levels, got {mults}")
        c0, c1, c2 = (w * m for m in mults)
        self.emb_dim = emb = 4 * w
        self.time = nn.Sequential(nn.Linear(w, emb), nn.SiLU(), nn.Linear(emb, emb))
        self.stem = nn.Conv2d(16, c0, 3, padding=1)
        self.enc0, self.down0 = ResBlock(c0, c0, emb), nn.Conv2d(c0, c1, 3, stride=2, padding=1)
        self.enc1, self.down1 = ResBlock(c1, c1, emb), nn.Conv2d(c1, c2, 3, stride=2, padding=1)
        self.mid1, self.mid2 = ResBlock(c2, c2, emb), ResBlock(c2, c2, emb)
        self.up1, self.dec1 = nn.Conv2d(c2, c1, 3, padding=1), ResBlock(2 * c1, c1, emb)
        self.up0, self.dec0 = nn.Conv2d(c1, c0, 3, padding=1), ResBlock(2 * c0, c0, emb)
        self.out_norm, self.out = nn.GroupNorm(_groups(c0), c0), nn.Conv2d(c0, 4, 3, padding=1)
        # logits start from the target reference: the network learns the edits that the
        # deformation makes to it instead of first learning to copy it
        self.ref_gain = nn.Parameter(torch.tensor(3.0))
        self.width = w

    def embed_time(self, t: torch.Tensor) -> torch.Tensor:
        half = self.width // 2
        freqs = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
        ang = t.float()[:, None] * freqs[None]
        return self.time(torch.cat([ang.sin(), ang.cos()], dim=1))

    def forward(self, x_t, cond, t):
        if x_t.shape[-1] % 8 or x_t.shape[-2] % 8:
            raise ValueError(f"image size {tuple(x_t.shape[-2:])} must be a multiple of 8")
        emb = self.embed_time(t)
        h = self.stem(F.pixel_unshuffle(torch.cat([x_t, cond], dim=1), 2))
        s0 = self.enc0(h, emb)
        s1 = self.enc1(self.down0(s0), emb)
        h = self.mid2(self.mid1(self.down1(s1), emb), emb)
        h = self.dec1(torch.cat([self.up1(F.interpolate(h, scale_factor=2.0)), s1], 1), emb)
        h = self.dec0(torch.cat([self.up0(F.interpolate(h, scale_factor=2.0)), s0], 1), emb)
        return F.pixel_shuffle(self.out(F.silu(self.out_norm(h))), 2) + self.ref_gain * cond[:, 2:3]


# ------------------------------------------------------------------------- diffusion

def alphas_cumprod(config: Mapping) -> torch.Tensor:
    """alpha-bar_t for t = 0..T-1 of the linear DDPM schedule."""
    betas = torch.linspace(config["beta_start"], config["beta_end"], int(config["timesteps"]),
                           dtype=torch.float64)
    return torch.cumprod(1.0 - betas, 0).float()


def noise_map(shape, seed: int = NOISE_SEED) -> torch.Tensor:
    """One fixed N(0,1) map (1,1,H,W), shared by every image of a translation."""
    g = torch.Generator().manual_seed(int(seed))
    return torch.randn((1, 1, *shape), generator=g)


def sampler_timesteps(config: Mapping, steps: int) -> list[int]:
    """The timesteps a sampler with `steps` network evaluations visits: T-1 first, then
    evenly spaced down to 0."""
    steps = int(steps)
    if steps < 1:
        raise ValueError(f"sampler steps must be >= 1, got {steps}")
    T = int(config["timesteps"])
    return sorted({int(t) for t in np.linspace(T - 1, 0, steps).round()}, reverse=True)


@torch.no_grad()
def sample(net: M2MNet, cond: torch.Tensor, config: Mapping, steps: int = 1) -> torch.Tensor:
    """Target-marker probabilities (B,1,H,W) for conditions cond (B,3,H,W).

    The first evaluation is the one-step generator: x_T = 0 (the mean of pure noise) at
    t = T-1.  Each further step re-noises the current x0 estimate to the next, smaller
    timestep with a fixed noise map and predicts x0 again (the multi-step sampling of
    one-step distilled models such as SD-Turbo)."""
    abar = alphas_cumprod(config).to(cond.device)
    b, _, h, w = cond.shape
    prob = None
    for i, t in enumerate(sampler_timesteps(config, steps)):
        if prob is None:
            x = torch.zeros(b, 1, h, w, device=cond.device)
        else:
            noise = noise_map((h, w), NOISE_SEED + i).to(cond.device)
            x = abar[t].sqrt() * (2 * prob - 1) + (1 - abar[t]).sqrt() * noise
        prob = torch.sigmoid(net(x, cond, torch.full((b,), t, dtype=torch.long, device=cond.device)))
    return prob


# ------------------------------------------------------------------------- weights

def state_arrays(net: nn.Module) -> dict[str, np.ndarray]:
    """Parameters and buffers as float32 numpy arrays (what the store keeps)."""
    return {k: v.detach().cpu().numpy().astype(np.float32, copy=True) for k, v in net.state_dict().items()}


def build(config: Mapping, weights: Mapping | None = None) -> M2MNet:
    """The network for `config`, loaded with `weights` (name -> array) when given."""
    net = M2MNet(config)
    if weights is not None:
        state = net.state_dict()
        missing = sorted(set(state) - set(weights))
        extra = sorted(set(weights) - set(state))
        shape = sorted(k for k in set(state) & set(weights) if tuple(np.shape(weights[k])) != tuple(state[k].shape))
        if missing or extra or shape:
            raise KeyError(f"weights do not fit the M2M config: missing {missing[:3]}, unexpected {extra[:3]}, "
                           f"wrong shape {shape[:3]}")
        net.load_state_dict({k: torch.from_numpy(np.array(weights[k], np.float32)) for k in state})
    return net.eval()


def weights_of(model) -> dict[str, np.ndarray]:
    """name -> array from a model artifact: a nested {"weights": {...}} mapping as a node
    returns it, or the flattened "weights/<name>" datasets of a store artifact."""
    w = model["weights"] if "weights" in model and isinstance(model["weights"], Mapping) else None
    if w is not None:
        return {k: np.asarray(v) for k, v in w.items()}
    out = {k[len("weights/"):]: np.asarray(model[k]) for k in model if str(k).startswith("weights/")}
    if not out:
        raise KeyError("model artifact has no 'weights' datasets")
    return out


# ------------------------------------------------------------------------- translator

def _to_unit(images: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(images, np.float32)) / 127.5 - 1.0


def _resize(images: np.ndarray, size) -> np.ndarray:
    """Binary images (N,H,W) to size (h,w): area-average, re-threshold at half coverage."""
    h, w = size
    if images.shape[-2:] == (h, w):
        return images
    if len(images) == 0:
        return np.zeros((0, h, w), np.uint8)
    import cv2
    interp = cv2.INTER_AREA if images.shape[-2] > h else cv2.INTER_LINEAR
    out = np.stack([cv2.resize(np.ascontiguousarray(im), (w, h), interpolation=interp) for im in images])
    return np.where(out >= 128, 255, 0).astype(np.uint8)


class Translator:
    """Runs a trained M2M network on uint8 marker images."""

    def __init__(self, config: Mapping, weights: Mapping):
        self.config = dict(config)
        self.device = device()
        self.net = build(self.config, weights).to(self.device)
        self.size = tuple(self.config["size"])

    def probabilities(self, images, source_reference, target_reference, steps: int = 1,
                      batch: int = 64) -> np.ndarray:
        """Target-marker probability (N,h,w) float32 at the model's size."""
        images = marker_images(images, "translator images")
        if images.ndim == 2:
            images = images[None]
        source_reference = marker_images(source_reference, "translator source_reference", (2,))
        target_reference = marker_images(target_reference, "translator target_reference", (2,))
        if source_reference.shape != images.shape[1:]:
            raise ValueError(f"translator: images {images.shape} and source_reference {source_reference.shape} "
                             "must be (N,H,W) and (H,W)")
        refs = np.stack([_resize(source_reference[None], self.size)[0], _resize(target_reference[None], self.size)[0]])
        refs_t = _to_unit(refs).to(self.device)
        out = []
        with torch.inference_mode():
            for i in range(0, len(images), batch):
                src = _to_unit(_resize(images[i:i + batch], self.size))[:, None].to(self.device)
                cond = torch.cat([src, refs_t[None].expand(len(src), 2, *self.size)], 1)
                out.append(sample(self.net, cond, self.config, steps)[:, 0].cpu().numpy())
        return np.concatenate(out) if out else np.zeros((0, *self.size), np.float32)

    def translate(self, images, source_reference, target_reference, steps: int = 1,
                  batch: int = 64) -> np.ndarray:
        """Source marker images (N,H,W) uint8 -> the same deformations in the target's marker
        style, (N,H',W') uint8 0/255 at the target reference's size."""
        target_reference = marker_images(target_reference, "translator target_reference", (2,))
        prob = self.probabilities(images, source_reference, target_reference, steps, batch)
        binary = np.where(prob >= 0.5, 255, 0).astype(np.uint8)
        return _resize(binary, target_reference.shape)


def load_translator(model) -> Translator:
    """A Translator from an M2M model artifact (node m2m_sim / m2m, or their return value)."""
    attrs = attrs_of(model)
    config = attrs.get("config")
    if not isinstance(config, Mapping) or not {"size", "width", "timesteps"} <= set(config):
        raise ValueError("load_translator: not an M2M model artifact (node m2m_sim or m2m): its 'config' "
                         f"attribute {'is missing' if config is None else 'lacks size/width/timesteps'}")
    return Translator(attrs["config"], weights_of(model))
