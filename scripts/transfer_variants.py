"""A transfer pair refitted or re-read with one of the variants the README's "Tried" lists
measure, scored as the studies score it: R2 per axis and MAE (N, all axes) on the target's
contacts of the test indenters, per seed and for the plain mean of the seeds' predictions (as
genforce_comp_ensemble with `force.ensemble: mean`; the default weighs the seeds, which a
variant's refit would move too).  Nothing is written to the store.

    python scripts/transfer_variants.py PAIR [--profile allpairs] [--seeds 0 1 2] VARIANT

PAIR is SOURCE:TARGET (a `transfer[source,target]` of the profile).  VARIANT, one of:

  --redraw stored            M2M's raw translations redrawn as the translate node redrew them
                             (its attrs: gains, tilt, or the shift read off the source), then
                             fit_transfer with the node's params: reproduces the stored model of
                             the transfer's seed exactly;
  --shift-gain X,Y           a 3-axis taxel target's common shift scaled by (X, Y) instead;
  --tilt split               a z-only taxel target's load tilt fitted with the drawn x moment in
                             two parts, each contact's place (its frames' load-weighted mean
                             centroid times the frame's load) and the drift around it;
  --tilt move                each contact's drawn load pattern moved (linear interpolation over
                             the taxels) so that its centroid lands at the fitted place weight
                             times where M2M drew it (x only), then the tilt refitted;
  --tilt source-shift        a z-only target's tilt (both axes) fitted, and drawn, with a 3-axis
                             source's own common shift in place of the one M2M drew, then
                             nodes.shrink_guard as the node applies it;
  --from-source dots|cells   the redrawn translation's shear cue read off the source's own
                             images (ridge regression on the paired frames against the target's
                             own): a 3-axis target's common shift, a z-only target's load moment;
                             dots: a taxel source's dots (into the 3-axis uSkin what
                             m2m.redraw_source_shift does), cells: any source's marker image on a
                             4x4 grid of cells (cell_cues);
  --linear-fz shift-free     the stored models' linear Fz read refitted on the image statistics a
                             dot's motion leaves alike (brightening less darkening, and the two
                             shares' difference), fz_readout redone;
  --shear-readout fz         the stored models' shear read as g x its shear + c x its Fz per axis,
                             fitted on the transfer's read-out frames and labels.

Seed k reads the pair as its ensemble member does: the transfer's own seed the translation of
`m2m` (`translate[source,target]`), another seed k the translation of M2M fine-tuned from k
(`translate_seed[source,target,seed=k]`, `m2m_seed[seed=k]`: a hetero pair of the profile with k
in hetero.seeds).  The refits train seed k with fit_transfer (the whole transfer from seed k) on
that translation, redrawn; the re-reads read the transfer's model for its own seed and
`hetero_seed[source,target,seed=k]` for the others.  --cache DIR keeps M2M's raw translations
between runs.
"""
import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

TOOL = "transfer_variants"


def _args():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("pair", help="SOURCE:TARGET")
    p.add_argument("--profile", default="default")
    p.add_argument("--store", default=None, help="store directory (default: the project's)")
    p.add_argument("--seeds", type=int, nargs="+", default=None,
                   help="regressor seeds (default: the transfer's own)")
    p.add_argument("--cache", default=None, help="directory for M2M's raw translations")
    v = p.add_mutually_exclusive_group(required=True)
    v.add_argument("--redraw", choices=["stored"])
    v.add_argument("--shift-gain", type=lambda s: tuple(float(x) for x in s.split(",")))
    v.add_argument("--tilt", choices=["split", "move", "source-shift"])
    v.add_argument("--from-source", choices=["dots", "cells"])
    v.add_argument("--linear-fz", choices=["shift-free"])
    v.add_argument("--shear-readout", choices=["fz"])
    a = p.parse_args()
    if a.shift_gain is not None and (len(a.shift_gain) != 2 or min(a.shift_gain) <= 0):
        p.error(f"--shift-gain takes two positive numbers X,Y, got {a.shift_gain}")
    if a.pair.count(":") != 1:
        p.error(f"PAIR is SOURCE:TARGET, got {a.pair!r}")
    return a


