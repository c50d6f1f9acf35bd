"""The learning curve (node `curves`, run when named): how far the profile's force models stop
from the end of their training.

For every study (an instance `curves[study=...]` each), the oracle (own[target]) of every
target and genforce_comp of every pair are trained at 1x and at `curves.factors` times (2x, 4x)
the profile's training length (force.steps and force.finetune_steps times k; everything else as
the profile trains them, the learning-rate schedule stretched to the length) from the first
regressor seed, and scored on the targets' validation contacts.  The 1x models are the
profile's own (own, transfer); the node trains the longer ones (the oracle with own's
stages.force.fit.train_own).

Metrics, per study and method (oracle, genforce_comp):

  curve/<study>/<method>/<k>x/mae_total   validation MAE (total), the mean over the study's pairs
  curve/<study>/<method>/<k>x/mae_fz      the same for Fz
  curve/<study>/<method>/ratio            1x mae_total over the longest's: the profile is
                                          converged where it is at most CONVERGED (1.10)
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from stages.common import attrs_of

CONVERGED = 1.10          # 1x within 10% of the longest training: converged
CURVE_METHODS = ("oracle", "genforce_comp")


def _fields(label: str) -> dict[str, str]:
    return dict(part.split("=", 1) for part in label.split(","))


def check_factors(factors: Sequence) -> list[int]:
    """curves.factors as sorted integers > 1, without repeats; anything else an InputError."""
    from stages.common import InputError
    if isinstance(factors, (str, bytes)) or not isinstance(factors, Sequence) or not factors:
        raise InputError(f"curves.factors must be a list of integers > 1, got {factors!r}")
    if any(isinstance(f, bool) or not isinstance(f, int) or f < 2 for f in factors) or len(set(factors)) != len(factors):
        raise InputError(f"curves.factors must be distinct integers > 1, got {list(factors)}")
    return sorted(int(f) for f in factors)


def curve_metrics(study: str, scores: Mapping[str, Mapping[int, Sequence[Mapping[str, float]]]]) -> dict:
    """The curve's metrics from `scores`: method -> factor -> the force_metrics of each of the
    study's pairs (the same pairs at every factor)."""
    out: dict[str, float] = {}
    for method, by_factor in scores.items():
        factors = sorted(by_factor)
        if 1 not in by_factor or len(factors) < 2:
            raise ValueError(f"curve[{study}/{method}]: factors {factors}; the curve needs 1 and a longer one")
        counts = {len(v) for v in by_factor.values()}
        if len(counts) != 1 or 0 in counts:
            raise ValueError(f"curve[{study}/{method}]: pair counts {sorted(counts)} differ between factors")
        for k in factors:
            for metric in ("mae_total", "mae_fz"):
                out[f"curve/{study}/{method}/{k}x/{metric}"] = float(np.mean([s[metric] for s in by_factor[k]]))
        longest = out[f"curve/{study}/{method}/{factors[-1]}x/mae_total"]
        out[f"curve/{study}/{method}/ratio"] = out[f"curve/{study}/{method}/1x/mae_total"] / max(longest, 1e-12)
    return out


def train_comp(translated: Mapping, curves: Mapping | None, config: Mapping, *, steps: int,
               finetune_steps: int, batch_size: int, lr: float, seed: int,
               train_indenters: Sequence[str] | None, checkpoint=None, label: str = "genforce_comp"):
    """transfer[source,target]'s genforce_comp as fit_transfer trains it (the translations, the
    compensated labels of `curves`, the two-stage recipe, the seed), for `steps` (and
    `finetune_steps`) steps."""
    from stages.force.data import contact_runs, read_runs
    from stages.force.fit import compensated_labels, recipe, split_config
    from stages.force.train import fit_two_stage, make_sequences
    model_cfg, train = split_config(config)
    runs = contact_runs(translated, train_indenters)
    comp = compensated_labels(translated, curves)
    seqs = make_sequences(read_runs(translated, "images", runs), [comp[a:b] for a, b in runs],
                          np.asarray(translated["reference"]), model_cfg)
    model, _ = fit_two_stage(seqs, model_cfg, steps=int(steps), finetune_steps=int(finetune_steps),
                             batch_size=int(batch_size), lr=float(lr), seed=int(seed),
                             **recipe(train), finetune_lr_factor=float(train["finetune_lr_factor"]), desc=label,
                             checkpoint=checkpoint, label=label)
    return model


