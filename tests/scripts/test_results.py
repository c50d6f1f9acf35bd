"""scripts/results.py: the README's results block is replaced, never appended, and a README
without the markers is refused in one line."""
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
