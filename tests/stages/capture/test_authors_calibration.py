"""Node `authors_calibration[sensor]`: the authors' released material-compensation curves as
stages.force.compensation Curves, evaluated exactly as their loaders evaluate them."""
import numpy as np
import pytest

from stages.capture.authors_calibration import authors_calibration
from stages.common import InputError
from stages.force.compensation import compensate, curves_from_calibration, label_scale
from tests.stages.capture import authors_fixture as fx

SETS = {"modulus": {"ratio_6": {}, "ratio_8": {}}, "hetero": {"gelsight": {}, "tactip": {}}}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("curves")
    training = root / "training"
    files = {}
    for set_name, sensors in SETS.items():
        for s in sensors:
            fx.write_coefficients(training, set_name, s)
            folder = training / fx.COEFF[set_name]
            files[s] = (folder / f"{s}_down.csv", folder / f"{s}_up.csv")
    return root, files


def _authors_poly(path):
    """What com_hetero/data_loader.py and com_modulus/data_loader.py build from a file."""
    return np.poly1d(np.loadtxt(path, delimiter=","))


@pytest.mark.parametrize("sensor", ["ratio_6", "ratio_8", "gelsight", "tactip"])
def test_curves_are_the_files_polynomials_exactly(dataset, sensor):
    root, files = dataset
    art = authors_calibration(root=str(root), sensor=sensor)
    curves = curves_from_calibration(art)
    d = np.linspace(-0.2, 1.5, 341)
    np.testing.assert_array_equal(np.polyval(curves.loading, d), _authors_poly(files[sensor][0])(d))
    np.testing.assert_array_equal(np.polyval(curves.unloading, d), _authors_poly(files[sensor][1])(d))
    assert art["attrs"]["loading_file"] == str(files[sensor][0])
    assert art["attrs"]["set"] == ("modulus" if sensor.startswith("ratio") else "hetero")


def test_labels_scale_as_the_authors_ratio(dataset):
    """target(depth) / source(depth): `_down` on loading (inc_z) frames, `_up` on unloading."""
    root, files = dataset
    src = curves_from_calibration(authors_calibration(root=str(root), sensor="tactip"))
    tgt = curves_from_calibration(authors_calibration(root=str(root), sensor="gelsight"))
    d = np.linspace(0.05, 1.0, 40)
    loading = np.arange(40) < 25
    down = _authors_poly(files["gelsight"][0])(d) / _authors_poly(files["tactip"][0])(d)
    up = _authors_poly(files["gelsight"][1])(d) / _authors_poly(files["tactip"][1])(d)
    assert (np.r_[_authors_poly(files["tactip"][0])(d), _authors_poly(files["gelsight"][1])(d)] > 0).all()
    np.testing.assert_array_equal(label_scale(d, loading, src, tgt), np.where(loading, down, up))
    force = np.tile([0.2, -0.1, -1.5], (40, 1))
    np.testing.assert_allclose(compensate(force, d, loading, src, tgt), force * np.where(loading, down, up)[:, None])


def test_where_a_curve_reads_no_force_the_labels_stay(dataset):
    root, _ = dataset
    src = curves_from_calibration({"loading_coefficients": [1.0, -0.1], "unloading_coefficients": [1.0, -0.1]})
    tgt = curves_from_calibration({"loading_coefficients": [2.0, 0.0], "unloading_coefficients": [2.0, 0.0]})
    d = np.array([0.0, 0.05, 0.5])
    np.testing.assert_allclose(label_scale(d, np.ones(3, bool), src, tgt), [1.0, 1.0, 1.0 / 0.4])


def test_missing_partner_and_other_spellings(tmp_path):
    folder = tmp_path / "training/material_compensation/modulus/cofficients"       # no `modulus` level
    folder.mkdir(parents=True)
    (folder / "ratio_10_down.csv").write_text("1.5\r\n2.0\r\n0.0\r\n")                # one value a line, CRLF
    (folder / "ratio_10_up.csv").write_text("1.0,1.0,0.0\n")
    art = authors_calibration(root=str(tmp_path), sensor="ratio_10")
    assert art["loading_coefficients"].tolist() == [1.5, 2.0, 0.0]
    assert art["unloading_coefficients"].tolist() == np.loadtxt(folder / "ratio_10_up.csv", delimiter=",").tolist()
    (folder / "ratio_10_up.csv").unlink()
    with pytest.raises(InputError, match=rf"^data.root: {folder}/ratio_10_down.csv has no unloading partner "
                                         rf"{folder}/ratio_10_up.csv$"):
        authors_calibration(root=str(tmp_path), sensor="ratio_10")
    (folder / "ratio_10_up.csv").write_text("1.0,x,0.0\n")
    with pytest.raises(InputError, match=rf"^{folder}/ratio_10_up.csv line 1: 'x' is not a number$"):
        authors_calibration(root=str(tmp_path), sensor="ratio_10")
