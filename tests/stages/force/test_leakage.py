"""No method but the oracle reads the target's force labels.

The whole chain a transfer runs (M2M pretrained and fine-tuned on location-paired frames of the
source and the target, the source translated, genforce / genforce_comp / genforce_plus trained
and built on it, and the source-only model) is run three times: with the target's labels, with
them replaced by NaN, and with them permuted.  Every weight and every prediction of the
non-oracle methods must be bit-identical across the three; the oracle, trained on the target's
labels, must change.
"""
import numpy as np
import pytest
from force_synthetic import contact_artifact

from stages.force import plus
from stages.force.fit import fit_own, fit_transfer
from stages.force.model import load_model, predict_contacts
from stages.m2m import fit as m2m_fit
from stages.m2m import translate as m2m_translate
from tests.helpers import drain

NAMES = ["sphere", "prism", "cone", "torus"]        # two training indenters, validation, test
TRAIN = ["sphere", "prism"]
FIT = dict(steps=6, batch_size=2, lr=0.05, seed=0)


def _calibration(scale, shear):
    """Press, a shear leg at the peak (out 1 mm, back: `shear` of the normal force), release."""
    d = np.r_[np.linspace(0, 1, 12), 1.0, 1.0, np.linspace(1, 0, 12)]
    phase = np.r_[np.zeros(12), 1, 2, np.full(12, 3)].astype(np.int8)
    fz = -scale * (d * d + 2 * d) * np.where(phase == 3, 0.8, 1.0)
    fx, fy = np.where(phase == 1, -shear * fz, 0.1 * fz), np.where(phase == 1, 0.0, -0.05 * fz)
    shift = np.zeros((d.size, 2))
    shift[12, 0] = 1.0
    return {"normalised_depth": d, "force": np.c_[fx, fy, fz], "phase": phase, "shift": shift}


def _poisoned(target, how):
    out = dict(target)
    force = np.asarray(target["force"], np.float32)
    if how == "nan":
        out["force"] = np.full_like(force, np.nan)
    elif how == "permuted":
        out["force"] = force[np.random.default_rng(7).permutation(len(force))]
    return out


def _chain(source, target, tiny_config):
    """Every node of one transfer, on these source and target marker artifacts."""
    markers = {"S": source, "T": target}
    base = m2m_fit.pretrain(markers=markers, skins=["S", "T"], train_indenters=TRAIN, size=(32, 32), steps=3,
                        batch_size=4, lr=1e-3, seed=0, width=4, timesteps=10)
    tuned = m2m_fit.finetune(base=base, markers=markers, skins=["S", "T"], train_indenters=TRAIN,
                         pairs_per_skin=6, steps=3, batch_size=4, lr=1e-3, seed=0)
    chunks, out = drain(m2m_translate.translate_sequence(model=tuned, source_markers=source, target_markers=target,
                                               eval_indenters=["torus"], val_indenters=["cone"], n_eval=4,
                                               train_indenters=TRAIN))
    translated = {**out, **{k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]},
                  "indenters": source["indenters"]}
    config = {**tiny_config, "seq_len": 10}
    transfer = fit_transfer(translated=translated, source_calibration=_calibration(1.0, 0.5),
                            target_calibration=_calibration(1.6, 0.2), source="S", target="T", config=config,
                            finetune_steps=2, train_indenters=TRAIN, target_markers=target,
                            additions=list(plus.ADDITIONS), source_punch=_calibration(1.2, 0.5),
                            target_punch=_calibration(2.4, 0.2), **FIT)
    own = {s: fit_own(markers=markers[s], skin=s, train_indenters=TRAIN, config=config, **FIT)
           for s in ("S", "T")}
    test = {k: np.asarray(target[k]) for k in ("images", "contact_id", "reference")}
    preds = {m: predict_contacts(load_model(transfer, m), test["images"], test["contact_id"], test["reference"])
             for m in ("genforce", "genforce_comp", "genforce_plus")}
    preds["source_only"] = predict_contacts(load_model(own["S"]), test["images"], test["contact_id"],
                                            test["reference"])
    arrays = {"m2m": tuned["weights"], "translated": {"images": translated["images"]},
              **{m: transfer[m] for m in ("genforce", "genforce_comp", "genforce_plus")},
              "source_only": own["S"]["weights"]}
    return arrays, preds, own["T"]["weights"], transfer["attrs"]


@pytest.fixture(scope="module")
def worlds(blobs, tiny_config):
    import pytest as _pytest
    monkey = _pytest.MonkeyPatch()                 # the features are not this test's: a cheap stand-in
    monkey.setattr("stages.imagemetrics.inception_features", lambda images, **kw: np.mean(images, axis=2) / 255.0)
    try:
        images, forces = blobs(12, seed=5)
        names = [NAMES[k % 4] for k in range(12)]
        source = contact_artifact(images, forces, names)
        # the target: another look (inverted markers) and a stiffer skin (its own labels 1.6x)
        target = contact_artifact([255 - im for im in images], [1.6 * f for f in forces], names)
        target["reference"] = np.full((32, 32), 255, np.uint8)
        return {how: _chain(source, _poisoned(target, how), tiny_config) for how in ("clean", "nan", "permuted")}
    finally:
        monkey.undo()


@pytest.mark.parametrize("how", ["nan", "permuted"])
def test_no_method_but_the_oracle_reads_the_targets_labels(worlds, how):
    clean, poisoned = worlds["clean"], worlds[how]
    for name, arrays in clean[0].items():
        assert set(arrays) == set(poisoned[0][name]), name
        for k, v in arrays.items():
            np.testing.assert_array_equal(v, poisoned[0][name][k], err_msg=f"{how}: {name} {k}")
    for m, pred in clean[1].items():
        np.testing.assert_array_equal(pred, poisoned[1][m], err_msg=f"{how}: predictions of {m}")
    assert clean[3] == poisoned[3]                  # the transfer's attrs: histories, gains, curves
    assert clean[3]["plus"]["additions"] == list(plus.ADDITIONS)
    assert clean[3]["plus"]["shear_calibration"]["scale"] == pytest.approx(0.4)     # 0.2 / 0.5
    assert clean[3]["plus"]["punch_calibration"]["scale"] == pytest.approx(1.25)    # 2.4 / 1.2 over 1.6
    # the oracle trains on the target's labels: the same change alters it
    oracle, changed = clean[2], poisoned[2]
    assert any(not np.array_equal(v, changed[k], equal_nan=False) for k, v in oracle.items()), how
