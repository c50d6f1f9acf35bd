"""transfer between sensors without material calibrations (the authors' homo set: one gel, no
depth): nothing to compensate, and genforce_comp is genforce."""
import numpy as np
import pytest

from stages.common import InputError
from stages.force import plus
from stages.force.fit import compensated_labels, fit_transfer
from force_synthetic import contact_artifact

NAMES = ["sphere", "prism", "cone", "torus"]
TRAIN = ["sphere", "prism"]


@pytest.fixture(scope="module")
def no_depth(blobs):
    """Two skins of one synthetic physics, without normalised_depth (the homo set has none)."""
    images, forces = blobs(8, seed=5)
    a = contact_artifact(images, forces, [NAMES[k % 4] for k in range(8)])
    del a["normalised_depth"]
    return {"A": a, "B": dict(a, images=255 - a["images"], reference=np.full((32, 32), 255, np.uint8))}


@pytest.fixture(scope="module")
def kw(tiny_config):
    return dict(config={**tiny_config, "seq_len": 10}, steps=4, batch_size=2, lr=0.05, seed=0, finetune_steps=0,
                train_indenters=TRAIN)


def test_no_calibration_is_the_identity_and_reads_no_depth(no_depth, kw):
    out = fit_transfer(translated=no_depth["A"], source="A", target="B", target_markers=no_depth["B"],
                       additions=list(plus.ADDITIONS), **kw)
    assert out["attrs"]["compensation_identity"] is True and out["attrs"]["curves"] is None
    assert out["attrs"]["label_scale"] == {"mean": 1.0, "min": 1.0, "max": 1.0}
    for k, v in out["genforce"].items():                       # genforce_comp is genforce, not retrained
        np.testing.assert_array_equal(v, out["genforce_comp"][k], err_msg=k)
    assert "genforce_comp" not in out["attrs"]["history"] and set(out["figures"]) == {"loss"}
    assert out["attrs"]["plus"]["shear_calibration"] == {"scale": 1.0, "calibrated": False}   # no shear legs
    assert out["attrs"]["punch_scale"] is None                                           # no punch calibrations
    assert out["attrs"]["plus"]["punch_calibration"] == {"scale": 1.0, "calibrated": False}
    np.testing.assert_array_equal(compensated_labels(no_depth["A"], None), no_depth["A"]["force"])


def test_one_calibrated_sensor_cannot_be_compensated(no_depth, kw):
    curves = {"loading_coefficients": np.array([1.0, 0.0]), "unloading_coefficients": np.array([1.0, 0.0])}
    with pytest.raises(InputError, match=r"^transfer\[A->B\]: B has no material calibration but the other sensor "
                                         r"has: compensation needs both \(or neither\)$"):
        fit_transfer(translated=no_depth["A"], source="A", target="B", source_calibration=curves, **kw)
