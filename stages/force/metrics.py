"""Force metrics: per-axis MAE and R2 (scikit-learn), and their overall MAE.

``mae_total`` is the mean of the three axes' MAE (scikit-learn's uniform average), in N.
R2 follows scikit-learn: on an axis whose true force is constant it is 1.0 for a perfect
prediction and 0.0 otherwise.  ``mae_fz_light`` is the normal-force MAE over the frames in
light contact (true normal force in (LIGHT_N[0], LIGHT_N[1]] N: the 0.6-1.2 N a fragile grasp
holds lies there), present where a set has at least two of them.
"""
from __future__ import annotations

import numpy as np

AXES = ("fx", "fy", "fz")
METRICS = ("mae_fx", "mae_fy", "mae_fz", "mae_total", "r2_fx", "r2_fy", "r2_fz")
LIGHT_N = (0.05, 2.0)   # N: the light-contact band of mae_fz_light


def force_metrics(pred, true) -> dict[str, float]:
    """MAE and R2 per axis of predicted vs true forces (N,3) N, plus mae_total (and
    mae_fz_light where the set has light contacts)."""
    from sklearn.metrics import mean_absolute_error, r2_score
    pred, true = np.asarray(pred, float), np.asarray(true, float)
    if pred.shape != true.shape or pred.ndim != 2 or pred.shape[1] != 3:
        raise ValueError(f"force_metrics: pred {pred.shape} and true {true.shape} must both be (N,3)")
    if len(pred) < 2:
        raise ValueError(f"force_metrics: need at least 2 frames, got {len(pred)}")
    out = {f"mae_{a}": float(mean_absolute_error(true[:, k], pred[:, k])) for k, a in enumerate(AXES)}
    out["mae_total"] = float(mean_absolute_error(true, pred))
    out.update({f"r2_{a}": float(r2_score(true[:, k], pred[:, k])) for k, a in enumerate(AXES)})
    out = {k: out[k] for k in METRICS}
    light = (-true[:, 2] > LIGHT_N[0]) & (-true[:, 2] <= LIGHT_N[1])
    if light.sum() >= 2:
        out["mae_fz_light"] = float(np.abs(pred[light, 2] - true[light, 2]).mean())
    return out
