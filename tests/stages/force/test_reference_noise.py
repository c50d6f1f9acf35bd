"""scripts/reference_noise.py: fresh noise realisations of a skin's reference, and how a model
reads its frames against each."""
import numpy as np
import pytest

from stages.markers.patterns import gelsight_pattern
from stages.markers.render import Renderer
from stages.markers.segment import segment
from stages.markers.unify import segmentation_params
from tests.helpers import load_script


@pytest.fixture(scope="module")
def script():
    return load_script("reference_noise")


def pad(n=17, size=20.0):
    g = (np.arange(n) - (n - 1) / 2) * size / (n - 1)
    return {"grid_x": g, "grid_y": g, "surface_z": np.zeros((n, n)), "on_pad": np.ones((n, n), bool)}


def patterns(name="gelsight-A-II"):
    m = gelsight_pattern("A-II")
    return {f"markers/{name}/centers": m.centers, f"markers/{name}/axes": m.axes,
            f"markers/{name}/angles": m.angles, f"markers/{name}/pad_size_mm": np.array(m.pad_size_mm)}


SPEC = {"pattern": "gelsight-A-II", "look": "gelsight", "noise": 3.0}


def test_fresh_references_are_the_markers_nodes_reference_under_other_seeds(script):
    deform = pad()
    refs = script.fresh_references(deform, patterns(), SPEC, {}, [5, 5, 6])
    r = Renderer(deform["grid_x"], deform["grid_y"], deform["surface_z"], deform["on_pad"],
                 gelsight_pattern("A-II"), look="gelsight", size=(128, 128), noise=3.0, seed=5)
    expect = segment(r.render(np.zeros((17, 17, 3), np.float32), -1)["raw"],
                     **segmentation_params({}, "gelsight"))
    assert np.array_equal(refs[0], expect) and np.array_equal(refs[1], expect)
    diff = int((refs[2] != refs[0]).sum())
    assert 0 < diff < 200                  # another seed flips a few marker-edge pixels
    assert 0.02 < (refs[0] > 0).mean() < 0.5
    with pytest.raises(ValueError, match="look 'taxel' has no camera noise"):
        script.fresh_references(deform, patterns(), {**SPEC, "look": "taxel"}, {}, [1])


def test_readings_give_the_gain_r2_and_pixels_of_each_reference(script):
    n = 40
    force = np.zeros((n, 3))
    force[:, 2] = -np.linspace(0.1, 3.0, n)
    base = np.zeros((8, 8), np.uint8)
    moved = base.copy()
    moved[0, :3] = 255

    def predict(images, contact_id, reference):
        # reads 10% high for each pixel the reference differs from `base` by
        return force * (1 + 0.1 * int((reference != base).sum()))

    rows = script.readings(predict, np.zeros((n, 8, 8), np.uint8), np.zeros(n, int), force,
                           [base, moved], band=(0.5, 2.0))
    assert rows[0] == {"gain": pytest.approx(1.0), "r2_fz": pytest.approx(1.0), "pixels": 0}
    assert rows[1]["gain"] == pytest.approx(1.3) and rows[1]["pixels"] == 3
    true = force[:, 2]
    assert rows[1]["r2_fz"] == pytest.approx(1 - np.sum((0.3 * true) ** 2) / np.sum((true - true.mean()) ** 2))
    with pytest.raises(ValueError, match=r"no frame has a normal force in \(5.0, 9.0\) N"):
        script.readings(predict, np.zeros((n, 8, 8), np.uint8), np.zeros(n, int), force, [base],
                        band=(5.0, 9.0))
