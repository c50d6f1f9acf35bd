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
from stages.m2m.data import LABEL_KEYS, eval_frame_indices, paired_table, read_rows

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
           change_share, title, checkpoint=None):
    from stages.m2m.model import Translator, state_arrays
    from stages.m2m.train import PairBatches, fit
    frames, rows = paired_table(markers, skins, train_indenters, per_skin)
    images, refs = _paired_arrays(markers, skins, rows, config["size"])
    _distinct_references(skins, refs, title)
    with torch_threads():
        batches = PairBatches(images, refs, seed)
        hist = fit(net, config, batches, steps=int(steps), batch_size=int(batch_size), lr=float(lr),
                   seed=int(seed), change_share=float(change_share), progress=title, checkpoint=checkpoint)
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
                  "lr": float(lr), "seed": int(seed), "change_share": float(change_share),
                  "final_loss": float(np.mean(tail)) if len(tail) else float("nan"),
                  "parameters": int(sum(v.size for v in weights.values()))},
        "timing": {"seconds": round(hist["seconds"], 2), "steps_per_s": round(hist["steps_per_s"], 3),
                   "resumed_at_step": int(hist["resumed_at"])},
    }


def pretrain(*, markers: Mapping, skins: list[str], train_indenters: list[str], size, steps: int,
             batch_size: int, lr: float, seed: int, width: int, timesteps: int,
             change_share: float = 0.0, source_gate: bool = True, checkpoint: str | None = None) -> dict:
    """Node m2m_sim: the generator trained from scratch on every ordered pair of `skins`
    (location-paired frames of the training indenters).  Returns weights (name -> array),
    the per-step loss, figures loss/samples and attrs (config to rebuild the model, ...).
    checkpoint: where the training saves its state as it goes (the worker gives a path per
    cache key), so an interrupted run resumes (train.fit).
    source_gate: the logits' base adds the source's edit where the references coincide
    (model.M2MNet.base); the fine-tune keeps the pretrained model's config."""
    import torch
    from stages.m2m.model import build, default_config
    config = default_config(size=size, width=width, timesteps=timesteps, source_gate=source_gate)
    torch.manual_seed(int(seed))
    net = build(config)
    return _train(net, config, markers, skins, train_indenters, 0, steps, batch_size, lr, seed,
                  change_share, "m2m pretrain", checkpoint=checkpoint)


def finetune(*, base, markers: Mapping, skins: list[str], train_indenters: list[str],
             pairs_per_skin: int, steps: int, batch_size: int, lr: float, seed: int,
             change_share: float = 0.0, checkpoint: str | None = None) -> dict:
    """Node m2m: `base` (a pretrained model) fine-tuned on `pairs_per_skin` location-paired
    frames shared by `skins`, evenly spread over the training indenters' frames.
    checkpoint: as pretrain's."""
    from stages.m2m.model import build, weights_of
    config = attrs_of(base)["config"]
    net = build(config, weights_of(base))
    out = _train(net, config, markers, skins, train_indenters, int(pairs_per_skin), steps, batch_size,
                 lr, seed, change_share, "m2m finetune", checkpoint)
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


def _eval_rows(source, eval_indenters, val_indenters, n_eval) -> dict[str, np.ndarray]:
    """The scored frames of each split: "" the test indenters', "_val" the validation ones'."""
    out = {"": eval_frame_indices(source, eval_indenters, n_eval)}
    if val_indenters:
        out["_val"] = eval_frame_indices(source, val_indenters, n_eval)
    return out


def _stream(source, target, eval_indenters, val_indenters, n_eval, convert, method: str):
    """Stream `convert(images) -> images` over the source sequence with its labels; then
    features of each split's scored frames (features, eval_frames; features_val,
    eval_frames_val), the examples figure and timing."""
    from stages.imagemetrics import inception_features
    from tqdm import tqdm
    splits = _eval_rows(source, eval_indenters, val_indenters, n_eval)
    labels = [k for k in LABEL_KEYS if k in source]
    n = len(source["images"])
    shape = np.asarray(target["reference"]).shape
    kept = {k: np.zeros((len(rows), *shape), np.uint8) for k, rows in splits.items()}
    t0 = time.perf_counter()
    for i in tqdm(range(0, n, CHUNK), desc=method, disable=None):
        out = convert(np.asarray(source["images"][i:i + CHUNK]))
        for k, rows in splits.items():
            sel = (rows >= i) & (rows < i + len(out))
            kept[k][sel] = out[rows[sel] - i]
        yield {"images": out, **{k: np.asarray(source[k][i:i + CHUNK]) for k in labels}}
    seconds = time.perf_counter() - t0
    result = {"reference": np.asarray(target["reference"], np.uint8)}
    for k, rows in splits.items():
        result[f"features{k}"] = inception_features(kept[k], progress=f"{method} features{k}")
        result[f"eval_frames{k}"] = np.asarray(source["frame"])[rows].astype(np.int64)
    result.update({
        "figures": {"examples": png(_examples_sheet(source, target, splits[""], kept[""]))},
        "attrs": {"method": method, "frames": int(n), "n_eval": int(len(splits[""])),
                  "eval_indenters": list(eval_indenters), "val_indenters": list(val_indenters or ())},
        "timing": {"seconds": round(seconds, 2), "images_per_s": round(n / max(seconds, 1e-9), 1)},
    })
    if "indenters" in source:
        result["indenters"] = [str(v) for v in np.asarray(source["indenters"]).ravel()]
    return result


