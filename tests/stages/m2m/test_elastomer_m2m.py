"""scripts/elastomer_m2m.py: location pairing of skins' frames and the pixel count."""
import numpy as np
import pytest

from tests.helpers import load_script


@pytest.fixture(scope="module")
def script():
    return load_script("elastomer_m2m")


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
