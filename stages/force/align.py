"""Paired batch-norm alignment: a transferred regressor reads the target's own frames as it
reads their translations.

A transfer's regressor learns from translations, and the target's real frames differ from
them (M2M draws a marker a little off, a light touch's motion too small): the features a
real frame makes in the network are shifted and scaled against those of its translation.
GenForce has pairs that show this with no force label: the few location-paired frames that
fine-tune M2M, the target's real frame beside the source's frame of the same location,
which translates into the target's style.  Fed both through the trained network, the two
sets of each batch-norm layer's inputs differ by the domain gap alone (same locations,
same contacts).

:func:`align_batchnorm` moves each such layer's running statistics so that the target's
paired frames are normalised to where the translations of the same frames are: with
mu_g, s_g and mu_t, s_t the per-channel mean and standard deviation of the layer's input on
the translated and the target frames, and mu, s the running statistics,

    (x_t - mu_t) / s_t * s_g + mu_g, normalised by (mu, s)
        = x_t normalised by (mu_t + (mu - mu_g) s_t / s_g,  s s_t / s_g)

layer after layer (each layer's target statistics measured through the layers already
aligned), so a target input that is an affine copy of its translation's gets the
translation's output.  Only the encoder's layers, which see one frame at a time, are aligned
by default: the head's inputs depend on the GRU state over a whole contact, which single
paired frames do not show.  Weights are untouched; this is AdaBN (Li et al., 2016) with the
source statistics taken from paired frames rather than the whole training set, so that a
difference of content (deeper presses among the paired frames) is not read as a domain gap.
"""
from __future__ import annotations

import copy

import numpy as np
import torch

from stages.force.model import ForceRegressor, prepare

LAYERS = ("encoder", "all")   # which batch-norm layers align_batchnorm moves


def _batchnorms(model: ForceRegressor, layers: str) -> list[torch.nn.BatchNorm2d]:
    if layers not in LAYERS:
        raise ValueError(f"align layers {layers!r}: expected one of {LAYERS}")
    parts = [model.encoder] if layers == "encoder" else [model.encoder, model.head]
    return [m for p in parts for m in p.modules() if isinstance(m, torch.nn.BatchNorm2d)]


@torch.no_grad()
def _input_stats(model: ForceRegressor, norms, x: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Per-channel (mean, variance) of every layer of `norms`' input, frames x (N,C,S,S) fed as
    N one-frame sequences."""
    stats: list = [None] * len(norms)

    def hook(i):
        def record(_, inputs):
            v = inputs[0].double()
            stats[i] = (v.mean((0, 2, 3)), v.var((0, 2, 3), unbiased=False))
        return record
    handles = [m.register_forward_pre_hook(hook(i)) for i, m in enumerate(norms)]
    try:
        model.eval()
        model(x[:, None].to(model.force_min.device))
    finally:
        for h in handles:
            h.remove()
    return stats


@torch.no_grad()
def align_batchnorm(model: ForceRegressor, translated, target, reference, *,
                    layers: str = "encoder") -> ForceRegressor:
    """A copy of `model` whose batch-norm layers (`layers`: "encoder" or "all") read the target's
    frames `target` (K,H,W) uint8 as it reads `translated` (K,H,W), their location-paired
    translations (frame k of one beside frame k of the other); `reference` (H,W) is the
    target's no-contact image, which both sets are prepared against."""
    translated, target = np.asarray(translated), np.asarray(target)
    if translated.shape != target.shape or translated.ndim != 3 or len(target) < 2:
        raise ValueError(f"align_batchnorm: paired frames {translated.shape} and {target.shape} must be "
                         "two (K,H,W) stacks of the same shape with K >= 2")
    out = copy.deepcopy(model)
    norms = _batchnorms(out, layers)
    g = _input_stats(out, norms, prepare(translated, reference, out.config))
    xt = prepare(target, reference, out.config)
    for i, bn in enumerate(norms):
        mu_t, var_t = _input_stats(out, norms, xt)[i]
        mu_g, var_g = g[i]
        ratio = torch.sqrt((var_t + bn.eps) / (var_g + bn.eps))
        mean = mu_t + (bn.running_mean.double() - mu_g) * ratio
        bn.running_mean.copy_(mean.to(bn.running_mean.dtype))
        bn.running_var.copy_((bn.running_var.double() * ratio ** 2).to(bn.running_var.dtype))
    return out.eval()