def translate_sequence(*, model, source_markers, target_markers, eval_indenters: list[str], n_eval: int,
                       val_indenters: Sequence[str] = (), sampler_steps: int = 1, source: str = "",
                       target: str = ""):
    """Nodes translate_sim[source,target] / translate[source,target]: the source sequence
    (source_markers, a marker artifact) translated into the target's marker style by the M2M
    model (chunks: images + the source labels); returns the target's reference, features and
    eval_frames of each split's scored frames, figures/examples and attrs.  source, target: the
    skins' names (the fan-out's values)."""
    from stages.m2m.model import load_translator
    translator = load_translator(model)
    src_ref = np.asarray(source_markers["reference"], np.uint8)
    tgt_ref = np.asarray(target_markers["reference"], np.uint8)
    with torch_threads():
        convert = lambda im: translator.translate(im, src_ref, tgt_ref, int(sampler_steps))
        result = yield from _stream(source_markers, target_markers, eval_indenters, val_indenters, n_eval,
                                    convert, "m2m")
    result["attrs"].update(sampler_steps=int(sampler_steps), source=source, target=target)
    return result


def flow_warp_sequence(*, source_markers, target_markers, eval_indenters: list[str], n_eval: int,
                       val_indenters: Sequence[str] = (), source: str = "", target: str = ""):
    """Node flow_warp[source,target]: the training-free baseline (stages.m2m.flow) with the
    same outputs as translate_sequence."""
    from stages.m2m.flow import MarkerFlow, warp
    flow = MarkerFlow(np.asarray(source_markers["reference"], np.uint8))
    tgt_ref = np.asarray(target_markers["reference"], np.uint8)
    convert = lambda ims: np.stack([warp(tgt_ref, flow.field(im)) for im in ims])
    result = yield from _stream(source_markers, target_markers, eval_indenters, val_indenters, n_eval,
                                convert, "flow_warp")
    result["attrs"].update(source=source, target=target)
    return result


def image_features(*, markers, eval_indenters: list[str], n_eval: int, val_indenters: Sequence[str] = (),
                   skin: str = "") -> dict:
    """Node features[skin]: InceptionV3 features (n,2048) of the skin's scored frames of each
    split (features, eval_frames: the test indenters'; features_val, eval_frames_val)."""
    from stages.imagemetrics import inception_features
    out = {}
    with torch_threads():
        for k, rows in _eval_rows(markers, eval_indenters, val_indenters, n_eval).items():
            out[f"features{k}"] = inception_features(read_rows(markers["images"], rows), progress=f"features{k}")
            out[f"eval_frames{k}"] = np.asarray(markers["frame"])[rows].astype(np.int64)
    out["attrs"] = {"n_eval": int(len(out["features"])), "eval_indenters": list(eval_indenters),
                    "val_indenters": list(val_indenters or ())}
    return out


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
    sources = {"m2m": translated or {}, "flow_warp": warped or {}}
    methods = ["before"] + [m for m, arts in sources.items() if arts]
    metrics, gen_feats = {}, {}
    # the validation split (`features_val`) where every set has it: the choices' image metrics
    splits = [""] + (["_val"] if all("features_val" in features[n] for n in names) else [])
    for split in splits:
        feats = {n: np.asarray(features[n][f"features{split}"]) for n in names}
        fids = {m: np.full((len(names),) * 2, np.nan) for m in methods}
        kids = {m: np.full((len(names),) * 2, np.nan) for m in methods}
        prefix = f"{study}{split}"
        for s, t in pairs:
            for m in methods:
                if m == "before":
                    fake = feats[s]
                else:
                    label = pair_label(s, t)
                    if label not in sources[m]:
                        raise KeyError(f"{m}: no artifact for pair {label!r}")
                    fake = np.asarray(sources[m][label][f"features{split}"])
                    if m == "m2m" and not split:
                        gen_feats[(s, t)] = fake
                i, j = index[s], index[t]
                fids[m][i, j] = fid(fake, feats[t])
                kids[m][i, j] = kid(fake, feats[t], kid_subset)
                metrics[f"{prefix}/{s}_{t}/{m}/fid"] = float(fids[m][i, j])
                metrics[f"{prefix}/{s}_{t}/{m}/kid"] = float(kids[m][i, j])
        for m in methods:
            metrics[f"{prefix}/mean/{m}/fid"] = float(np.nanmean(fids[m]))
            metrics[f"{prefix}/mean/{m}/kid"] = float(np.nanmean(kids[m]))
        if not split:
            test_fids, test_kids, test_feats = fids, kids, feats
    fids, kids, feats = test_fids, test_kids, test_feats
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
