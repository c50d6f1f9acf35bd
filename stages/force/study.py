"""Scoring the force methods of a study, and the ablation of genforce_plus's additions.

Every method of a source -> target pair reads the target's images with the target's reference
and is scored against the target's labels:

  source_only    own[source], the regressor trained on the source's own labels
  genforce       transfer[...] genforce: M2M translations, the source's labels
  genforce_comp  transfer[...] genforce_comp: the same with the paper's compensation
  genforce_plus  transfer[...] genforce_plus: genforce_comp with our additions (stages.force.plus)
  oracle         own[target], trained on the target's own labels: the ceiling

on two disjoint sets of the target's contacts: the validation indenters, which make every
choice (metrics `<study>_val/...`), and the test indenters, the authors' unseen ones, read by
this final scoring only (metrics `<study>/...`).  Neither set was trained on.
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from stages.common import attrs_of
from stages.force.data import scoring_set
from stages.force.figures import METHODS, r2_hist_png, radar_png, trace_png, violin_png

AXES = ("fx", "fy", "fz", "total")


def check_splits(train: Sequence[str] | None, val: Sequence[str], test: Sequence[str], name: str) -> None:
    """The three indenter splits are disjoint, and validation and test are not empty."""
    from stages.common import InputError
    sets = {"train": set(map(str, train or ())), "validation": set(map(str, val)), "test": set(map(str, test))}
    for what in ("validation", "test"):
        if not sets[what]:
            raise InputError(f"{name}: the {what} split names no indenter")
    for a, b in (("train", "validation"), ("train", "test"), ("validation", "test")):
        both = sorted(sets[a] & sets[b])
        if both:
            raise InputError(f"{name}: indenters {both} are in both the {a} and the {b} split")


def seeds_of(own: Mapping[str, Mapping], transfer: Mapping[str, Mapping]) -> list[int]:
    """The regressor seeds the inputs hold (own labelled "skin=..,seed=..", transfer
    "source=..,target=..,seed=.."), the same for both, in order."""
    def found(table):
        return sorted({int(dict(part.split("=", 1) for part in label.split(","))["seed"]) for label in table})
    seeds = found(own)
    if not seeds or found(transfer) != seeds:
        raise ValueError(f"force study: own holds seeds {seeds}, transfer {found(transfer)}: "
                         "every method needs the same seeds")
    return seeds


def _models(own, transfer, source, target, seed, load):
    tr = transfer[f"source={source},target={target},seed={seed}"]
    return {"source_only": load(own[f"skin={source},seed={seed}"], "weights"), "genforce": load(tr, "genforce"),
            "genforce_comp": load(tr, "genforce_comp"), "genforce_plus": load(tr, "genforce_plus"),
            "oracle": load(own[f"skin={target},seed={seed}"], "weights")}


def seed_statistics(per_seed: Sequence[Mapping[str, float]], prefix: str,
                    groups: Mapping[str, Sequence[str]]) -> dict[str, float]:
    """Means over seeds, and their spread, of a study's force metrics.  per_seed: one mapping
    per regressor seed of `<prefix>/<pair>/<method>/<metric>`; groups: name -> pair labels
    ("mean" is every pair).  Returns per pair and per group `<prefix>/<row>/<method>/<metric>`,
    the mean over seeds (a group's: of the mean over its pairs), and `<...>/<metric>_sd`, the
    standard deviation over seeds (ddof 1; with one seed, none)."""
    out: dict[str, float] = {}
    names = sorted(per_seed[0])
    rows: dict[str, list[str]] = {name.split("/")[1]: [name.split("/")[1]] for name in names}
    rows.update({g: list(p) for g, p in groups.items()})
    leaves = sorted({tuple(name.split("/")[2:]) for name in names})
    for row, pairs in rows.items():
        for method, metric in leaves:
            keys = [f"{prefix}/{p}/{method}/{metric}" for p in pairs]
            if not all(k in per_seed[0] for k in keys):
                continue
            values = np.array([np.mean([m[k] for k in keys]) for m in per_seed])
            out[f"{prefix}/{row}/{method}/{metric}"] = float(values.mean())
            if len(values) > 1:
                out[f"{prefix}/{row}/{method}/{metric}_sd"] = float(values.std(ddof=1))
    return out


def force_study(*, study: str, pairs: Sequence[Sequence[str]], own: Mapping[str, Mapping],
                transfer: Mapping[str, Mapping], markers: Mapping[str, Mapping],
                test_indenters: Sequence[str], val_indenters: Sequence[str],
                trace_frames: int = 1000, groups: Mapping[str, Sequence[Sequence[str]]] | None = None) -> dict:
    """The force part of nodes homo / material / hetero: METHODS per pair and regressor seed,
    scored on the target's validation and test contacts.  Metrics `<study>[_val]/<row>/<method>/
    <metric>` for every pair (`<source>_<target>`), `mean` (all pairs) and each of `groups`,
    the mean over seeds, each beside its `<metric>_sd` over seeds (seed_statistics).  Arrays
    mae/<method> (pairs, 4: fx, fy, fz, total) and r2/<method> (pairs, 3) of the test split,
    means over seeds, pairs, sources, targets, trace/*; figures radar (MAE), r2_hist, trace and
    violin (test split; the trace and violin of the first seed)."""
    from stages.common import torch_threads
    with torch_threads():
        return _force_study(study, [(str(s), str(t)) for s, t in pairs], own, transfer, markers,
                            list(test_indenters), list(val_indenters), int(trace_frames), groups or {})


def _force_study(study, pairs, own, transfer, markers, test_indenters, val_indenters, trace_frames,
                 groups) -> dict:
    from stages.common import torch_device
    from stages.force.metrics import METRICS, force_metrics
    from stages.force.model import load_model, predict_contacts
    dev = torch_device()

    def load(art, prefix):                # batch prediction runs where training does
        return load_model(art, prefix, device=dev)

    def predict(model, data):
        return predict_contacts(model, data["images"], data["contact_id"], data["reference"])

    if not pairs:
        raise ValueError(f"force_study[{study}]: no pairs")
    seeds = seeds_of(own, transfer)
    for s, t in pairs:
        for seed in seeds:
            for name, table, key in (("own", own, f"skin={s},seed={seed}"), ("own", own, f"skin={t},seed={seed}"),
                                     ("transfer", transfer, f"source={s},target={t},seed={seed}")):
                if key not in table:
                    raise KeyError(f"force_study[{study}]: {name} has no {key!r} (pair {s} -> {t})")
        if t not in markers:
            raise KeyError(f"force_study[{study}]: markers has no {t!r} (pair {s} -> {t})")
        check_splits(attrs_of(transfer[f"source={s},target={t},seed={seeds[0]}"]).get("train_indenters"),
                     val_indenters, test_indenters, f"force_study[{study}] {s} -> {t}")
    splits = {study: test_indenters, f"{study}_val": val_indenters}
    sets: dict = {}
    per_seed = {prefix: [{} for _ in seeds] for prefix in splits}
    per_pair: list[dict] = []
    for s, t in pairs:
        for i, seed in enumerate(seeds):
            models = _models(own, transfer, s, t, seed, load)
            for prefix, indenters in splits.items():
                key = (t, prefix)
                if key not in sets:
                    sets[key] = scoring_set(markers[t], indenters, "validation" if prefix.endswith("_val") else "test")
                data = sets[key]
                preds = {m: predict(models[m], data) for m in METHODS}
                scores = {m: force_metrics(preds[m], data["force"]) for m in METHODS}
                for m in METHODS:
                    for k, v in scores[m].items():
                        per_seed[prefix][i][f"{prefix}/{s}_{t}/{m}/{k}"] = v
                if prefix == study and i == 0:
                    per_pair.append({"source": s, "target": t,
                                     "errors": {m: preds[m] - data["force"] for m in METHODS}, "preds": preds})
    labels = [f"{s}_{t}" for s, t in pairs]
    rows = {"mean": labels, **{g: [f"{a}_{b}" for a, b in p] for g, p in groups.items()}}
    metrics: dict = {}
    for prefix in splits:
        metrics.update(seed_statistics(per_seed[prefix], prefix, rows))
    mae = {m: np.array([[metrics[f"{study}/{p}/{m}/mae_{a}"] for a in AXES] for p in labels]) for m in METHODS}
    r2 = {m: np.array([[metrics[f"{study}/{p}/{m}/{k}"] for k in ("r2_fx", "r2_fy", "r2_fz")] for p in labels])
          for m in METHODS}
    for p, row in zip(per_pair, labels):
        p["scores"] = {m: {k: metrics[f"{study}/{row}/{m}/{k}"] for k in METRICS} for m in METHODS}
    # representative pair: the median genforce_comp total MAE
    rep = per_pair[int(np.argsort(mae["genforce_comp"][:, 3])[(len(per_pair) - 1) // 2])]
    test = sets[(rep["target"], study)]
    n = min(trace_frames, len(test["force"]))
    trace = {"true": test["force"][:n],
             **{m: rep["preds"][m][:n].astype(np.float32) for m in ("source_only", "genforce_comp", "genforce_plus")}}
    figures = {"radar": radar_png(mae, labels, study), "r2_hist": r2_hist_png(r2, study),
               "trace": trace_png(trace, f"{study}: {rep['source']} -> {rep['target']}"),
               "violin": violin_png(per_pair, study)}
    return {"mae": mae, "r2": r2, "pairs": labels, "sources": [p["source"] for p in per_pair],
            "targets": [p["target"] for p in per_pair], "trace": trace, "figures": figures,
            "metrics": metrics,
            "attrs": {"study": study, "test_indenters": test_indenters, "val_indenters": val_indenters,
                      "seeds": seeds, "trace_pair": [rep["source"], rep["target"]],
                      "test_frames": {t: int(len(v["force"])) for (t, p), v in sets.items() if p == study},
                      "val_frames": {t: int(len(v["force"])) for (t, p), v in sets.items() if p != study}}}


# ------------------------------------------------------------------------------- ablation

def _seed_models(transfer: Mapping[str, Mapping], source: str, target: str) -> list[tuple[int, Mapping]]:
    """(seed, artifact) of the transfers (keyed "source=..,target=..,seed=..") trained for
    source -> target, in seed order."""
    found = []
    for key, art in transfer.items():
        fields = dict(part.split("=", 1) for part in key.split(","))
        if fields.get("source") == source and fields.get("target") == target:
            found.append((int(fields["seed"]), art))
    return sorted(found, key=lambda x: x[0])


def ablation_study(*, homo: Mapping, material: Mapping, hetero: Mapping, transfer: Mapping[str, Mapping],
                   markers: Mapping[str, Mapping], val_indenters: Sequence[str],
                   additions: Sequence[str]) -> dict:
    """Node `ablation`: what each addition of genforce_plus earns, on the validation indenters.

    For every study (`homo`, `material`, `hetero`: its groups of pairs) and every seed's
    genforce_comp model of each pair (the transfers of `force.seeds`, at least 3), genforce_plus is
    rebuilt with all `additions` and with each one left out in turn (stages.force.plus.apply,
    to genforce_comp's model on the target's view the transfer read), and scored on the
    target's validation contacts.
    With m(s, v) the mean over the study's pairs of the validation MAE (total) of variant v
    from seed s:

      ablation/<study>/<addition>/delta_mae_total   mean over s of m(s, without it) - m(s, all):
                                                    positive means the addition helps
      ablation/<study>/seed_spread/mae_total        the standard deviation over s of m(s, all)
      ablation/<study>/genforce_plus/mae_total      mean over s of m(s, all)
      ablation/<study>/genforce_comp/mae_total      mean over s of m(s, no addition)

and the same four of `mae_fz_light` (the normal MAE at light contact, the grasps' range) in
place of mae_total, where every target's validation set has light contacts.

    An addition whose delta does not beat the seed spread has not earned its place."""
    from stages.common import torch_threads
    from stages.force import plus
    additions = plus.check_additions(additions, "ablation")
    studies = {}
    for study, groups in (("homo", homo), ("material", material), ("hetero", hetero)):
        pairs_of = [[str(s), str(t)] for group in groups.values() for s, t in group]
        studies[study] = [p for k, p in enumerate(pairs_of) if p not in pairs_of[:k]]
    with torch_threads():
        return _ablation(studies, transfer, markers, list(val_indenters), additions)


ABLATION_METRICS = ("mae_total", "mae_fz_light")   # the validation figures each addition is judged by


def ablation_variants(additions: Sequence[str]) -> dict[str, list[str]]:
    """The genforce_plus variants the ablation scores: "all", "none" and "-<addition>"."""
    return {"all": list(additions), "none": [],
            **{f"-{a}": [b for b in additions if b != a] for a in additions}}


def ablation_metrics(study: str, scores: Mapping[str, np.ndarray], additions: Sequence[str],
                     metric: str = "mae_total") -> dict:
    """The ablation's metrics from `scores`: variant -> (seeds, pairs) validation `metric`
    (mae_total, or mae_fz_light); none where a pair's validation set lacks it (NaN)."""
    m = {v: np.asarray(s, float).mean(axis=1) for v, s in scores.items()}     # per seed
    if len(m["all"]) < 3:
        raise ValueError(f"ablation[{study}]: {len(m['all'])} seeds; the seed spread needs 3 or more")
    if not all(np.isfinite(x).all() for x in m.values()):
        return {}
    out = {f"ablation/{study}/seed_spread/{metric}": float(np.std(m["all"], ddof=1)),
           f"ablation/{study}/genforce_plus/{metric}": float(np.mean(m["all"])),
           f"ablation/{study}/genforce_comp/{metric}": float(np.mean(m["none"]))}
    for a in additions:
        out[f"ablation/{study}/{a}/delta_{metric}"] = float(np.mean(m[f"-{a}"] - m["all"]))
    return out


def _ablation(studies, transfer, markers, val_indenters, additions) -> dict:
    from stages.force import plus
    from stages.force.metrics import force_metrics
    from stages.force.model import load_model, predict_contacts
    variants = ablation_variants(additions)
    metrics, per_study, sets = {}, {}, {}
    for study, study_pairs in studies.items():
        study_pairs = [(str(s), str(t)) for s, t in study_pairs]
        # metric -> variant -> per pair: per seed (NaN: the pair's validation set lacks it)
        scores = {m: {v: [] for v in variants} for m in ABLATION_METRICS}
        for s, t in study_pairs:
            key = f"source={s},target={t}"
            trained = _seed_models(transfer, s, t)
            if not trained:
                raise KeyError(f"ablation[{study}]: transfer has no {key!r}")
            info = attrs_of(trained[0][1])
            overlap = sorted(set(info.get("train_indenters") or ()) & set(val_indenters))
            if overlap:
                from stages.common import InputError
                raise InputError(f"ablation[{study}]: validation indenters {overlap} trained {s} -> {t}")
            if t not in sets:
                sets[t] = scoring_set(markers[t], val_indenters, "validation")
            val = sets[t]
            view = plus.target_view(markers[t], info.get("shear_ratios"), punch_scale=info.get("punch_scale"))
            models = [load_model(a, "genforce_comp") for _, a in trained]
            seen = scores["mae_total"]["all"]
            if seen and len(models) != len(seen[0]):
                raise ValueError(f"ablation[{study}]: {s} -> {t} has {len(models)} seed models, the "
                                 f"study's other pairs {len(seen[0])}")
            for v, used in variants.items():
                scored = [force_metrics(predict_contacts(plus.apply(model, view, used)[0], val["images"],
                                                         val["contact_id"], val["reference"]), val["force"])
                          for model in models]
                for m in ABLATION_METRICS:
                    scores[m][v].append([x.get(m, np.nan) for x in scored])
        tables = {m: {v: np.asarray(by_v[v], float).T for v in variants}      # (seeds, pairs)
                  for m, by_v in scores.items()}
        for m, table in tables.items():
            metrics.update(ablation_metrics(study, table, additions, m))
        per_study[study] = tables["mae_total"]
    from stages.force.figures import ablation_png
    from stages.summary import ablation_table, markdown
    table = ablation_table(metrics)
    return {"metrics": metrics,
            **{f"mae/{study}/{v}": table[v] for study, table in per_study.items() for v in table},
            "figures": {"ablation": ablation_png(metrics, list(studies), additions)},
            "attrs": {"report_tables": [table], "markdown": markdown([table]),
                      "studies": {k: [list(p) for p in v] for k, v in studies.items()},
                      "additions": list(additions), "val_indenters": val_indenters,
                      "seeds": len(next(iter(per_study.values()))["all"]) if per_study else 0}}
