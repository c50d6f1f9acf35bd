"""scripts/ci_baseline.py: the baseline is the first run's values, the spread their sample sd,
and `pipeline metrics --baseline` allows k of those spreads."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))

import ci_baseline  # noqa: E402
from pipeline import metrics as M  # noqa: E402
from pipeline.errors import PipelineError  # noqa: E402


def test_the_baseline_is_the_first_runs_value_and_the_spread_the_sample_sd():
    runs = [{"a/mae_fz": 1.0, "a/r2_fz": 0.5, "segment/x/iou": 0.9, "gone": 1.0},
            {"a/mae_fz": 2.0, "a/r2_fz": 0.7, "segment/x/iou": 0.9},
            {"a/mae_fz": 4.0, "a/r2_fz": 0.6, "segment/x/iou": 0.9}]
    base, spread = ci_baseline.summarise(runs)
    assert base == {"a/mae_fz": 1.0, "a/r2_fz": 0.5, "segment/x/iou": 0.9}     # "gone": not in every run
    assert spread["a/mae_fz"] == pytest.approx(1.5275252316519468)              # sd of 1, 2, 4 (ddof 1)
    assert spread["a/r2_fz"] == pytest.approx(0.1)
    assert spread["segment/x/iou"] == 0.0                                       # every run agreed


def test_the_gate_allows_k_spreads_in_the_metrics_direction(tmp_path):
    path = tmp_path / "b.yaml"
    path.write_text("k: 4\nmetrics: {a/mae_fz: 1.0, a/r2_fz: 0.5, segment/x/iou: 0.9}\n"
                    "spread: {a/mae_fz: 0.1, a/r2_fz: 0.05, segment/x/iou: 0.0}\n")
    b = M.load_baseline(path)
    rows = {r["metric"]: r for r in M.compare({"a/mae_fz": 1.39, "a/r2_fz": 0.29, "segment/x/iou": 0.9}, b)}
    assert rows["a/mae_fz"]["allowed"] == pytest.approx(0.4) and not rows["a/mae_fz"]["regression"]
    assert rows["a/r2_fz"]["regression"]                      # 0.21 lower, 0.2 allowed
    assert not rows["segment/x/iou"]["regression"]
    rows = {r["metric"]: r for r in M.compare({"a/mae_fz": 1.41, "a/r2_fz": 0.9, "segment/x/iou": 0.8999}, b)}
    assert rows["a/mae_fz"]["regression"] and not rows["a/r2_fz"]["regression"]   # better is never a regression
    assert rows["segment/x/iou"]["regression"]                # no spread: no change allowed
    path.write_text("k: -1\nmetrics: {a: 1.0}\n")
    with pytest.raises(PipelineError, match="'k' must be a number >= 0, got -1"):
        M.load_baseline(path)


def test_a_spread_is_better_lower_whatever_its_metric():
    assert M.higher_is_better("h/mean/oracle/r2_fz") and not M.higher_is_better("h/mean/oracle/r2_fz_sd")
    assert not M.higher_is_better("h/mean/oracle/mae_fz_sd") and M.higher_is_better("segment/x/iou")
