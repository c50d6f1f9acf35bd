"""Node `summary`: the answer first, with the paper's figures beside ours.

One table per study, on the test split (the authors' unseen indenters), every method of
stages.force.study in a column, the paper's stated figure beside the row it speaks to; the
paper's targets checked pair by pair.  Force figures are means over the regressor seeds
(`force.seeds`) shown with their standard deviation, and a target counts as met, or a method as
better, only beyond that spread.  The tables go to the front of the report (attrs
report_tables, which pipeline.report renders first) and, as markdown, to docs/results.md
(`python scripts/results.py`), with the ablation's table (ablation_table, node `ablation`)
where it has run.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

METHODS = ("source_only", "genforce", "genforce_comp", "genforce_plus", "oracle")
R2_LINE = 0.8

# The paper's figures (Chen et al., GenForce; ../shared/FACTS.md), by study and row.
PAPER = {
    "sim-m2m": {"fid": "> 400 -> about 4", "kid": "> 0.75 -> about 0.01"},
    "homo": {"fid": "drop > 98%", "mae_fz": "GenForce < 1 N (min < 0.7 N); source-only max > 4.8 N",
             "mae_shear": "GenForce min < 0.06 N; source-only > 0.28 N", "r2": "GenForce mean > 0.8; source-only mostly < 0"},
    "material": {"mae_fz": "hard-to-soft 1.41 -> 0.99 N (-30%), soft-to-hard 1.03 -> 0.87 N (-16%)",
                 "mae_shear": "hard-to-soft 0.18 / 0.20 -> 0.10 / 0.14 N",
                 "r2": "r18 -> r6: 0.73 / 0.79 / 0.78 -> 0.87 / 0.86 / 0.84"},
    "hetero": {"mae_fz": "GenForce + comp. mean < 0.92 N; source-only max 7.76 N",
               "mae_shear": "GenForce + comp. Fx < 0.22 N, Fy < 0.3 N", "r2": "every R2 > 0 with compensation"},
}


def metrics_of(art) -> dict[str, float]:
    """A study artifact's metrics (a store artifact's, or a node output's "metrics")."""
    got = getattr(art, "metrics", None)
    if got is None and isinstance(art, Mapping):
        got = art.get("metrics", {})
    return dict(got or {})


def _fmt(v, digits=3) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "-"
    return f"{v:.{digits}g}" if abs(v) < 100 else f"{v:.0f}"


def _pairs(m: Mapping[str, float], study: str) -> list[str]:
    return sorted({k.split("/")[1] for k in m if k.startswith(f"{study}/") and k.count("/") == 3
                   and k.split("/")[1] not in ("mean", "hard_to_soft", "soft_to_hard", "pairs")
                   and k.endswith("/source_only/mae_total")})


def _get(m, study, row, method, metric):
    return m.get(f"{study}/{row}/{method}/{metric}")


def _sd(m, study, row, method, metric) -> float:
    """The metric's standard deviation over regressor seeds (0 where there is none)."""
    return float(m.get(f"{study}/{row}/{method}/{metric}_sd") or 0.0)


def _with_sd(m, study, row, method, metric) -> str:
    """'mean ± sd' over the regressor seeds, or the value alone where it has no spread."""
    v = _get(m, study, row, method, metric)
    sd = m.get(f"{study}/{row}/{method}/{metric}_sd")
    return _fmt(v) if sd is None or v is None else f"{_fmt(v)} ± {_fmt(sd, 2)}"


def above(m, study, row, method, metric, line) -> bool:
    """The metric is above `line` by more than its seed spread."""
    v = _get(m, study, row, method, metric)
    return v is not None and v - _sd(m, study, row, method, metric) > line


def lower(m, study, row, a, b, metric) -> bool:
    """Method a's metric is below method b's by more than the spread of their difference
    (the two seed spreads added in quadrature): a real improvement, not seed noise."""
    va, vb = _get(m, study, row, a, metric), _get(m, study, row, b, metric)
    if va is None or vb is None:
        return False
    return vb - va > float(np.hypot(_sd(m, study, row, a, metric), _sd(m, study, row, b, metric)))


