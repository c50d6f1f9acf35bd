"""M2M's translation nodes: translate_sim[source,target] and translate[source,target] (a
source sequence in the target's marker style), flow_warp[source,target] (the training-free
baseline, same outputs) and features[skin] (InceptionV3 features of a skin's scored frames).

Every image-scoring node selects its frames with data.eval_frame_indices, so a skin's own
features and the translations into it describe the same contact frames.
"""
from __future__ import annotations

import time
from typing import Sequence

import numpy as np

from stages.common import LABEL_KEYS, torch_threads
from stages.figures import contact_sheet, png
from stages.m2m.data import eval_frame_indices, read_rows

CHUNK = 64              # frames per streamed chunk
N_EXAMPLES = 4          # rows of the examples figure


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


def _stream(source, target, eval_indenters, val_indenters, n_eval, convert, method: str,
            train_indenters: Sequence[str] | None = None):
    """Stream `convert(images) -> images` with the labels over the rows of the source sequence
    its readers use: the whole contacts of `train_indenters` (what `transfer` trains on) and
    each split's scored frames (None: the scored frames alone, a translation only the image
    metrics read); then features of each split's scored frames (features, eval_frames;
    features_val, eval_frames_val), the examples figure and timing."""
    from stages.force.data import contact_runs, run_rows
    from stages.imagemetrics import inception_features
    from tqdm import tqdm
    splits = _eval_rows(source, eval_indenters, val_indenters, n_eval)
    labels = [k for k in LABEL_KEYS if k in source]
    trained = run_rows(contact_runs(source, train_indenters)) if train_indenters is not None else []
    rows_out = np.unique(np.concatenate([np.asarray(trained, int), *splits.values()]))
    n = len(rows_out)
    shape = np.asarray(target["reference"]).shape
    kept = {k: np.zeros((len(rows), *shape), np.uint8) for k, rows in splits.items()}
    t0 = time.perf_counter()
    for i in tqdm(range(0, n, CHUNK), desc=method, disable=None):
        rows = rows_out[i:i + CHUNK]
        out = convert(read_rows(source["images"], rows))
        for k, wanted in splits.items():
            at = np.searchsorted(rows, wanted)
            sel = (at < len(rows)) & (rows[np.minimum(at, len(rows) - 1)] == wanted)
            kept[k][sel] = out[at[sel]]
        yield {"images": out, **{k: read_rows(source[k], rows) for k in labels}}
    seconds = time.perf_counter() - t0
    result = {"reference": np.asarray(target["reference"], np.uint8)}
    for k, rows in splits.items():
        result[f"features{k}"] = inception_features(kept[k], progress=f"{method} features{k}")
        result[f"eval_frames{k}"] = np.asarray(source["frame"])[rows].astype(np.int64)
    result.update({
        "figures": {"examples": png(_examples_sheet(source, target, splits[""], kept[""]))},
        "attrs": {"method": method, "frames": int(n), "n_eval": int(len(splits[""])),
                  "train_indenters": None if train_indenters is None else list(train_indenters),
                  "eval_indenters": list(eval_indenters), "val_indenters": list(val_indenters or ())},
        "timing": {"seconds": round(seconds, 2), "images_per_s": round(n / max(seconds, 1e-9), 1)},
    })
    if "indenters" in source:
        result["indenters"] = [str(v) for v in np.asarray(source["indenters"]).ravel()]
    return result


def translate_sequence(*, model, source_markers, target_markers, eval_indenters: list[str], n_eval: int,
                       val_indenters: Sequence[str] = (), train_indenters: Sequence[str] | None = None,
                       sampler_steps: int = 1, source: str = "", target: str = ""):
    """Nodes translate_sim[source,target] / translate[source,target]: the source sequence
    (source_markers, a marker artifact) translated into the target's marker style by the M2M
    model, as chunks of images with the source's labels: the whole contacts of
    `train_indenters` (what `transfer` trains on; None: none) and the scored frames of each
    split.  Returns the target's reference, features and eval_frames of each split's scored
    frames, figures/examples and attrs.  source, target: the skins' names (the fan-out's
    values).  Two skins of one marker style (stages.m2m.data.same_style: one layout, the
    material study's gels) translate as the identity (attrs same_style), as M2M fine-tunes
    them as one target."""
    from stages.m2m.data import same_style
    from stages.m2m.model import load_translator
    src_ref = np.asarray(source_markers["reference"], np.uint8)
    tgt_ref = np.asarray(target_markers["reference"], np.uint8)
    identity = same_style(src_ref, tgt_ref)     # one marker layout: the paper's method is then
    with torch_threads():                       # the source's images with compensated labels
        if identity:
            convert = lambda im: np.asarray(im, np.uint8)
        else:
            translator = load_translator(model)
            convert = lambda im: translator.translate(im, src_ref, tgt_ref, int(sampler_steps))
        result = yield from _stream(source_markers, target_markers, eval_indenters, val_indenters, n_eval,
                                    convert, "m2m", train_indenters=train_indenters)
    result["attrs"].update(sampler_steps=int(sampler_steps), source=source, target=target,
                           **({"same_style": True} if identity else {}))
    return result


def translate_sim_sequence(**kw):
    """Node translate_sim[source,target]: translate_sequence on the scored frames alone (only
    the sim_m2m study's image metrics read it)."""
    result = yield from translate_sequence(**kw, train_indenters=None)
    return result


def flow_warp_sequence(*, source_markers, target_markers, eval_indenters: list[str], n_eval: int,
                       source: str = "", target: str = ""):
    """Node flow_warp[source,target]: the training-free baseline (stages.m2m.flow) with the
    same outputs as translate_sequence, on the test split's scored frames alone (only the
    image metrics read it, and no choice is made with it, so it has no validation split)."""
    from stages.m2m.flow import MarkerFlow, warp
    flow = MarkerFlow(np.asarray(source_markers["reference"], np.uint8))
    tgt_ref = np.asarray(target_markers["reference"], np.uint8)
    convert = lambda ims: np.stack([warp(tgt_ref, flow.field(im)) for im in ims])
    result = yield from _stream(source_markers, target_markers, eval_indenters, (), n_eval,
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
