"""M2M's training nodes: m2m_sim (pretrain: the generator trained from scratch on the
simulation patterns) and m2m (finetune: the same weights fine-tuned on location-paired
frames of the twins or of the authors' sensors)."""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from stages.common import attrs_of, torch_threads
from stages.figures import contact_sheet, figure_png, png
from stages.m2m.data import paired_table, read_rows, styles

N_EXAMPLES = 4          # rows of the examples figure


def _paired_arrays(markers: Mapping, skins: Sequence[str], rows: np.ndarray, size) -> tuple[np.ndarray, np.ndarray]:
    """Images (S,K,h,w) at the rows of the paired table and references (S,h,w), at `size`."""
    from stages.m2m.model import _resize
    images = np.stack([_resize(read_rows(markers[s]["images"], r), size) for s, r in zip(skins, rows)])
    refs = np.stack([_resize(np.asarray(markers[s]["reference"], np.uint8)[None], size)[0] for s in skins])
    return images, refs


def _loss_figure(loss: np.ndarray, title: str):
    from matplotlib.figure import Figure
    fig = Figure(figsize=(6, 3.5))
    ax = fig.subplots()
    ax.plot(loss, lw=0.5, alpha=0.4, color="C0")
    k = max(1, len(loss) // 50)
    if len(loss) >= k:
        smooth = np.convolve(loss, np.ones(k) / k, mode="valid")
        ax.plot(np.arange(len(smooth)) + k - 1, smooth, color="C0", label=f"mean of {k}")
    ax.set_xlabel("step")
    ax.set_ylabel("BCE + Dice loss")
    ax.set_yscale("log")
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    return fig


def _samples_sheet(translator, images: np.ndarray, refs: np.ndarray, seed: int) -> np.ndarray:
    """Rows of source | translated | target for random training pairs (one per row)."""
    rng = np.random.default_rng(seed)
    s, k = images.shape[:2]
    tiles = []
    for _ in range(N_EXAMPLES):
        a, f = int(rng.integers(s)), int(rng.integers(k))
        b = int((a + rng.integers(1, s)) % s) if s > 1 else a
        out = translator.translate(images[a, f][None], refs[a], refs[b])[0]
        tiles += [images[a, f], out, images[b, f]]
    return contact_sheet(tiles, cols=3)


def _one_per_style(skins: Sequence[str], images: np.ndarray, refs: np.ndarray):
    """The skins of distinct marker styles (stages.m2m.data.styles), their images and
    references, and {skin: the skin whose style it shares} for the rest.  The generator knows a
    target only by its reference, so sensors of one layout are one target: the first of them
    stands for the style, and a translation between them is the identity (translate_sequence)."""
    first = styles(list(refs))
    keep = [i for i, j in enumerate(first) if i == j]
    merged = {skins[i]: skins[j] for i, j in enumerate(first) if i != j}
    return [skins[i] for i in keep], images[keep], refs[keep], merged


def _train(net, config, markers, skins, train_indenters, per_skin, steps, batch_size, lr, seed,
           title, checkpoint=None, change_share=0.0):
    from stages.m2m.model import Translator, state_arrays
    from stages.m2m.train import PairBatches, fit
    frames, rows = paired_table(markers, skins, train_indenters, per_skin)
    kept, images, refs, merged = _one_per_style(list(skins), *_paired_arrays(markers, skins, rows,
                                                                              config["size"]))
    trainable = len(kept) > 1
    if trainable:
        with torch_threads():
            batches = PairBatches(images, refs, seed)
            hist = fit(net, config, batches, steps=int(steps), batch_size=int(batch_size), lr=float(lr),
                       seed=int(seed), progress=title, checkpoint=checkpoint,
                       change_share=float(change_share))
            weights = state_arrays(net)
            samples = _samples_sheet(Translator(config, weights), images, refs, seed)
        figures = {"loss": figure_png(_loss_figure(hist["loss"], title)), "samples": png(samples)}
    else:       # every skin of one marker style: nothing to translate, so the weights stay
        steps, weights, figures = 0, state_arrays(net), {}
        hist = {"loss": np.zeros(0, np.float32), "seconds": 0.0, "steps_per_s": 0.0, "resumed_at": 0}
    tail = hist["loss"][-max(1, len(hist["loss"]) // 20):]
    return {
        "weights": weights,
        "loss": hist["loss"],
        "figures": figures,
        "attrs": {"config": config, "skins": list(skins), "train_indenters": list(train_indenters),
                  "pairs": int(len(frames)), "steps": int(steps), "batch_size": int(batch_size),
                  "lr": float(lr), "seed": int(seed),
                  "final_loss": float(np.mean(tail)) if len(tail) else float("nan"),
                  "parameters": int(sum(v.size for v in weights.values())),
                  **({"same_style": merged} if merged else {})},
        "timing": {"seconds": round(hist["seconds"], 2), "steps_per_s": round(hist["steps_per_s"], 3),
                   "resumed_at_step": int(hist["resumed_at"])},
    }


# The fine-tune's change share (stages.m2m.train.loss_fn): the BCE's share on the pixels a
# contact changes, at a skin's mean contact.  Chosen on the validation indenters' force error
# of the methods trained on the translations (mae_total and the light-contact mae_fz_light);
# the pretrain on the simulated patterns keeps the plain BCE.
CHANGE_SHARE = 0.1


def pretrain(*, markers: Mapping, skins: list[str], train_indenters: list[str], size, steps: int,
             batch_size: int, lr: float, seed: int, width: int, timesteps: int,
             checkpoint: str | None = None) -> dict:
    """Node m2m_sim: the generator trained from scratch on every ordered pair of `skins`
    (location-paired frames of the training indenters).  Returns weights (name -> array),
    the per-step loss, figures loss/samples and attrs (config to rebuild the model, ...).
    checkpoint: where the training saves its state as it goes (the worker gives a path per
    cache key), so an interrupted run resumes (train.fit)."""
    import torch
    from stages.m2m.model import build, default_config
    config = default_config(size=size, width=width, timesteps=timesteps)
    torch.manual_seed(int(seed))
    net = build(config)
    return _train(net, config, markers, skins, train_indenters, 0, steps, batch_size, lr, seed,
                  "m2m pretrain", checkpoint=checkpoint)


def finetune(*, base, markers: Mapping, train_indenters: list[str], pairs_per_skin: int, steps: int,
             batch_size: int, lr: float, seed: int, skins: list[str] | None = None,
             fit: str | None = None, checkpoint: str | None = None) -> dict:
    """Node m2m[fit]: `base` (a pretrained model) fine-tuned on `pairs_per_skin` location-paired
    frames shared by `skins` (default: every one of `markers`, in its order: one fine-tune's
    sensors, collected along the same contacts), evenly spread over the training indenters'
    frames.  Skins of one marker style are one target, the first of them standing for it
    (attrs same_style: skin -> that first one); a set of one style trains nothing.  `fit`
    names the fine-tune (the grid's: the twin, or one of the authors' sets).
    checkpoint: as pretrain's."""
    from stages.m2m.model import build, weights_of
    config = attrs_of(base)["config"]
    net = build(config, weights_of(base))
    out = _train(net, config, markers, list(markers) if skins is None else skins, train_indenters,
                 int(pairs_per_skin), steps, batch_size, lr, seed,
                 "m2m finetune" + (f" {fit}" if fit else ""), checkpoint, CHANGE_SHARE)
    out["attrs"]["base_skins"] = list(attrs_of(base).get("skins", []))
    out["attrs"]["pairs_per_skin"] = int(pairs_per_skin)
    if fit is not None:
        out["attrs"]["fit"] = str(fit)
    return out
