"""scripts/elastomer_m2m.py: location pairing of skins' frames and the pixel count."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[3] / "scripts" / "elastomer_m2m.py"


@pytest.fixture(scope="module")
def script():
    spec = importlib.util.spec_from_file_location("elastomer_m2m", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_frames_are_paired_by_label_not_by_row(script):
    rng = np.random.default_rng(0)
    images = rng.integers(0, 2, (6, 4, 4)).astype(np.uint8) * 255
    order = np.array([3, 0, 5, 1, 4, 2])           # the second skin stores the frames shuffled
    markers = {"a": {"frame": np.arange(6), "images": images},
               "b": {"frame": order, "images": images[order]}}
    out = script.paired_frames(markers, np.array([1, 4]))
    assert np.array_equal(out["a"], images[[1, 4]]) and np.array_equal(out["b"], images[[1, 4]])
    assert script.differing(out["a"], images[[1, 1]]) == pytest.approx((images[4] != images[1]).sum() / 2)
    markers["b"] = {"frame": order[:-1], "images": images[order[:-1]]}      # frame 2 is missing
    with pytest.raises(SystemExit, match="b lacks 1 of a's test frames"):
        script.paired_frames(markers, np.array([2, 4]))
