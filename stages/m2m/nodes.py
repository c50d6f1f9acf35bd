"""Node functions of the M2M part of the pipeline.

  m2m_sim            pretrain          the generator, trained from scratch on the sim patterns
  m2m                finetune          the same weights fine-tuned on a few pairs of the twins
  translate[...]     translate_sequence  a source sequence in the target's marker style
  flow_warp[...]     flow_warp_sequence  the training-free baseline, same outputs
  features[skin]     image_features    InceptionV3 features of a skin's evaluation frames
  sim_m2m, ...       image_study       FID/KID before / m2m / flow_warp per pair, figures

Every image-scoring node selects its frames with data.eval_frame_indices, so a skin's own
features and the translations into it describe the same contact frames.
"""
from __future__ import annotations

import time
from typing import Mapping, Sequence

import numpy as np

from stages.figures import contact_sheet, figure_png, png
from stages.common import attrs_of, torch_threads
from stages.m2m.data import LABEL_KEYS, eval_frame_indices, paired_table, read_rows, take_rows

CHUNK = 64              # frames per streamed chunk
N_EXAMPLES = 4          # rows of the examples figure
TSNE_PER_SET = 12       # points per image set in the t-SNE figure


# ------------------------------------------------------------------------- training

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


def _distinct_references(skins: Sequence[str], refs: np.ndarray, title: str) -> None:
    """The generator knows a target only by its reference image: two skins drawn alike would
    teach it two answers to one question."""
    seen = {}
    for skin, ref in zip(skins, refs):
        key = ref.tobytes()
        if key in seen:
            raise ValueError(f"{title}: skins {seen[key]!r} and {skin!r} have identical reference "
                             f"images, so the translator cannot tell them apart as targets; draw "
                             f"one differently (its pattern, or base_area for a taxel skin)")
        seen[key] = skin


