"""scripts/m2m_scale.py: a saved model scores as the trained one, and bad arguments are one line."""
import sys

import numpy as np
import pytest

from stages.m2m.model import build, default_config, load_translator, state_arrays
from tests.helpers import load_script


@pytest.fixture(scope="module")
def script():
    return load_script("m2m_scale")


def test_a_saved_model_loads_back_to_the_same_translations(script, tmp_path):
    cfg = default_config(size=(32, 32), width=8, timesteps=1000)
    model = {"weights": state_arrays(build(cfg)), "loss": np.linspace(1.0, 0.1, 5, dtype=np.float32),
             "attrs": {"config": cfg, "steps": 5, "final_loss": 0.1}}
    script.save_model(model, tmp_path / "m")
    back = script.load_model(tmp_path / "m")
    assert back["attrs"] == model["attrs"] and set(back["weights"]) == set(model["weights"])
    rng = np.random.default_rng(0)
    images = (rng.random((3, 32, 32)) < 0.3).astype(np.uint8) * 255
    ref_a, ref_b = images[0], images[1]
    assert np.array_equal(load_translator(back).translate(images, ref_a, ref_b),
                          load_translator(model).translate(images, ref_a, ref_b))
    with pytest.raises(SystemExit, match="no weights.npz"):
        script.load_model(tmp_path / "nothing")


@pytest.mark.parametrize("argv, message", [
    (["--kid-subset", "60", "--n-eval", "50"], "--kid-subset 60 is larger than --n-eval 50"),
    (["--steps", "0"], "--steps, --width and --batch-size must be at least 1"),
    (["--markers-dir", "/nonexistent", "--baseline", "x.h5"], "needs <skin>.h5 for every pattern"),
])
def test_bad_arguments_are_one_line_errors(script, monkeypatch, argv, message):
    monkeypatch.setattr(sys, "argv", ["m2m_scale.py", *argv])
    with pytest.raises(SystemExit, match=message):
        script.main()


def test_report_prints_each_pair_the_mean_and_the_drops(script, capsys):
    pairs = [("A", "B"), ("B", "A")]
    stored, new = {}, {}
    for (s, t), before, old, now in ((("A", "B"), 100.0, 5.0, 2.0), (("B", "A"), 300.0, 15.0, 1.0)):
        stored[f"sim-m2m/{s}_{t}/before/fid"], stored[f"sim-m2m/{s}_{t}/m2m/fid"] = before, old
        new[f"sim-m2m/{s}_{t}/m2m/fid"] = now
    stored.update({"sim-m2m/mean/before/fid": 200.0, "sim-m2m/mean/m2m/fid": 10.0,
                   "sim-m2m/mean/before/kid": 0.4, "sim-m2m/mean/m2m/kid": 0.01})
    new.update({"sim-m2m/mean/m2m/fid": 1.5, "sim-m2m/mean/m2m/kid": -0.0002})
    cfg = {"config": {"width": 12}, "steps": 800, "batch_size": 16}
    script.report(stored, new, cfg, {"config": {"width": 32}, "steps": 12800, "batch_size": 32}, pairs)
    out = capsys.readouterr().out
    assert "stored: width 12, 800 steps of 16; new: width 32, 12800 steps of 32" in out
    assert "B->A                      300.00     15.00      1.00" in out
    assert "mean FID: before 200, stored 10 (20.0x), new 1.5 (133.3x)" in out
    assert "mean KID: before 0.4, stored 0.01 (40.0x), new -0.0002 (at the noise floor)" in out
