"""scripts/results.py: the README's results block is replaced, never appended, and a README
without the markers is refused in one line; the control table counts the runs in the band."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))

import results  # noqa: E402


def test_the_results_block_is_replaced_between_its_markers():
    text = f"intro\n{results.BEGIN}\nold | table\n{results.END}\nafter\n"
    once = results.replace_block(text, "| a |")
    assert once == f"intro\n{results.BEGIN}\n| a |\n{results.END}\nafter\n"
    assert results.replace_block(once, "| b |").count("| ") == 1


def test_a_readme_without_the_markers_is_refused():
    with pytest.raises(SystemExit, match="no <!-- results"):
        results.replace_block("no markers here\n", "| a |")


def test_the_readme_holds_the_markers():
    text = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    assert text.index(results.BEGIN) < text.index(results.END)


def test_control_table_counts_the_runs_in_the_band(monkeypatch):
    """Each run's steady error and verdict for both drivers, and the count of successes."""
    import pipeline.artifact

    metrics = {"control/grasp/grape/force_error_N": 0.12, "control/grasp/grape/success": 1.0,
               "control/slip/plum/force_error_N": 0.5, "control/slip/plum/success": 0.0,
               "control/mean/grasp/success": 1.0,
               "control/supervised/grasp/grape/force_error_N": 0.31,
               "control/supervised/grasp/grape/success": 0.0,
               "control/supervised/slip/plum/force_error_N": 0.2,
               "control/supervised/slip/plum/success": 1.0}
    attrs = {"tolerance_N": 0.25, "targets_N": {"grape": 0.8, "plum": 1.2}, "supervised": True,
             "camera": {"skin": "gelsight-A-II"}}

    class Stub:
        def __init__(self, path):
            self.metrics, self.attrs = metrics, attrs

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

    monkeypatch.setattr(pipeline.artifact, "Artifact", Stub)
    table = results.control_table("x.h5")
    assert "| grasp grape | 0.8 | 0.12, yes | 0.31, no |" in table
    assert "| slip plum | 1.2 | 0.5, no | 0.2, yes |" in table
    assert "| runs in the band | | 1/2 | 1/2 |" in table
    assert "gelsight-A-II fingers" in table and "within 0.25 N" in table