def _train(net, config, markers, skins, train_indenters, per_skin, steps, batch_size, lr, seed,
           change_weight, change_share, title, target_balance=0.0, change_per_example=0.0,
           identity_share=0.0, checkpoint=None):
    from stages.m2m.model import Translator, state_arrays
    from stages.m2m.train import PairBatches, fit, target_probabilities
    frames, rows = paired_table(markers, skins, train_indenters, per_skin)
    images, refs = _paired_arrays(markers, skins, rows, config["size"])
    _distinct_references(skins, refs, title)
    # a skin whose markers carry no `look` is a look of its own
    share = target_probabilities([attrs_of(markers[s]).get("look", s) for s in skins], float(target_balance))
    with torch_threads():
        # balance 0 keeps PairBatches' even draw (and its random stream)
        batches = PairBatches(images, refs, seed, share if float(target_balance) > 0 else None,
                              identity_share=float(identity_share))
        hist = fit(net, config, batches, steps=int(steps),
                   batch_size=int(batch_size), lr=float(lr), seed=int(seed),
                   change_weight=float(change_weight), change_share=float(change_share),
                   change_per_example=float(change_per_example),
                   progress=title, checkpoint=checkpoint)
        weights = state_arrays(net)
        samples = _samples_sheet(Translator(config, weights), images, refs, seed)
    tail = hist["loss"][-max(1, len(hist["loss"]) // 20):]
    return {
        "weights": weights,
        "loss": hist["loss"],
        "figures": {"loss": figure_png(_loss_figure(hist["loss"], title)),
                    "samples": png(samples)},
        "attrs": {"config": config, "skins": list(skins), "train_indenters": list(train_indenters),
                  "pairs": int(len(frames)), "steps": int(steps), "batch_size": int(batch_size),
                  "lr": float(lr), "seed": int(seed), "change_weight": float(change_weight),
                  "change_share": float(change_share), "target_balance": float(target_balance),
                  "identity_share": float(identity_share),
                  "target_share": {s: round(float(v), 4) for s, v in zip(skins, share)},
                  "final_loss": float(np.mean(tail)) if len(tail) else float("nan"),
                  "parameters": int(sum(v.size for v in weights.values()))},
        "timing": {"seconds": round(hist["seconds"], 2), "steps_per_s": round(hist["steps_per_s"], 3),
                   "resumed_at_step": int(hist["resumed_at"])},
    }


def pretrain(*, markers: Mapping, skins: list[str], train_indenters: list[str], size, steps: int,
             batch_size: int, lr: float, seed: int, width: int, timesteps: int,
             change_weight: float = 0.0, change_share: float = 0.0, source_gate: bool = True,
             identity_share: float = 0.0, checkpoint: str | None = None) -> dict:
    """Node m2m_sim: the generator trained from scratch on every ordered pair of `skins`
    (location-paired frames of the training indenters).  Returns weights (name -> array),
    the per-step loss, figures loss/samples and attrs (config to rebuild the model, ...).
    checkpoint: where the training saves its state as it goes (the worker gives a path per
    cache key), so an interrupted run resumes (train.fit).
    source_gate: the logits' base adds the source's edit where the references coincide
    (model.M2MNet.base); the fine-tune keeps the pretrained model's config.  identity_share:
    that share of the examples is a skin into itself (train.PairBatches)."""
    import torch
    from stages.m2m.model import build, default_config
    config = default_config(size=size, width=width, timesteps=timesteps, source_gate=source_gate)
    torch.manual_seed(int(seed))
    net = build(config)
    return _train(net, config, markers, skins, train_indenters, 0, steps, batch_size, lr, seed,
                  change_weight, change_share, "m2m pretrain", identity_share=identity_share,
                  checkpoint=checkpoint)


def finetune(*, base, markers: Mapping, skins: list[str], train_indenters: list[str],
             pairs_per_skin: int, steps: int, batch_size: int, lr: float, seed: int,
             change_weight: float = 0.0, change_share: float = 0.0, target_balance: float = 0.0,
             change_per_example: float = 0.0, identity_share: float = 0.0,
             checkpoint: str | None = None) -> dict:
    """Node m2m: `base` (a pretrained model) fine-tuned on `pairs_per_skin` location-paired
    frames shared by `skins`, evenly spread over the training indenters' frames.  Targets are
    drawn by train.target_probabilities over the skins' looks (the markers' `look` attribute)
    with `target_balance`.  checkpoint: as pretrain's."""
    from stages.m2m.model import build, weights_of
    config = attrs_of(base)["config"]
    net = build(config, weights_of(base))
    out = _train(net, config, markers, skins, train_indenters, int(pairs_per_skin), steps, batch_size,
                 lr, seed, change_weight, change_share, "m2m finetune", target_balance,
                 change_per_example, identity_share, checkpoint)
    out["attrs"]["base_skins"] = list(attrs_of(base).get("skins", []))
    out["attrs"]["pairs_per_skin"] = int(pairs_per_skin)
    return out


# ------------------------------------------------------------------------- translation

def _examples_sheet(source, target, rows: np.ndarray, translated: np.ndarray) -> np.ndarray:
    """source | translated | target at the same `frame` (target's reference if it lacks it)."""
    t_frames = np.asarray(target["frame"])
    t_ref = np.asarray(target["reference"], np.uint8)
    pick = np.unique(np.linspace(0, len(rows) - 1, min(N_EXAMPLES, len(rows))).round().astype(int))
    tiles = []
    for p in pick:
        frame = int(np.asarray(source["frame"][rows[p]:rows[p] + 1])[0])
        hit = np.flatnonzero(t_frames == frame)
        tgt = read_rows(target["images"], hit[:1])[0] if hit.size else t_ref
        src = np.asarray(source["images"][rows[p]:rows[p] + 1])[0]
        h, w = tgt.shape
        tiles += [_resize_nearest(src, (h, w)), translated[p], tgt]
    return contact_sheet(tiles, cols=3)


def _resize_nearest(image: np.ndarray, shape) -> np.ndarray:
    import cv2
    return image if image.shape == tuple(shape) else cv2.resize(image, shape[::-1], interpolation=cv2.INTER_NEAREST)


def _stream(source, target, eval_indenters, n_eval, convert, method: str):
    """Stream `convert(images) -> images` over the source sequence with its labels; then
    features of the evaluation frames, the examples figure and timing."""
    from stages.imagemetrics import inception_features
    from tqdm import tqdm
    rows = eval_frame_indices(source, eval_indenters, n_eval)
    labels = [k for k in LABEL_KEYS if k in source]
    n = len(source["images"])
    kept = np.zeros((len(rows), *np.asarray(target["reference"]).shape), np.uint8)
    t0 = time.perf_counter()
    for i in tqdm(range(0, n, CHUNK), desc=method, disable=None):
        out = convert(np.asarray(source["images"][i:i + CHUNK]))
        sel = (rows >= i) & (rows < i + len(out))
        kept[sel] = out[rows[sel] - i]
        yield {"images": out, **{k: np.asarray(source[k][i:i + CHUNK]) for k in labels}}
    seconds = time.perf_counter() - t0
    frames = np.asarray(source["frame"])[rows]
    result = {
        "reference": np.asarray(target["reference"], np.uint8),
        "features": inception_features(kept, progress=f"{method} features"),
        "eval_frames": frames.astype(np.int64),
        "figures": {"examples": png(_examples_sheet(source, target, rows, kept))},
        "attrs": {"method": method, "frames": int(n), "n_eval": int(len(rows)),
                  "eval_indenters": list(eval_indenters)},
        "timing": {"seconds": round(seconds, 2), "images_per_s": round(n / max(seconds, 1e-9), 1)},
    }
    if "indenters" in source:
        result["indenters"] = [str(v) for v in np.asarray(source["indenters"]).ravel()]
    return result


def _in_target_space(convert, target_markers, target: str, redraw_taxels: Sequence[str],
                     gain_of=None):
    """`convert`, followed for a target skin named in `redraw_taxels` by uskin.redraw: the
    output read as the taxel skin's 16 dots and drawn again as the skin draws them, with
    redraw's gain keywords `gain_of(convert, settings)` (gain, shift_gain, tilt) when given.
    Returns (convert, the keywords: None where it does not redraw)."""
    if target not in set(redraw_taxels or ()):
        return convert, None
    attrs = attrs_of(target_markers)
    if attrs.get("look") != "taxel":
        raise ValueError(f"m2m.redraw_taxels names {target!r}, whose markers are not taxel dots "
                         f"(look {attrs.get('look')!r})")
    from stages.markers.uskin import redraw
    settings = attrs.get("settings", {})
    gains = {"gain": (1.0, 1.0, 1.0)} if gain_of is None else dict(gain_of(convert, settings))
    return (lambda images: redraw(convert(images), settings, **gains)), gains


MATCH_GAIN_RANGE = (0.25, 4.0)
REDRAW_MATCH = ("none", "spread", "shift")


def _paired_dot_changes(convert, source_markers, target_markers, indenters: Sequence[str], pairs: int,
                        settings: Mapping):
    """uskin.dot_changes of the translations and of the target's own images on `pairs`
    location-paired frames of `indenters`: (fake offsets, fake area changes, real offsets,
    real area changes)."""
    from stages.markers.uskin import dot_changes
    _, rows = paired_table({"s": source_markers, "t": target_markers}, ["s", "t"], indenters, int(pairs))

    fake_off, fake_area = dot_changes(convert(take_rows(source_markers["images"], rows[0])), settings)
    real_off, real_area = dot_changes(take_rows(target_markers["images"], rows[1]), settings)
    return fake_off, fake_area, real_off, real_area


def _clip_gains(gains) -> tuple[float, ...]:
    return tuple(round(float(np.clip(g, *MATCH_GAIN_RANGE)), 4) for g in gains)


def matched_gain(convert, source_markers, target_markers, indenters: Sequence[str], pairs: int,
                 settings: Mapping) -> tuple[float, float, float]:
    """(x, y, area) gains that give translations into a taxel skin the spread of the skin's own
    dots: the RMS of the target's dot offsets (and area changes) over the RMS of the
    translations' on `pairs` location-paired frames of `indenters` (the frames the model was
    fine-tuned on: images only, no labels), each clipped to MATCH_GAIN_RANGE.  A translator
    that draws the dots' motion at half its size gets gain 2."""
    fake_off, fake_area, real_off, real_area = _paired_dot_changes(
        convert, source_markers, target_markers, indenters, pairs, settings)
    rms = lambda x: float(np.sqrt(np.mean(np.square(x))))
    return _clip_gains(rms(r) / max(rms(f), 1e-9) if rms(r) > 0 else 1.0
                       for r, f in [(real_off[..., 0], fake_off[..., 0]),
                                    (real_off[..., 1], fake_off[..., 1]), (real_area, fake_area)])


def matched_shift_gain(convert, source_markers, target_markers, indenters: Sequence[str], pairs: int,
                       settings: Mapping) -> tuple[float, float]:
    """(x, y) gains for the dots' common shift (their mean offset in a frame, what a shear
    moves): the least-squares slope, through 0, of the target's common shift on the
    translations' over the paired frames of matched_gain, each clipped to MATCH_GAIN_RANGE.
    The rest of the dots' motion and their areas keep their drawn size."""
    fake_off, _, real_off, _ = _paired_dot_changes(
        convert, source_markers, target_markers, indenters, pairs, settings)
    fake, real = fake_off.mean(1), real_off.mean(1)
    return _clip_gains(float((real[:, k] * fake[:, k]).sum() / (fake[:, k] ** 2).sum())
                       if (fake[:, k] ** 2).sum() > 1e-12 else 1.0 for k in (0, 1))


TILT_WEIGHTS = tuple(round(0.05 * i, 2) for i in range(41))   # the a shrink_guard tries, 0..2
MIN_SHRINK_FRAMES = 8          # paired frames with shrunk dots on both sides it needs to judge


def matched_tilt(convert, source_markers, target_markers, indenters: Sequence[str], pairs: int,
                 settings: Mapping) -> tuple[tuple[float, float], tuple[float, float]]:
    """uskin.redraw's tilt for a z-only taxel skin: per axis, the least-squares (a, b) with which
    the first moment of the skin's own area changes is a times the translations' plus b times
    their common shift (uskin.load_moments) over the paired frames of matched_gain, unless that
    a adds to the drawn moment and sets the dots the redraw shrinks elsewhere than the skin
    shrinks them (shrink_guard).
    M2M draws a shear into the z-only skin as dot motion, which the skin cannot show, and
    barely tilts its load; the tilt moves that cue to where the skin has it."""
    from stages.markers.uskin import USKIN_PAD_MM, load_moments
    fake_off, fake_area, real_off, real_area = _paired_dot_changes(
        convert, source_markers, target_markers, indenters, pairs, settings)
    pad = tuple(float(v) for v in settings.get("pad_mm", USKIN_PAD_MM))
    fake_moment, fake_shift = load_moments(fake_off, fake_area, pad)
    real_moment, _ = load_moments(real_off, real_area, pad)
    out = []
    for k in (0, 1):
        x = np.stack([fake_moment[:, k], fake_shift[:, k]], 1)
        coef, *_ = np.linalg.lstsq(x, real_moment[:, k], rcond=None)
        a, b = shrink_guard(k, (float(coef[0]), float(coef[1])), fake_area, fake_moment, fake_shift,
                            real_area, real_moment, settings, pad)
        out.append((round(a, 4), round(b, 4)))
    return tuple(out)


def shrink_guard(axis: int, fit: tuple[float, float], fake_area, fake_moment, fake_shift, real_area,
                 real_moment, settings: Mapping, pad) -> tuple[float, float]:
    """matched_tilt's (a, b) along `axis`: the least-squares `fit`, unless its a exceeds 1 and
    with it the dots the redraw shrinks below their rest size sit elsewhere than on the skin's
    own frames.  Over the paired frames where both shrink a dot, the correlation of the two
    centroids of shrunk area (uskin.shrink_centroids) is taken for the fit and for each a of
    TILT_WEIGHTS, b then the least-squares fit given a.  If the fit's falls short of the best by
    more than the best's standard error, (1 - r^2) / sqrt(n - 1), the best a and its b replace
    it.

    The skin shows where the contact is by where its load is.  A fit whose a exceeds 1 adds a
    plane in proportion to the translations' drawn moment, mostly where the contact is, scaled
    up where they draw it too near the pad's centre (TacTip's at 0.55 of the skin's spread:
    a 1.40 in x): that plane is no shear, yet it moves the shrunk dots, the skin's shear cue,
    with where the contact is.  An a below 1 only takes some of M2M's drawn moment away, and is
    kept (in y, where the contacts barely move, the translations' shrunk dots follow the
    skin's better at larger a, but the regressor reads shear worse).  A skin whose dots cannot
    shrink (min_area = base_area), or fewer than MIN_SHRINK_FRAMES such frames, keeps the fit."""
    from stages.markers.uskin import shrink_centroids, tilt_changes
    shift = fake_shift[:, axis]
    den = float(shift @ shift)
    if fit[0] <= 1.0 or den <= 1e-12:
        return fit
    real_c, real_lost = shrink_centroids(real_area, settings, pad)

    def score(a: float, b: float) -> tuple[float, int]:
        want = fake_moment.copy()
        want[:, axis] = a * fake_moment[:, axis] + b * shift
        c, lost = shrink_centroids(tilt_changes(fake_area, fake_moment, want, pad), settings, pad)
        on = (lost > 1e-3) & (real_lost > 1e-3)
        if on.sum() < MIN_SHRINK_FRAMES or c[on, axis].std() == 0 or real_c[on, axis].std() == 0:
            return -np.inf, int(on.sum())
        return float(np.corrcoef(c[on, axis], real_c[on, axis])[0, 1]), int(on.sum())

    given = [(a, float(shift @ (real_moment[:, axis] - a * fake_moment[:, axis]) / den)) for a in TILT_WEIGHTS]
    (best, n), a, b = max(((score(a, b), a, b) for a, b in given), key=lambda t: t[0][0])
    if not np.isfinite(best) or score(*fit)[0] >= best - max(1.0 - best ** 2, 1e-9) / np.sqrt(n - 1):
        return fit
    return float(a), b


SHIFT_READ_ALPHAS = tuple(float(a) for a in np.logspace(-4, 3, 30))   # RidgeCV's penalties


def source_shift_read(source_markers, target_markers, indenters: Sequence[str], pairs: int,
                      source_settings: Mapping, settings: Mapping) -> dict:
    """How a 3-axis taxel skin's common shift reads off another taxel skin's own dots: per axis,
    the ridge regression (scikit-learn's RidgeCV, its penalty picked by leave-one-out from
    SHIFT_READ_ALPHAS) of the target's common shift (uskin.load_moments) on the source's
    uskin.dot_features, over `pairs` location-paired frames of `indenters` (the frames M2M was
    fine-tuned on: images only, no labels).  Returns {"coef": (2, 48), "intercept": (2,),
    "alpha": (2,)}, as lists (read_source_shift applies it).

    A z-only skin shows a shear only as a tilt of its load, which M2M barely draws into the
    3-axis skin's dot shift: the common shift it draws from the z-only uSkin follows the skin's
    own at correlation 0.51 in x on the test contacts, this read at 0.92."""
    from sklearn.linear_model import RidgeCV

    from stages.markers.uskin import dot_changes, dot_features, load_moments
    _, rows = paired_table({"s": source_markers, "t": target_markers}, ["s", "t"], indenters, int(pairs))
    x = dot_features(take_rows(source_markers["images"], rows[0]), source_settings)
    real_off, real_area = dot_changes(take_rows(target_markers["images"], rows[1]), settings)
    _, real_shift = load_moments(real_off, real_area)
    fits = [RidgeCV(alphas=SHIFT_READ_ALPHAS).fit(x, real_shift[:, k]) for k in (0, 1)]
    return {"coef": [[float(c) for c in f.coef_] for f in fits],
            "intercept": [float(f.intercept_) for f in fits], "alpha": [float(f.alpha_) for f in fits]}


def read_source_shift(read: Mapping, images, source_settings: Mapping) -> np.ndarray:
    """(N, 2) mm: the common shift source_shift_read's `read` gives the source's images."""
    from stages.markers.uskin import dot_features
    return dot_features(images, source_settings) @ np.asarray(read["coef"], float).T + \
        np.asarray(read["intercept"], float)


def _redraw_gains(mode: str, convert, settings: Mapping, **paired) -> dict:
    """uskin.redraw's gain keywords for m2m.redraw_match `mode` (REDRAW_MATCH): "shift" matches
    a 3-axis skin's common shift (matched_shift_gain) and a z-only skin's load tilt
    (matched_tilt)."""
    if mode == "spread":
        return {"gain": matched_gain(convert, settings=settings, **paired)}
    if settings.get("z_only", False):
        return {"gain": (1.0, 1.0, 1.0), "tilt": matched_tilt(convert, settings=settings, **paired)}
    return {"gain": (1.0, 1.0, 1.0), "shift_gain": matched_shift_gain(convert, settings=settings, **paired)}


def translate_sequence(*, model, source_markers, target_markers, eval_indenters: list[str], n_eval: int,
                       sampler_steps: int = 1, redraw_taxels: Sequence[str] = (), redraw_match: str = "none",
                       redraw_source_shift: bool = False, source: str = "", target: str = ""):
    """Nodes translate_sim[source,target] / translate[source,target]: the source sequence
    (source_markers, a marker artifact) translated into the target's marker style by the M2M
    model (chunks: images + the source labels); returns the target's reference, `features`
    and `eval_frames` of the evaluation frames, figures/examples and attrs.  redraw_taxels:
    the taxel skins whose translations are redrawn as their dots (_in_target_space; attrs
    redraw_taxels true where done); redraw_match (REDRAW_MATCH): "spread" scales their dots'
    motion and area change by matched_gain, "shift" their common shift by matched_shift_gain
    (a z-only skin: tilts their load by matched_tilt), all measured on the model's fine-tuning
    frames (attrs redraw_gain, redraw_shift_gain, redraw_tilt); "none" draws them as read.
    redraw_source_shift: into a 3-axis taxel skin from another taxel skin, the dots' common
    shift is read off the source's own dots instead (source_shift_read on those frames, attrs
    redraw_source_shift), whatever redraw_match.  source, target: the skins' names (the
    fan-out's values)."""
    from stages.m2m.model import load_translator
    if redraw_match not in REDRAW_MATCH:
        raise ValueError(f"m2m.redraw_match must be one of {', '.join(REDRAW_MATCH)}, got {redraw_match!r}")
    translator = load_translator(model)
    src_ref = np.asarray(source_markers["reference"], np.uint8)
    tgt_ref = np.asarray(target_markers["reference"], np.uint8)
    trained = attrs_of(model)
    gain_of = None
    paired = dict(source_markers=source_markers, target_markers=target_markers,
                  indenters=trained["train_indenters"], pairs=int(trained.get("pairs_per_skin", 0)))
    if redraw_match != "none":
        gain_of = lambda convert, settings: _redraw_gains(redraw_match, convert, settings, **paired)
    if not isinstance(redraw_source_shift, bool):
        raise ValueError(f"m2m.redraw_source_shift must be true or false, got {redraw_source_shift!r}")
    source_attrs, settings = attrs_of(source_markers), attrs_of(target_markers).get("settings", {})
    from_source = (redraw_source_shift and source_attrs.get("look") == "taxel"
                   and target in set(redraw_taxels or ()) and not settings.get("z_only", False))
    read = None
    if from_source:
        gain_of = None                        # the common shift is read off the source, not matched
    with torch_threads():
        plain = lambda im: translator.translate(im, src_ref, tgt_ref, int(sampler_steps))
        convert, gain = _in_target_space(plain, target_markers, target, redraw_taxels, gain_of)
        if from_source:
            from stages.markers.uskin import redraw
            source_settings = source_attrs.get("settings", {})
            read = source_shift_read(source_settings=source_settings, settings=settings, **paired)
            convert = lambda images: redraw(plain(images), settings,
                                            shift=read_source_shift(read, images, source_settings))
        result = yield from _stream(source_markers, target_markers, eval_indenters, n_eval, convert, "m2m")
    result["attrs"].update(sampler_steps=int(sampler_steps), source=source, target=target)
    if gain is not None:
        result["attrs"]["redraw_taxels"] = True
        result["attrs"]["redraw_gain"] = [float(g) for g in gain["gain"]]
        if "shift_gain" in gain:
            result["attrs"]["redraw_shift_gain"] = [float(g) for g in gain["shift_gain"]]
        if "tilt" in gain:
            result["attrs"]["redraw_tilt"] = [[float(v) for v in row] for row in gain["tilt"]]
        if read is not None:
            result["attrs"]["redraw_source_shift"] = read
    return result


def translate_seed_sequence(*, model, source_markers, target_markers, eval_indenters: list[str],
                            n_eval: int, seed: int, sampler_steps: int = 1,
                            redraw_taxels: Sequence[str] = (), redraw_match: str = "none",
                            redraw_source_shift: bool = False, source: str = "", target: str = ""):
    """Node translate_seed[source,target,seed]: translate_sequence with `model`, the M2M
    fine-tuned again from `seed` (m2m_seed), for a hetero ensemble member; attrs m2m_seed."""
    result = yield from translate_sequence(
        model=model, source_markers=source_markers, target_markers=target_markers,
        eval_indenters=eval_indenters, n_eval=n_eval, sampler_steps=sampler_steps,
        redraw_taxels=redraw_taxels, redraw_match=redraw_match, redraw_source_shift=redraw_source_shift,
        source=source, target=target)
    result["attrs"]["m2m_seed"] = int(seed)
    return result


def flow_warp_sequence(*, source_markers, target_markers, eval_indenters: list[str], n_eval: int,
                       redraw_taxels: Sequence[str] = (), source: str = "", target: str = ""):
    """Node flow_warp[source,target]: the training-free baseline (stages.m2m.flow) with the
    same outputs as translate_sequence (redraw_taxels as there)."""
    from stages.m2m.flow import MarkerFlow, warp
    flow = MarkerFlow(np.asarray(source_markers["reference"], np.uint8))
    tgt_ref = np.asarray(target_markers["reference"], np.uint8)
    convert, gain = _in_target_space(lambda ims: np.stack([warp(tgt_ref, flow.field(im)) for im in ims]),
                                     target_markers, target, redraw_taxels)
    result = yield from _stream(source_markers, target_markers, eval_indenters, n_eval, convert, "flow_warp")
    result["attrs"].update(source=source, target=target)
    if gain is not None:
        result["attrs"]["redraw_taxels"] = True
    return result


def image_features(*, markers, eval_indenters: list[str], n_eval: int, skin: str = "") -> dict:
    """Node features[skin]: InceptionV3 features (n,2048) of the skin's evaluation frames."""
    from stages.imagemetrics import inception_features
    rows = eval_frame_indices(markers, eval_indenters, n_eval)
    with torch_threads():
        features = inception_features(read_rows(markers["images"], rows), progress="features")
    return {"features": features,
            "eval_frames": np.asarray(markers["frame"])[rows].astype(np.int64),
            "attrs": {"n_eval": int(len(rows)), "eval_indenters": list(eval_indenters)}}


# ------------------------------------------------------------------------- study

def pair_label(source: str, target: str) -> str:
    """The gather label of a two-variable fan-out instance."""
    return f"source={source},target={target}"


def image_study(*, study: str, pairs: list, features: Mapping, translated: Mapping,
                warped: Mapping | None = None, kid_subset: int = 100, markers: Mapping | None = None) -> dict:
    """FID/KID of every (source, target) pair: `before` (source's own evaluation images vs
    the target's), `m2m` (translated vs target) and `flow_warp` (warped vs target), their
    means, (S,S) matrices fid/<method>, kid/<method> (NaN off the pairs), heatmaps and t-SNE.

    With `markers` (the skins' marker artifacts): for the pairs whose two skins' evaluation
    frames show one and the same deformation (equal force labels: one mechanical twin, as the
    simulation patterns and the GelSight twins are), whether each method keeps it,
    `motion_err_px` per pair and method (stages.m2m.flow.motion_error on the evaluation frames
    against the target's own; `before` is the target's reference, which keeps none of it, so
    it scores the markers' mean motion), matrices motion_err/<method> and a heatmap."""
    from stages.imagemetrics import fid, heatmaps_figure, kid
    t0 = time.perf_counter()
    pairs = [(str(s), str(t)) for s, t in pairs]
    used = {n for p in pairs for n in p}
    missing = sorted(used - set(features))
    if missing:
        raise KeyError(f"no features for skins {missing}")
    names = [n for n in features if n in used]
    index = {n: i for i, n in enumerate(names)}
    feats = {n: np.asarray(features[n]["features"]) for n in names}
    sources = {"m2m": translated or {}, "flow_warp": warped or {}}
    methods = ["before"] + [m for m, arts in sources.items() if arts]
    fids = {m: np.full((len(names),) * 2, np.nan) for m in methods}
    kids = {m: np.full((len(names),) * 2, np.nan) for m in methods}
    metrics, gen_feats = {}, {}
    for s, t in pairs:
        for m in methods:
            if m == "before":
                fake = feats[s]
            else:
                label = pair_label(s, t)
                if label not in sources[m]:
                    raise KeyError(f"{m}: no artifact for pair {label!r}")
                fake = np.asarray(sources[m][label]["features"])
                if m == "m2m":
                    gen_feats[(s, t)] = fake
            i, j = index[s], index[t]
            fids[m][i, j] = fid(fake, feats[t])
            kids[m][i, j] = kid(fake, feats[t], kid_subset)
            metrics[f"{study}/{s}_{t}/{m}/fid"] = float(fids[m][i, j])
            metrics[f"{study}/{s}_{t}/{m}/kid"] = float(kids[m][i, j])
    for m in methods:
        metrics[f"{study}/mean/{m}/fid"] = float(np.nanmean(fids[m]))
        metrics[f"{study}/mean/{m}/kid"] = float(np.nanmean(kids[m]))
    figures = {"fid": figure_png(heatmaps_figure(fids, names, "FID", log=True)),
               "kid": figure_png(heatmaps_figure(kids, names, "KID"))}
    motion = {}
    if markers:
        motion = _motion_errors(study, pairs, names, index, features, markers, sources, methods, metrics)
    if motion:
        figures["motion"] = figure_png(heatmaps_figure(motion, names, "marker motion error (px)"))
    if gen_feats:
        figures["tsne"] = figure_png(_tsne_figure(names, feats, gen_feats))
    drop = {m: metrics[f"{study}/mean/before/fid"] / max(metrics[f"{study}/mean/{m}/fid"], 1e-12)
            for m in methods if m != "before"}
    return {
        "skins": names,
        "fid": fids, "kid": kids,
        **({"motion_err": motion} if motion else {}),
        "figures": figures,
        "metrics": metrics,
        "attrs": {"study": study, "pairs": len(pairs), "methods": methods, "kid_subset": int(kid_subset),
                  "fid_drop": {m: round(v, 2) for m, v in drop.items()}},
        "timing": {"seconds": round(time.perf_counter() - t0, 2)},
    }


def _motion_errors(study, pairs, names, index, features, markers, sources, methods, metrics) -> dict:
    """image_study's motion_err_px of every pair of skins in `markers` whose evaluation frames
    carry the same force labels in both (one mechanical twin, so one deformation; see there)
    and whose target's own markers move there (a z-only taxel skin's dots grow and shrink in
    place: no marker motion to keep, so no score)."""
    from stages.m2m.flow import motion_error

    def rows_of(art, wanted):  # art's rows of the frames `wanted`, in that order
        pos = {int(f): r for r, f in enumerate(np.asarray(art["frame"]))}
        missing = [int(f) for f in wanted if int(f) not in pos]
        if missing:
            raise KeyError(f"evaluation frames {missing[:5]} missing from an artifact")
        return np.asarray([pos[int(f)] for f in wanted])

    def read(arr, rows):  # read_rows wants sorted rows
        order = np.argsort(rows)
        data = read_rows(arr, rows[order])
        out = np.empty_like(data)
        out[order] = data
        return out

    out = {m: np.full((len(names),) * 2, np.nan) for m in methods}
    scored = False
    for s, t in pairs:
        if s not in markers or t not in markers:
            continue
        frames = np.asarray(features[t]["eval_frames"])
        rows_s, rows_t = rows_of(markers[s], frames), rows_of(markers[t], frames)
        if not np.array_equal(read(markers[s]["force"], rows_s), read(markers[t]["force"], rows_t)):
            continue                 # two twins pressed alike but deformed differently
        truth = read(markers[t]["images"], rows_t)
        reference = np.asarray(markers[t]["reference"], np.uint8)
        for m in methods:
            if m == "before":
                images = np.broadcast_to(reference, truth.shape)
            else:
                art = sources[m][pair_label(s, t)]
                images = read(art["images"], rows_of(art, frames))
            err, _, moving = motion_error(images, truth, reference)
            if not moving:           # no marker of the target moves (truth's alone): nothing to keep
                break
            out[m][index[s], index[t]] = err
            metrics[f"{study}/{s}_{t}/{m}/motion_err_px"] = err
            scored = True
    if not scored:
        return {}
    for m in methods:
        metrics[f"{study}/mean/{m}/motion_err_px"] = float(np.nanmean(out[m]))
    return out


def _tsne_figure(names, feats: Mapping, gen_feats: Mapping):
    """Joint t-SNE of a few images per skin and per translated pair (fixed seed)."""
    from stages.imagemetrics import tsne, tsne_figure
    from stages.m2m.data import evenly
    blocks, groups, kinds = [], [], []
    for n in names:
        pick = evenly(np.arange(len(feats[n])), TSNE_PER_SET)
        blocks.append(feats[n][pick])
        groups += [n] * len(pick)
        kinds += ["real"] * len(pick)
    per_pair = max(2, TSNE_PER_SET // max(1, len(names) - 1))
    for (s, t), f in gen_feats.items():
        pick = evenly(np.arange(len(f)), per_pair)
        blocks.append(f[pick])
        groups += [t] * len(pick)
        kinds += ["translated"] * len(pick)
    points = tsne(np.concatenate(blocks), seed=0)
    return tsne_figure(points, groups, kinds, names)
