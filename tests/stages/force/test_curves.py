"""The learning curve's arithmetic (stages.force.curves) on a stub study."""
import numpy as np
import pytest

from stages.common import InputError
from stages.force import curves


def _markers(n_contacts=4, length=6):
    rng = np.random.default_rng(0)
    n = n_contacts * length
    return {"images": np.zeros((n, 8, 8), np.uint8), "reference": np.zeros((8, 8), np.uint8),
            "force": rng.uniform(-3, 0, (n, 3)).astype(np.float32),
            "contact_id": np.repeat(np.arange(n_contacts), length),
            "indenter_id": np.repeat(np.arange(n_contacts) % 2, length).astype(np.int16),
            "indenters": np.array(["val_a", "val_b"])}


def test_curve_arithmetic_on_a_stub_study(monkeypatch):
    """Per method and length the mean over the study's pairs of the validation MAE; an oracle
    is its target's (one per target, scored once), genforce_comp the pair's; ratio = 1x / 4x."""
    from stages.force import model as force_model
    markers = {"B": _markers(), "C": _markers()}
    truth = markers["B"]["force"]
    offsets = {("oracle", "B"): {1: 0.6, 2: 0.3, 4: 0.3}, ("oracle", "C"): {1: 1.2, 2: 0.9, 4: 0.6},
               ("genforce_comp", "B", "C"): {1: 3.0, 2: 1.5, 4: 1.2},
               ("genforce_comp", "C", "B"): {1: 1.5, 2: 1.5, 4: 1.2}}
    calls = []

    def trained(method, s, t, k):
        calls.append((method, s, t, k))
        key = (method, t) if method == "oracle" else (method, s, t)
        return {"model": offsets[key][k]}, None

    def predict(offset, images, contact_id, reference):      # Fz off by the model's offset
        out = truth.copy()
        out[:, 2] += offset
        return out
    monkeypatch.setattr(force_model, "predict_contacts", predict)
    out = curves._curves("homo", [("B", "C"), ("C", "B")], trained, markers, ["val_a", "val_b"], 50, 3, [2, 4])
    m = out["metrics"]
    assert m["curve/homo/oracle/1x/mae_fz"] == pytest.approx((1.2 + 0.6) / 2)
    assert m["curve/homo/oracle/1x/mae_total"] == pytest.approx((1.2 + 0.6) / 6)
    assert m["curve/homo/oracle/4x/mae_fz"] == pytest.approx(0.45)
    assert m["curve/homo/oracle/ratio"] == pytest.approx(0.9 / 0.45)
    assert m["curve/homo/genforce_comp/2x/mae_fz"] == pytest.approx(1.5)
    assert m["curve/homo/genforce_comp/ratio"] == pytest.approx(2.25 / 1.2)
    assert len(calls) == 12 and len(set(calls)) == 12          # each model scored once
    assert out["attrs"]["steps"] == {1: 50, 2: 100, 4: 200} and out["attrs"]["seed"] == 3
    assert "| homo | oracle | 0.300 | 0.200 | 0.150 | 2.00 | no |" in out["attrs"]["markdown"]
    assert "| homo | genforce_comp | 0.750 | 0.500 | 0.400 | 1.87 | no |" in out["attrs"]["markdown"]
    assert out["figures"]["curves"][:8].tobytes() == b"\x89PNG\r\n\x1a\n"
    assert curves._curves("material", [], trained, markers, ["val_a"], 50, 3, [2])["metrics"] == {}


@pytest.fixture(scope="module")
def skins(blobs):
    from force_synthetic import contact_artifact
    images, forces = blobs(12, seed=3)
    return {"A": contact_artifact(images, forces, [("sphere", "prism", "cone", "torus")[k % 4] for k in range(12)])}


def test_the_curve_trains_as_own_and_transfer_do(skins, tiny_config):
    """At 1x, the curve's oracle is own's regressor and its genforce_comp transfer's, bit for bit:
    the longer ones differ only in their length."""
    from stages.force.fit import fit_own, fit_transfer
    from stages.force.model import load_model, to_arrays
    kw = dict(config={**tiny_config, "seq_len": 10}, batch_size=2, lr=0.05, seed=1)
    train = ["sphere", "prism"]
    own = fit_own(markers=skins["A"], skin="A", train_indenters=train, steps=3, **kw)
    from stages.force.fit import train_own
    mine, _ = train_own(skins["A"], steps=3, train_indenters=train, **kw)
    for k, v in to_arrays(load_model(own)).items():
        if k != "reference":
            np.testing.assert_array_equal(v, to_arrays(mine)[k], err_msg=k)
    d = np.r_[np.linspace(0, 1, 20), np.linspace(1, 0, 20)]
    loading = np.r_[np.ones(20, bool), np.zeros(20, bool)]
    cal = lambda scale: {"normalised_depth": d, "loading": loading,
                         "force": np.c_[np.zeros((40, 2)), -scale * (d * d + 2 * d) * np.where(loading, 1.0, 0.8)]}
    cal1, cal2 = cal(1.0), cal(2.0)
    tr = fit_transfer(translated=skins["A"], source_calibration=cal1, target_calibration=cal2, source="B",
                      target="A", finetune_steps=2, train_indenters=train, steps=3, **kw)
    comp = curves.train_comp(skins["A"], tr["attrs"]["curves"], steps=3, finetune_steps=2, train_indenters=train, **kw)
    for k, v in tr["genforce_comp"].items():
        if k != "reference":
            np.testing.assert_array_equal(v, to_arrays(comp)[k], err_msg=k)


def test_curve_metrics_need_every_factor():
    with pytest.raises(ValueError, match="pair counts"):
        curves.curve_metrics("homo", {"oracle": {1: [{"mae_total": 1.0, "mae_fz": 1.0}], 2: []}})
    with pytest.raises(ValueError, match="needs 1 and a longer"):
        curves.curve_metrics("homo", {"oracle": {2: [{"mae_total": 1.0, "mae_fz": 1.0}]}})


@pytest.mark.parametrize("bad", [[], [1], [2, 2], [2.5], "2", [True]])
def test_factors_are_integers_above_one(bad):
    with pytest.raises(InputError, match="curves.factors"):
        curves.check_factors(bad)
