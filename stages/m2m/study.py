"""M2M's image study: FID/KID of before / m2m / flow_warp per pair, heatmaps, t-SNE, and how
well each keeps the deformation (the sim_m2m node, and the image part of homo, material and
hetero)."""
from __future__ import annotations

import time
from typing import Mapping

import numpy as np

from stages.figures import figure_png
from stages.m2m.data import read_rows

TSNE_PER_SET = 12       # points per image set in the t-SNE figure


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
                if split and m != "before" and f"features{split}" not in sources[m].get(pair_label(s, t), {}):
                    continue         # a method no choice reads has no validation split (flow_warp)
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
            if np.isfinite(fids[m]).any():
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
        try:
            rows_s, rows_t = rows_of(markers[s], frames), rows_of(markers[t], frames)
        except KeyError:             # the source never pressed some of those locations: no truth
            continue
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