def force_table(m: Mapping[str, float], study: str, title: str) -> dict:
    """Rows: mean MAE per axis, mean R2 per axis, and the pair counts of the paper's targets."""
    pairs = _pairs(m, study)
    paper = PAPER.get(study, {})
    rows = []
    for label, metric, key in (("MAE Fz (N)", "mae_fz", "mae_fz"), ("MAE Fx (N)", "mae_fx", "mae_shear"),
                               ("MAE Fy (N)", "mae_fy", None),
                               ("MAE Fz at light contact, 0.05-2 N (N)", "mae_fz_light", None),
                               ("R2 Fx", "r2_fx", "r2"), ("R2 Fy", "r2_fy", None),
                               ("R2 Fz", "r2_fz", None)):
        rows.append([f"{label}, mean of {len(pairs)} pairs", paper.get(key, "") if key else "",
                     *(_with_sd(m, study, "mean", meth, metric) for meth in METHODS)])

    def count(test) -> list[str]:
        return [f"{sum(bool(test(p, meth)) for p in pairs)}/{len(pairs)}" for meth in METHODS]
    r2 = lambda p, meth, line: all(above(m, study, p, meth, f"r2_{a}", line) for a in ("fx", "fy", "fz"))
    rows.append(["pairs with R2 >= 0.8 on every axis", "", *count(lambda p, meth: r2(p, meth, R2_LINE - 1e-12))])
    rows.append(["pairs with R2 > 0 on every axis", "", *count(lambda p, meth: r2(p, meth, 0.0))])
    beats = lambda p, meth: lower(m, study, p, meth, "source_only", "mae_total")
    rows.append(["pairs where the method beats source-only (MAE)", "", *count(beats)])
    rows[-1][2] = "-"
    return {"title": f"{title} (mean ± sd over the regressor seeds; a count is beyond the spread)",
            "header": ["test split", "paper", *METHODS], "rows": rows}


def image_row(m: Mapping[str, float], study: str) -> list:
    before, after = (_get(m, study, "mean", meth, "fid") for meth in ("before", "m2m"))
    kb, ka = (_get(m, study, "mean", meth, "kid") for meth in ("before", "m2m"))
    drop = (1 - after / before) * 100 if before and after is not None else None
    return [f"{study}: FID before -> m2m (drop)", PAPER.get(study, {}).get("fid", ""),
            f"{_fmt(before)} -> {_fmt(after)} ({_fmt(drop, 2)}%)", f"KID {_fmt(kb)} -> {_fmt(ka)}",
            f"flow-warp FID {_fmt(_get(m, study, 'mean', 'flow_warp', 'fid'))}"]


def targets(m: Mapping[str, float]) -> dict:
    """The paper's targets, each scored once, on test."""
    rows = []
    for study in ("homo", "material", "hetero"):
        pairs = _pairs(m, study)
        if not pairs:
            continue
        won = sum(lower(m, study, p, "genforce", "source_only", "mae_total") for p in pairs)
        rows.append([f"{study}: GenForce beats source-only on every pair", f"{won}/{len(pairs)}",
                     "yes" if won == len(pairs) else "no"])
    before, after = (m.get(f"material/hard_to_soft/{meth}/mae_fz") for meth in ("genforce", "genforce_comp"))
    if before and after is not None:
        cut = (1 - after / before) * 100
        real = lower(m, "material", "hard_to_soft", "genforce_comp", "genforce", "mae_fz")
        rows.append(["material: compensation cuts hard-to-soft normal MAE by >= 30%",
                     f"{_with_sd(m, 'material', 'hard_to_soft', 'genforce', 'mae_fz')} -> "
                     f"{_with_sd(m, 'material', 'hard_to_soft', 'genforce_comp', 'mae_fz')} N ({_fmt(cut, 2)}%)",
                     "yes" if cut >= 30 and real else "no"])
    pairs = _pairs(m, "hetero")
    if pairs:
        ok = sum(all(above(m, "hetero", p, "genforce_comp", f"r2_{a}", 0.0) for a in ("fx", "fy", "fz"))
                 for p in pairs)
        rows.append(["hetero: R2 > 0 on every axis with genforce_comp", f"{ok}/{len(pairs)}",
                     "yes" if ok == len(pairs) else "no"])
    return {"title": "The paper's targets (test split, scored once; met only beyond the seed spread)",
            "header": ["target", "measured", "met"],
            "rows": rows}