class Store:
    """The profile's artifacts by instance name, and its params."""

    def __init__(self, store, profile):
        from pipeline import params as P
        from pipeline.config import find_project
        project = find_project(REPO)
        self.store = store or str(project.store_dir)
        self.profile = profile
        self.params = P.load(project.params_file, profile, [], project.profiles_dir)
        self._opened = {}

    def __call__(self, instance):
        """The instance's artifact, looked up (a `pipeline get`) and opened once per run."""
        from pipeline.artifact import Artifact
        from store_lookup import artifact_path
        if instance not in self._opened:
            self._opened[instance] = Artifact(artifact_path(self.store, instance, TOOL, profile=self.profile))
        return self._opened[instance]


def _score(y, p) -> str:
    from sklearn.metrics import r2_score
    r2 = "/".join(f"{r2_score(y[:, i], p[:, i]):.3f}" for i in range(3))
    return f"R2 Fx/Fy/Fz {r2}  MAE {np.abs(p - y).mean():.3f} N"


def _report(name, y, preds: dict) -> None:
    for seed, p in preds.items():
        print(f"{name}  seed {seed}: {_score(y, p)}")
    if len(preds) > 1:
        print(f"{name}  mean of {len(preds)}: {_score(y, np.mean(list(preds.values()), 0))}")


# ------------------------------------------------------------------------- refits

def _member(get, source, target, seed):
    """(translate instance, M2M instance) that seed `seed`'s model of the pair reads: the
    transfer's own seed `translate` and `m2m`, another the member's translate_seed and m2m_seed."""
    own = int(get(f"transfer[source={source},target={target}]").provenance["params"]["seed"])
    if seed is None or int(seed) == own:
        return f"translate[source={source},target={target}]", "m2m"
    return f"translate_seed[source={source},target={target},seed={int(seed)}]", f"m2m_seed[seed={int(seed)}]"


def _raw_translations(get, source, target, cache, seed=None):
    """M2M's translations of the source's whole sequence into the target, before any redraw, by
    the M2M seed `seed`'s model reads (_member)."""
    from stages.common import attrs_of
    from stages.m2m.model import load_translator
    from stages.m2m.nodes import CHUNK
    translation, m2m = _member(get, source, target, seed)
    tag = "" if m2m == "m2m" else f"_seed{int(seed)}"
    path = Path(cache) / f"raw_{source}_{target}{tag}.npy" if cache else None
    if path and path.is_file():
        return np.load(path)
    src, tgt, tra = get(f"markers[skin={source}]"), get(f"markers[skin={target}]"), get(translation)
    steps = int(attrs_of(tra).get("sampler_steps", 1))
    translator = load_translator(get(m2m))
    ims = src["images"]
    src_ref, tgt_ref = np.asarray(src["reference"], np.uint8), np.asarray(tgt["reference"], np.uint8)
    out = np.concatenate([translator.translate(np.asarray(ims[i:i + CHUNK]), src_ref, tgt_ref, steps)
                          for i in range(0, len(ims), CHUNK)])
    if path:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.save(path, out)
    return out


def _places(moment, load, contact_id):
    """Per frame (N, 2 each): its contact's load-weighted mean centroid of the load moment (sum
    m w / sum w^2 over the contact's frames, w the load where positive), and the place part of
    its moment, that centroid times the frame's load."""
    w = np.clip(load, 0, None)
    centroid = np.zeros_like(moment)
    for c in np.unique(contact_id):
        s = contact_id == c
        centroid[s] = (moment[s] * w[s, None]).sum(0) / max(float((w[s] ** 2).sum()), 1e-9)
    return centroid, centroid * load[:, None]