def curves_study(*, study: str, homo: Mapping, material: Mapping, hetero: Mapping,
                 own: Mapping[str, Mapping], transfer: Mapping[str, Mapping],
                 translated: Mapping[str, Mapping], markers: Mapping[str, Mapping],
                 config: Mapping, steps: int, finetune_steps: int, batch_size: int, lr: float,
                 seeds: Sequence[int], factors: Sequence[int], train_indenters: Sequence[str],
                 val_indenters: Sequence[str], checkpoint: str | None = None) -> dict:
    """Node `curves[study]`: the learning curve of one study (the module's docstring).  The
    1x models are the first seed's own and transfer; the longer ones are trained here (every
    fit resumes from the node's checkpoint after an interruption)."""
    from stages.common import torch_threads
    from stages.force.fit import _checkpoint, train_own
    factors = check_factors(factors)
    groups = {"homo": homo, "material": material, "hetero": hetero}[study]
    pairs_of = [(str(s), str(t)) for group in groups.values() for s, t in group]
    pairs = [p for k, p in enumerate(pairs_of) if p not in pairs_of[:k]]
    seed = int(seeds[0])
    overlap = sorted(set(map(str, train_indenters)) & set(map(str, val_indenters)))
    if overlap:
        from stages.common import InputError
        raise InputError(f"curves[{study}]: indenters {overlap} are in both the train and the validation split")
    ckpt = _checkpoint(checkpoint)
    kw = dict(config=config, batch_size=batch_size, lr=lr, seed=seed)

    def trained(method, s, t, k):
        if method == "oracle":
            if k == 1:
                return _find(own, "own", skin=t, seed=seed), "weights"
            model, _ = train_own(markers[t], steps=k * int(steps), train_indenters=train_indenters,
                                 checkpoint=ckpt, label=f"oracle/{t}/{k}x", desc=f"oracle/{t}/{k}x", **kw)
            return {"model": model}, None
        art = _find(transfer, "transfer", source=s, target=t, seed=seed)
        if k == 1:
            return art, "genforce_comp"
        key = f"source={s},target={t}"
        if key not in translated:
            raise KeyError(f"curves[{study}]: translated has no {key!r}")
        return {"model": train_comp(translated[key], attrs_of(art).get("curves"), steps=k * int(steps),
                                    finetune_steps=k * int(finetune_steps), train_indenters=train_indenters,
                                    checkpoint=ckpt, label=f"genforce_comp/{s}_{t}/{k}x", **kw)}, None
    with torch_threads():
        return _curves(study, pairs, trained, markers, list(val_indenters), int(steps), seed, factors)


def _find(table: Mapping[str, Mapping], name: str, **want):
    for label, art in table.items():
        if all(_fields(label).get(k) == str(v) for k, v in want.items()):
            return art
    raise KeyError(f"curves: {name} has no {','.join(f'{k}={v}' for k, v in want.items())}")


def _curves(study, pairs, trained, markers, val_indenters, steps, seed, factors) -> dict:
    """Score `trained(method, source, target, k)` -> (artifact, group) (or ({"model": m}, None))
    on each pair's target's validation contacts."""
    from stages.force.data import scoring_set
    from stages.force.metrics import force_metrics
    from stages.force.model import load_model, predict_contacts
    lengths = {k: k * steps for k in [1] + factors}
    attrs = {"study": study, "pairs": [list(p) for p in pairs], "steps": lengths, "seed": seed,
             "val_indenters": val_indenters, "converged_at": CONVERGED}
    if not pairs:
        return {"metrics": {}, "attrs": {**attrs, "markdown": ""}}
    sets, memo = {}, {}
    scores = {m: {k: [] for k in lengths} for m in CURVE_METHODS}
    for s, t in pairs:
        if t not in markers:
            raise KeyError(f"curves[{study}]: markers has no {t!r}")
        if t not in sets:
            sets[t] = scoring_set(markers[t], val_indenters, "validation")
        val = sets[t]
        for method in CURVE_METHODS:
            for k in lengths:
                key = (method, t, k) if method == "oracle" else (method, s, t, k)
                if key not in memo:        # an oracle serves every pair into its target
                    art, group = trained(method, s, t, k)
                    model = art["model"] if group is None else load_model(art, group)
                    pred = predict_contacts(model, val["images"], val["contact_id"], val["reference"])
                    memo[key] = force_metrics(pred, val["force"])
                scores[method][k].append(memo[key])
    metrics = curve_metrics(study, scores)
    from stages.force.figures import curves_png
    return {"metrics": metrics,
            "figures": {"curves": curves_png(metrics, [study], lengths, CURVE_METHODS)},
            "attrs": {**attrs, "markdown": curves_markdown(metrics, [study], list(lengths))}}


def curves_markdown(metrics: Mapping[str, float], studies: Sequence[str], factors: Sequence[int]) -> str:
    """The curve's table: validation MAE total (N) per study and method at each length, and the
    1x / longest ratio with its verdict."""
    head = ["study", "method"] + [f"{k}x" for k in factors] + ["1x / longest", "converged"]
    rows = []
    for study in studies:
        for method in CURVE_METHODS:
            ratio = metrics[f"curve/{study}/{method}/ratio"]
            rows.append([study, method] + [f"{metrics[f'curve/{study}/{method}/{k}x/mae_total']:.3f}" for k in factors]
                        + [f"{ratio:.2f}", "yes" if ratio <= CONVERGED else "no"])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])
