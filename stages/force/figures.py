"""The force studies' figures: radar plots of MAE, R2 histograms, force traces, error violins."""
from __future__ import annotations

from typing import Mapping

import numpy as np

METHODS = ("source_only", "genforce", "genforce_comp", "genforce_plus", "oracle")
COLOURS = {"source_only": "C3", "genforce": "C0", "genforce_comp": "C2", "genforce_plus": "C1",
           "oracle": "0.45"}


def _figure(**kw):
    from matplotlib.figure import Figure
    return Figure(**kw)


def _png(fig):
    from stages.figures import figure_png
    fig.tight_layout()
    return figure_png(fig)


def radar_png(mae: Mapping[str, np.ndarray], labels: list[str], study: str):
    """One panel per force component: a radar whose spokes are the pairs, one polygon per
    method (grouped bars instead when there are fewer than 3 pairs: a radar needs 3 spokes)."""
    fig = _figure(figsize=(11, 3.4))
    radar = len(labels) >= 3
    angles = np.linspace(0, 2 * np.pi, len(labels), endpoint=False)
    closed = np.r_[angles, angles[:1]]
    width = 0.8 / len(mae)
    for k, comp in enumerate(("Fx", "Fy", "Fz", "Ft (mean)")):
        ax = fig.add_subplot(1, 4, k + 1, projection="polar" if radar else None)
        for j, (m, values) in enumerate(mae.items()):
            v = values[:, k]
            if radar:
                ax.plot(closed, np.r_[v, v[:1]], color=COLOURS[m], lw=1.2, label=m)
                ax.fill(closed, np.r_[v, v[:1]], color=COLOURS[m], alpha=0.08)
            else:
                ax.bar(np.arange(len(labels)) + (j - (len(mae) - 1) / 2) * width, v, width,
                       color=COLOURS[m], label=m)
        ax.set_xticks(angles if radar else np.arange(len(labels)))
        ax.set_xticklabels(labels, fontsize=5 if radar else 7)
        ax.tick_params(axis="y", labelsize=6)
        if radar:            # a few radial labels: at an angle, more of them overprint each other
            from matplotlib.ticker import MaxNLocator
            ax.yaxis.set_major_locator(MaxNLocator(3))
        ax.set_title(f"MAE {comp} (N)", fontsize=9)
    fig.suptitle(study, fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    fig.legend(*fig.axes[0].get_legend_handles_labels(), loc="upper left", ncol=4, fontsize=7,
               frameon=False)
    from stages.figures import figure_png
    return figure_png(fig)


def r2_hist_png(r2: Mapping[str, np.ndarray], study: str):
    """R2 over pairs and axes: source-only, GenForce + compensation and genforce_plus (R2 < -1
    drawn at -1)."""
    fig = _figure(figsize=(4.5, 3.2))
    ax = fig.add_subplot()
    bins = np.linspace(-1.0, 1.0, 21)
    for m in ("source_only", "genforce_comp", "genforce_plus"):
        ax.hist(np.clip(r2[m].ravel(), -1.0, 1.0), bins=bins, color=COLOURS[m], alpha=0.55, label=m)
    ax.set(xlabel="R$^2$ (all pairs and axes; below -1 at -1)", ylabel="count", title=study)
    ax.legend(fontsize=8)
    return _png(fig)


def trace_png(trace: Mapping[str, np.ndarray], title: str):
    fig = _figure(figsize=(8, 5.5))
    for k, comp in enumerate(("Fx", "Fy", "Fz")):
        ax = fig.add_subplot(3, 1, k + 1)
        ax.plot(trace["true"][:, k], color="k", lw=1.2, label="true")
        for m in ("source_only", "genforce_comp", "genforce_plus"):
            ax.plot(trace[m][:, k], color=COLOURS[m], lw=0.9, label=m)
        ax.set_ylabel(f"{comp} (N)")
        if k == 0:
            ax.set_title(title, fontsize=9)
            ax.legend(fontsize=7, ncol=3)
    fig.axes[-1].set_xlabel("test frame")
    return _png(fig)


def violin_png(per_pair: list[dict], study: str):
    """Prediction error per method and axis, pooled over pairs."""
    fig = _figure(figsize=(9, 3.2))
    for k, comp in enumerate(("Fx", "Fy", "Fz")):
        ax = fig.add_subplot(1, 3, k + 1)
        data = [np.concatenate([p["errors"][m][:, k] for p in per_pair]) for m in METHODS]
        parts = ax.violinplot(data, showmedians=True, showextrema=False)
        for body, m in zip(parts["bodies"], METHODS):
            body.set_facecolor(COLOURS[m])
            body.set_alpha(0.6)
        parts["cmedians"].set_color("k")
        ax.axhline(0.0, color="0.5", lw=0.6)
        ax.set_xticks(np.arange(1, len(METHODS) + 1))
        ax.set_xticklabels(METHODS, rotation=30, fontsize=7)
        ax.set_ylabel(f"{comp} error (N)")
    fig.suptitle(f"{study}: prediction error", fontsize=9)
    return _png(fig)


def ablation_png(metrics: Mapping[str, float], studies: list[str], additions: list[str]):
    """Per study: each addition's validation gain (MAE without it minus with it, N) as bars, the
    seed spread as a grey band: a bar inside the band has not earned its place."""
    fig = _figure(figsize=(3.2 * max(1, len(studies)), 3.2))
    for k, study in enumerate(studies):
        ax = fig.add_subplot(1, len(studies), k + 1)
        spread = metrics[f"ablation/{study}/seed_spread/mae_total"]
        ax.axhspan(-spread, spread, color="0.85", label="seed spread")
        gains = [metrics[f"ablation/{study}/{a}/delta_mae_total"] for a in additions]
        ax.bar(np.arange(len(additions)), gains, color=["C2" if g > spread else "C3" for g in gains])
        ax.axhline(0.0, color="0.4", lw=0.6)
        ax.set_xticks(np.arange(len(additions)))
        ax.set_xticklabels(additions, rotation=35, fontsize=7, ha="right")
        ax.set_ylabel("validation MAE gain (N)", fontsize=8)
        ax.set_title(study, fontsize=9)
        if k == 0:
            ax.legend(fontsize=7)
    return _png(fig)


def curves_png(metrics: Mapping[str, float], studies: list[str], lengths: Mapping[int, int],
               methods):
    """Per study: validation MAE (total, N) against training length (steps, log scale) for each
    method, the profile's length (1x) ringed: where the profile sits on its learning curve."""
    fig = _figure(figsize=(3.2 * max(1, len(studies)), 3.2))
    factors = sorted(lengths)
    for k, study in enumerate(studies):
        ax = fig.add_subplot(1, len(studies), k + 1)
        x = [lengths[f] for f in factors]
        for m in methods:
            y = [metrics[f"curve/{study}/{m}/{f}x/mae_total"] for f in factors]
            ax.plot(x, y, "o-", color=COLOURS[m], label=m, ms=4)
            ax.plot(x[:1], y[:1], "o", ms=11, mfc="none", mec=COLOURS[m])
        ax.set_xscale("log", base=2)
        ax.set_xticks(x)
        ax.set_xticklabels([f"{v}\n({f}x)" for v, f in zip(x, factors)], fontsize=7)
        ax.set_xlabel("training steps", fontsize=8)
        ax.set_ylabel("validation MAE total (N)", fontsize=8)
        ax.set_title(study, fontsize=9)
        if k == 0:
            ax.legend(fontsize=7)
    return _png(fig)
