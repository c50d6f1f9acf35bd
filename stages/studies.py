"""The transfer studies (paper Figs. 4-6): image metrics and force metrics of one study in one
artifact, so its tables, heatmaps, radar plots and traces sit side by side in the report.

`transfer_study` (nodes `homo`, `material`, `hetero`) runs stages.m2m.study.image_study (FID/KID
before / m2m / flow_warp) and stages.force.study.force_study (source_only / genforce /
genforce_comp / genforce_plus / oracle, each trained from every seed of `force.seeds`) over the
study's (source, target) pairs, on the test indenters (`<study>/...`) and on the validation
indenters (`<study>_val/...`).  `groups` names subsets of pairs (the material study's
hard_to_soft and soft_to_hard, paper Fig. 5E-F) whose means are reported as
`<study>/<group>/<method>/<metric>`, beside the all-pairs `<study>/mean/...`; a force metric is
the mean over seeds, beside its standard deviation over seeds `<metric>_sd`.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np


def group_means(metrics: Mapping[str, float], study: str, groups: Mapping[str, list]) -> dict:
    """`<study>[_val]/<group>/<method>/<metric>`: the mean over a group's pairs of every
    `<study>[_val]/<source>_<target>/<method>/<metric>` in metrics."""
    out = {}
    for group, pairs in groups.items():
        labels = {f"{s}_{t}" for s, t in pairs}
        values: dict[str, list[float]] = {}
        for name, v in metrics.items():
            parts = name.split("/")
            if len(parts) == 4 and parts[0] in (study, f"{study}_val") and parts[1] in labels:
                values.setdefault(f"{parts[0]}/{group}/{parts[2]}/{parts[3]}", []).append(float(v))
        for key, vs in values.items():
            out[key] = float(np.mean(vs))
    return out


def transfer_study(*, study: str, groups: Mapping[str, list], features: Mapping, translated: Mapping,
                   warped: Mapping, own: Mapping, transfer: Mapping, markers: Mapping,
                   test_indenters: list, val_indenters: list, kid_subset: int, trace_frames: int,
                   members: list | None = None) -> dict:
    """One study over the pairs of all its groups (a pair in two groups is scored once);
    members: the study's sensors, whose artifacts the inputs hold."""
    from stages.force.study import force_study
    from stages.m2m.study import image_study
    pairs: list[list[str]] = []
    for group in groups.values():
        pairs += [[str(s), str(t)] for s, t in group if [str(s), str(t)] not in pairs]
    images = image_study(study=study, pairs=pairs, features=features, translated=translated,
                         warped=warped, kid_subset=kid_subset, markers=markers)
    force = force_study(study=study, pairs=pairs, own=own, transfer=transfer, markers=markers,
                        test_indenters=test_indenters, val_indenters=val_indenters,
                        trace_frames=trace_frames, groups=groups if len(groups) > 1 else None)
    metrics = images.pop("metrics")
    if len(groups) > 1:                  # the force metrics' group means come with their seed spread
        metrics.update(group_means(metrics, study, groups))
    metrics.update(force.pop("metrics"))
    figures = {**{f"images_{k}": v for k, v in images.pop("figures").items()},
               **{f"force_{k}": v for k, v in force.pop("figures").items()}}
    attrs = {"images": images.pop("attrs"), "force": force.pop("attrs"),
             "groups": {g: [f"{s}_{t}" for s, t in p] for g, p in groups.items()}}
    # the parts' timings go to the provenance with the node's, not into its content: a re-run
    # that scores the same at another speed must give the same artifact (early cutoff)
    timing = {part: t for part, t in (("images", images.pop("timing", None)),
                                      ("force", force.pop("timing", None))) if t}
    return {"images": images, "force": force, "figures": figures, "metrics": metrics, "attrs": attrs,
            "timing": timing}


def homo_study(**kw) -> dict:
    """Node `homo` (paper Fig. 4): the GelSight twins."""
    return transfer_study(study="homo", **kw)


def material_study(**kw) -> dict:
    """Node `material` (paper Fig. 5): elastomers of different hardness."""
    return transfer_study(study="material", **kw)


def hetero_study(**kw) -> dict:
    """Node `hetero` (paper Fig. 6): GelSight, TacTip and uSkin."""
    return transfer_study(study="hetero", **kw)


def sim_m2m_study(*, skins: list, **kw) -> dict:
    """Node `sim_m2m` (paper Fig. 3): image metrics of the simulation patterns' translations."""
    from stages.m2m.study import image_study
    return image_study(study="sim-m2m", **kw)