def _redrawn(get, args, source, target, seed=None):
    """The images of the translation seed `seed`'s model reads (_member) redrawn per the
    variant (N, H, W) uint8."""
    from stages.common import attrs_of
    from stages.m2m.data import paired_table, take_rows
    from stages.markers.uskin import USKIN_PAD_MM, TAXELS, dot_changes, load_moments, redraw
    translation, m2m_name = _member(get, source, target, seed)
    tra = get(translation)
    tgt, src = get(f"markers[skin={target}]"), get(f"markers[skin={source}]")
    attrs, settings = attrs_of(tra), attrs_of(tgt).get("settings", {})
    if not attrs.get("redraw_taxels"):
        sys.exit(f"{TOOL}: {target} is not a redrawn taxel target (translate's attrs have no redraw)")
    raw = _raw_translations(get, source, target, args.cache, seed)
    stored = {"gain": tuple(attrs["redraw_gain"])}
    for key in ("shift_gain", "tilt"):
        if f"redraw_{key}" in attrs:
            stored[key] = tuple(tuple(v) if isinstance(v, list) else v for v in attrs[f"redraw_{key}"])
    if args.redraw:
        if "redraw_source_shift" in attrs:              # a 3-axis target's shift read off a taxel source
            from stages.m2m.nodes import read_source_shift
            return redraw(raw, settings, shift=read_source_shift(
                attrs["redraw_source_shift"], np.asarray(src["images"]), attrs_of(src)["settings"]))
        return redraw(raw, settings, **stored)
    z_only = bool(settings.get("z_only", False))
    if args.from_source:
        return _from_source(get, raw, src, tgt, settings, m2m_name, args.from_source)
    if args.shift_gain:
        if z_only:
            sys.exit(f"{TOOL}: --shift-gain is for a 3-axis taxel target; {target} is z-only")
        return redraw(raw, settings, gain=stored["gain"], shift_gain=args.shift_gain)
    if not z_only:
        sys.exit(f"{TOOL}: --tilt is for a z-only taxel target; {target} is not")
    pad = tuple(float(v) for v in settings.get("pad_mm", USKIN_PAD_MM))
    offsets, changes = dot_changes(raw, settings)
    moment, shift = load_moments(offsets, changes, pad)
    load = changes.sum(1)
    centroid, place = _places(moment, load, np.asarray(src["contact_id"]))
    m2m = attrs_of(get(m2m_name))             # the frames M2M's fine-tune paired, as the node fits on
    _, rows = paired_table({"s": src, "t": tgt}, ["s", "t"], m2m["train_indenters"],
                           int(m2m.get("pairs_per_skin", 0)))
    real_off, real_area = dot_changes(take_rows(tgt["images"], rows[1]), settings)
    real_moment, _ = load_moments(real_off, real_area, pad)
    r0 = rows[0]
    x = np.stack([place[:, 0], moment[:, 0] - place[:, 0], shift[:, 0]], 1)
    (w_place, w_drift, b), *_ = np.linalg.lstsq(x[r0], real_moment[:, 0], rcond=None)
    a_y, b_y = np.asarray(stored.get("tilt", ((1.0, 0.0), (1.0, 0.0))), float)[1]   # y: the node's tilt
    want = moment.copy()
    want[:, 1] = a_y * moment[:, 1] + b_y * shift[:, 1]
    if args.tilt == "source-shift":             # the shift term from a 3-axis source's own dots
        s_off, s_area = dot_changes(np.asarray(src["images"]), attrs_of(src)["settings"])
        _, s_shift = load_moments(s_off, s_area, pad)
        from stages.m2m.nodes import shrink_guard
        for k in (0, 1):
            fit = np.stack([moment[r0, k], s_shift[r0, k]], 1)
            (a, b), *_ = np.linalg.lstsq(fit, real_moment[:, k], rcond=None)
            ga, gb = shrink_guard(k, (float(a), float(b)), changes[r0], moment[r0], s_shift[r0], real_area,
                                  real_moment, settings, pad)
            print(f"tilt {'xy'[k]} on the source's shift: a {a:.3f}, b {b:.1f}; guarded {ga:.3f}, {gb:.1f}")
            want[:, k] = ga * moment[:, k] + gb * s_shift[:, k]
    elif args.tilt == "split":
        print(f"tilt x: place {w_place:.3f}, drift {w_drift:.3f}, b {b:.1f}")
        want[:, 0] = x @ np.array([w_place, w_drift, b])
    else:
        from scipy.ndimage import shift as nd_shift
        rows_n, cols_n = TAXELS
        step = centroid[:, 0] * (w_place - 1.0) / (pad[0] / cols_n)
        changes = np.stack([nd_shift(m, (0.0, s), order=1, mode="constant", cval=0.0)
                            for m, s in zip(changes.reshape(-1, rows_n, cols_n), step)]).reshape(len(raw), -1)
        moment, _ = load_moments(offsets, changes, pad)
        fit = np.stack([moment[r0, 0], shift[r0, 0]], 1)
        (a, b), *_ = np.linalg.lstsq(fit, real_moment[:, 0], rcond=None)
        print(f"contacts moved by place weight {w_place:.3f}; tilt x refitted: a {a:.3f}, b {b:.1f}")
        want = np.stack([a * moment[:, 0] + b * shift[:, 0], a_y * moment[:, 1] + b_y * shift[:, 1]], 1)
    return _draw_tilted(changes, moment, want, settings, pad, raw.shape[1:])