def ablation_table(m: Mapping[str, float]) -> dict | None:
    studies = sorted({k.split("/")[1] for k in m if k.startswith("ablation/")})
    if not studies:
        return None
    additions = sorted({k.split("/")[2] for k in m if k.startswith("ablation/") and k.endswith("/delta_mae_total")})
    rows = []
    for a in additions:
        rows.append([a, *(_fmt(m.get(f"ablation/{s}/{a}/delta_mae_total")) for s in studies)])
    rows.append(["seed spread (sd of genforce_plus's MAE)", *(_fmt(m.get(f"ablation/{s}/seed_spread/mae_total"))
                                                             for s in studies)])
    for meth in ("genforce_comp", "genforce_plus"):
        rows.append([f"{meth} MAE (mean over seeds)", *(_fmt(m.get(f"ablation/{s}/{meth}/mae_total")) for s in studies)])
    if any(k.endswith("/delta_mae_fz_light") for k in m if k.startswith("ablation/")):
        for a in additions:
            rows.append([f"{a}: light-contact Fz MAE (0.05-2 N)",
                         *(_fmt(m.get(f"ablation/{s}/{a}/delta_mae_fz_light")) for s in studies)])
        rows.append(["seed spread of the light-contact Fz MAE",
                     *(_fmt(m.get(f"ablation/{s}/seed_spread/mae_fz_light")) for s in studies)])
        for meth in ("genforce_comp", "genforce_plus"):
            rows.append([f"{meth} light-contact Fz MAE (mean over seeds)",
                         *(_fmt(m.get(f"ablation/{s}/{meth}/mae_fz_light")) for s in studies)])
    return {"title": "Ablation on the validation indenters: MAE without the addition minus with it (N)",
            "header": ["addition", *studies], "rows": rows}


def markdown(tables: list[dict]) -> str:
    out = []
    for t in tables:
        out += [f"### {t['title']}", "", "| " + " | ".join(t["header"]) + " |",
                "|" + "---|" * len(t["header"])]
        out += ["| " + " | ".join(str(c) for c in row) + " |" for row in t["rows"]]
        out.append("")
    return "\n".join(out)


def summary(*, homo=None, material=None, hetero=None, sim_m2m=None) -> dict:
    """Node `summary`: the tables above from the studies' metrics."""
    m: dict[str, float] = {}
    for art in (homo, material, hetero, sim_m2m):
        if art is not None:
            m.update(metrics_of(art))
    tables = []
    titles = {"homo": "homo (paper Fig. 4): the five GelSight twins",
              "material": "material (paper Fig. 5): elastomers of different hardness",
              "hetero": "hetero (paper Fig. 6): GelSight, TacTip, uSkin"}
    for study, title in titles.items():
        if _pairs(m, study):
            tables.append(force_table(m, study, title))
    images = [image_row(m, s) for s in ("sim-m2m", "homo", "material", "hetero") if _get(m, s, "mean", "before", "fid")]
    if images:
        tables.append({"title": "M2M image metrics (test split; clean-fid's clean protocol)",
                       "header": ["study", "paper", "FID", "KID", "baseline"], "rows": images})
    tables.append(targets(m))
    return {"attrs": {"report_tables": tables, "markdown": markdown(tables)}}