def _draw_tilted(changes, moment, want, settings, pad, size):
    """A z-only skin's images: its dots at their taxels, their area changes (N, 16) tilted so that
    their first moment `moment` (N, 2) becomes `want` (uskin.tilt_changes), clipped as the skin
    draws them."""
    from stages.markers.uskin import _draw, taxel_centres, tilt_changes
    base = float(settings.get("base_area"))
    areas = np.clip(base + tilt_changes(changes, moment, want, pad), float(settings.get("min_area", base)),
                    float(settings.get("max_area", 16.0)))
    return _draw(np.repeat(taxel_centres(pad)[None], len(changes), 0), areas, size=size, pad_mm=pad)


def cell_cues(images, reference, grid=(4, 4)) -> np.ndarray:
    """(N, 3*cells): per cell of a grid over the image, the change from the reference of its
    white area and of its two first moments (pixels, from the cell's centre)."""
    ims = np.asarray(images, np.float32) / 255.0
    ref = np.asarray(reference, np.float32) / 255.0
    n, h, w = ims.shape
    gy, gx = grid
    d = ims - ref[None]
    ys = (np.arange(h) + 0.5) % (h / gy) - h / gy / 2
    xs = (np.arange(w) + 0.5) % (w / gx) - w / gx / 2
    cell = lambda a: a.reshape(n, gy, h // gy, gx, w // gx).sum((2, 4)).reshape(n, -1)  # noqa: E731
    return np.concatenate([cell(d), cell(d * xs[None, None, :]), cell(d * ys[None, :, None])], 1)


def _from_source(get, raw, src, tgt, settings, m2m_name, mode):
    """The translation's shear cue read off the source's own images instead of M2M's drawing,
    by ridge regression (RidgeCV) on the paired frames against the target's own: a 3-axis
    target's common shift (uskin.redraw's shift), a z-only target's load moment (a plane across
    the pad, as the tilt).  mode "dots": a taxel source's uskin.dot_features (on a 3-axis
    target what m2m.redraw_source_shift does); "cells": any source's cell_cues, standardised on
    the paired frames."""
    from sklearn.linear_model import RidgeCV
    from stages.common import attrs_of
    from stages.m2m.data import paired_table, take_rows
    from stages.m2m.nodes import SHIFT_READ_ALPHAS
    from stages.markers.uskin import USKIN_PAD_MM, dot_changes, dot_features, load_moments, redraw
    src_settings = attrs_of(src).get("settings")
    if mode == "dots" and not src_settings:
        sys.exit(f"{TOOL}: --from-source dots needs a taxel source")
    m2m = attrs_of(get(m2m_name))
    _, rows = paired_table({"s": src, "t": tgt}, ["s", "t"], m2m["train_indenters"],
                           int(m2m.get("pairs_per_skin", 0)))
    images, alphas = src["images"], SHIFT_READ_ALPHAS
    if mode == "cells":
        x = np.concatenate([cell_cues(np.asarray(images[i:i + 512]), np.asarray(src["reference"]))
                            for i in range(0, len(images), 512)])
        sd = x[rows[0]].std(0)
        x, alphas = (x - x[rows[0]].mean(0)) / np.where(sd > 1e-9, sd, 1.0), np.logspace(-4, 4, 33)
    else:
        x = dot_features(np.asarray(images), src_settings)
    pad = tuple(float(v) for v in settings.get("pad_mm", USKIN_PAD_MM))
    real_moment, real_shift = load_moments(*dot_changes(take_rows(tgt["images"], rows[1]), settings), pad)
    z_only = bool(settings.get("z_only", False))
    want_of = real_moment if z_only else real_shift
    want = np.stack([RidgeCV(alphas=alphas).fit(x[rows[0]], want_of[:, k]).predict(x) for k in (0, 1)], 1)
    if not z_only:
        return redraw(raw, settings, shift=want)
    offsets, changes = dot_changes(raw, settings)
    return _draw_tilted(changes, load_moments(offsets, changes, pad)[0], want, settings, pad, raw.shape[1:])


def refit(get, args, source, target, test):
    from stages.force.model import from_arrays, predict_contacts
    from stages.force.nodes import fit_transfer
    tr = get(f"transfer[source={source},target={target}]")
    params = dict(tr.provenance["params"])
    cal = lambda sensor: get(f"calibrate[sensor={sensor}]")  # noqa: E731
    preds = {}
    for seed in args.seeds or [int(params["seed"])]:
        tra = get(_member(get, source, target, seed)[0])
        translated = {k: np.asarray(tra[k]) for k in tra.keys()
                      if k not in ("images", "features", "figures/examples", "eval_frames")}
        translated["images"] = _redrawn(get, args, source, target, seed)
        if args.redraw:
            diff = np.abs(translated["images"].astype(int) - np.asarray(tra["images"]).astype(int)).mean()
            print(f"seed {seed} redrawn as stored: mean |difference| {diff:.4f} of 255")
        translated["indenters"] = np.asarray(tra["indenters"]).astype(str)
        out = fit_transfer(translated=translated, source_calibration=cal(params["source_spec"]["sensor"]),
                           target_calibration=cal(params["target_spec"]["sensor"]), source=source,
                           target=target, target_markers=get(f"markers[skin={target}]"),
                           indenters=get("indenters"), captured_calibrations={},
                           **{**params, "seed": seed})
        model = from_arrays(out["genforce_comp"], out["attrs"]["config"])
        preds[seed] = predict_contacts(model, test["images"], test["contact_id"], test["reference"])
    return preds


# ------------------------------------------------------------------------- re-reads

def _stored_models(get, source, target, seeds):
    from stages.common import attrs_of
    from stages.force.model import load_model
    tr = get(f"transfer[source={source},target={target}]")
    own = int(tr.provenance["params"]["seed"])
    models = {}
    for seed in seeds or [own]:
        if seed == own:
            models[seed] = load_model(tr, "genforce_comp")
            continue
        models[seed] = load_model(get(f"hetero_seed[source={source},target={target},seed={seed}]"),
                                  "genforce_comp")
    return tr, attrs_of(tr), models


def _statistics(model, images, reference):
    from stages.force.model import image_statistics, prepare
    cfg = model.config
    return np.concatenate([image_statistics(prepare(images[i:i + 256], reference, cfg), cfg["input_mode"]).numpy()
                           for i in range(0, len(images), 256)])


def fit_shift_free(train_stats, fz, paired_translated, paired_target):
    """The linear Fz read (4 coefficients on STATISTICS, intercept) fitted as fit_linear_fz fits
    it, but on the two statistics a dot's motion leaves alike: brightening less darkening and the
    brighter less the darker share.  Each is scaled, for the fit, by the least-squares ratio of
    the target's own to the translations' at the paired frames (K,4 each), so that the read
    applies to the target's statistics as they are.  Returns coefficients (+c0, -c0, +c1, -c1)."""
    from sklearn.linear_model import RidgeCV
    net = lambda s: np.stack([s[:, 0] - s[:, 1], s[:, 2] - s[:, 3]], 1)  # noqa: E731
    a, b = net(np.asarray(paired_translated, float)), net(np.asarray(paired_target, float))
    den = (a * a).sum(0)
    scale = np.where(den > 0, (a * b).sum(0) / np.where(den > 0, den, 1.0), 1.0)
    x = net(np.asarray(train_stats, float)) * scale
    mu, sd = x.mean(0), np.where(x.std(0) > 0, x.std(0), 1.0)
    ridge = RidgeCV(alphas=np.logspace(-4, 3, 15)).fit((x - mu) / sd, np.asarray(fz, float))
    c = ridge.coef_ / sd
    return np.array([c[0], -c[0], c[1], -c[1]], np.float32), float(ridge.intercept_ - c @ mu)


def shift_free_coefficients(model, translated, target_markers, runs, fz, paired_rows):
    """fit_shift_free on the translated frames of `runs` and their Fz labels, with the image
    statistics of the paired frames (paired_rows (2,K): translated, target)."""
    from stages.m2m.data import take_rows
    ref_tr, ref_t = np.asarray(translated["reference"]), np.asarray(target_markers["reference"])
    rows = np.concatenate([np.arange(a, b) for a, b in runs])
    return fit_shift_free(_statistics(model, take_rows(translated["images"], rows), ref_tr),
                          np.asarray(fz)[rows],
                          _statistics(model, take_rows(translated["images"], paired_rows[0]), ref_tr),
                          _statistics(model, take_rows(target_markers["images"], paired_rows[1]), ref_t))


def reread(get, args, source, target, test):
    from stages.force.model import predict_contacts
    from stages.force.nodes import (_paired_rows, _target_predictions, contact_runs, fz_readout,
                                    recorded_compensation, scale_fz)
    tr, attrs, models = _stored_models(get, source, target, args.seeds)
    tra, tgt = get(f"translate[source={source},target={target}]"), get(f"markers[skin={target}]")
    _, rows = _paired_rows(tra, tgt, attrs["train_indenters"], int(tr.provenance["params"]["align_pairs"]))
    read = lambda m: predict_contacts(m, test["images"], test["contact_id"], test["reference"])  # noqa: E731
    stored = {seed: read(m) for seed, m in models.items()}
    if args.linear_fz:
        lin = attrs.get("linear_fz") or {}
        lin = lin.get("genforce_comp", lin.get("genforce"))
        if not lin:
            sys.exit(f"{TOOL}: transfer[{source},{target}] has no linear Fz read")
        out = {}
        for seed, m in models.items():          # each on the translation its model trained on
            tra_k = get(_member(get, source, target, seed)[0])
            _, rows_k = _paired_rows(tra_k, tgt, attrs["train_indenters"],
                                     int(tr.provenance["params"]["align_pairs"]))
            fz = recorded_compensation(tra_k, attrs)[:, 2]
            runs = contact_runs(tra_k, attrs["train_indenters"])
            coef, intercept = shift_free_coefficients(m, tra_k, tgt, runs, fz, rows_k)
            print(f"seed {seed} shift-free read: coefficients {[round(float(c), 1) for c in coef]}, "
                  f"intercept {intercept:.2f}")
            m.set_linear_fz(coef, intercept, float(lin["weight"]))
            gain, raw = fz_readout(m, tra_k, tgt, rows_k)
            scale_fz(m, gain)
            out[seed] = read(m)
        return stored, out
    if "readout_shear" not in tr.keys():
        sys.exit(f"{TOOL}: transfer[{source},{target}] has no shear read-out labels")
    labels = np.asarray(tr["readout_shear"], float)
    out = {}
    for seed, m in models.items():
        on = _target_predictions(m, tgt, rows[1]).astype(float)
        p = stored[seed].astype(float).copy()
        for k in (0, 1):
            c, *_ = np.linalg.lstsq(on[:, [k, 2]], labels[:, k], rcond=None)
            p[:, k] = stored[seed][:, [k, 2]] @ c
        out[seed] = p
    return stored, out


def main():
    args = _args()
    from stages.force.nodes import _test_set
    source, target = args.pair.split(":")
    get = Store(args.store, args.profile)
    test = _test_set(get(f"markers[skin={target}]"), get.params["splits"]["test_indenters"])
    y = test["force"]
    if args.linear_fz or args.shear_readout:
        stored, variant = reread(get, args, source, target, test)
        _report("stored ", y, stored)
        _report("variant", y, variant)
    else:
        _report("refit  ", y, refit(get, args, source, target, test))


if __name__ == "__main__":
    main()
