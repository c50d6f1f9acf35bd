"""Node functions: training, translation streams, features and the image study."""
import numpy as np
import pytest
from m2m_synthetic import SKINS

from stages.imagemetrics import fid, kid
from stages.m2m import fit, study, translate
from stages.m2m.data import eval_frame_indices
from tests.helpers import drain as run_node

N_EVAL = 6
PNG = bytes([0x89, 0x50, 0x4E, 0x47])


@pytest.fixture(scope="module")
def trained(skins):
    """A width-8 generator trained from scratch for 1200 steps on the 3 tiny skins (~40 s; at
    400 steps it drew the target's markers but kept little of their motion)."""
    return fit.pretrain(markers=skins, skins=list(SKINS), train_indenters=["sphere"], size=(64, 64),
                          steps=1200, batch_size=16, lr=3e-3, seed=0, width=8, timesteps=100)


def _iou(a, b):
    return ((a > 0) & (b > 0)).sum() / ((a > 0) | (b > 0)).sum()


def test_pretrain_outputs(trained):
    attrs = trained["attrs"]
    assert attrs["config"]["size"] == [64, 64] and attrs["config"]["width"] == 8
    assert attrs["pairs"] == 24 and attrs["steps"] == 1200 and attrs["skins"] == list(SKINS)
    loss = trained["loss"]
    assert loss.shape == (1200,) and attrs["final_loss"] < 0.5 * loss[:20].mean()
    assert attrs["parameters"] == sum(v.size for v in trained["weights"].values())
    for png in trained["figures"].values():
        assert bytes(png[:4]) == PNG


def test_trained_model_beats_before_on_held_out_frames(skins, trained):
    """Held-out indenter, Array3 -> Diamond3: the translations score better FID and KID
    against Diamond3's own images than Array3's images do, and they overlap the true
    deformed Diamond3 images better than its undeformed reference does."""
    src, tgt = skins["Array3"], skins["Diamond3"]
    real = translate.image_features(markers=tgt, eval_indenters=["wave"], n_eval=N_EVAL)
    before = translate.image_features(markers=src, eval_indenters=["wave"], n_eval=N_EVAL)
    chunks, out = run_node(translate.translate_sequence(model=trained, source_markers=src, target_markers=tgt,
                                                    eval_indenters=["wave"], n_eval=N_EVAL))
    np.testing.assert_array_equal(out["eval_frames"], real["eval_frames"])
    fid_before, fid_m2m = fid(before["features"], real["features"]), fid(out["features"], real["features"])
    kid_before, kid_m2m = kid(before["features"], real["features"]), kid(out["features"], real["features"])
    assert fid_before > 100 and fid_m2m < 0.5 * fid_before
    assert kid_m2m < 0.5 * kid_before
    rows = eval_frame_indices(src, ["wave"], N_EVAL)
    images = np.concatenate([c["images"] for c in chunks])         # no training indenters: the scored frames
    assert len(images) == len(rows)
    assert _iou(images, tgt["images"][rows]) > _iou(tgt["reference"][None], tgt["images"][rows]) + 0.02


def test_trained_model_keeps_the_deformation(skins, trained, monkeypatch):
    """On the held-out indenter's frames the translations' markers move as the target's own
    do: image_study's motion_err_px (the mean |measured - true| displacement of the markers
    that move > 1 px) is well below the undeformed reference's, which keeps none of it and
    so scores their mean motion (1.5-1.7 px here)."""
    monkeypatch.setattr("stages.imagemetrics.inception_features",   # FID is not this test's
                        lambda images, **kw: np.mean(images, axis=2) / 255.0)
    pairs = [["Array3", "Diamond3"], ["Circle3", "Array3"], ["Diamond3", "Circle3"]]
    feats = {n: translate.image_features(markers=skins[n], eval_indenters=["wave"], n_eval=24) for n in SKINS}
    translated = {study.pair_label(s, t): dict(zip(("chunks", "out"), run_node(translate.translate_sequence(
        model=trained, source_markers=skins[s], target_markers=skins[t], eval_indenters=["wave"], n_eval=24))))
        for s, t in pairs}
    translated = {k: {"images": np.concatenate([c["images"] for c in v["chunks"]]),
                      "frame": np.concatenate([c["frame"] for c in v["chunks"]]), **v["out"]}
                  for k, v in translated.items()}
    out = study.image_study(study="s", pairs=pairs, features=feats, translated=translated, kid_subset=10,
                            markers=skins)
    m = out["metrics"]
    for s, t in pairs:
        before, m2m = m[f"s/{s}_{t}/before/motion_err_px"], m[f"s/{s}_{t}/m2m/motion_err_px"]
        assert 1.3 < before < 2.2
        assert m2m < 0.85 * before, (s, t, m2m, before)      # measured 0.29-0.73 of it
    assert m["s/mean/m2m/motion_err_px"] < 0.6 * m["s/mean/before/motion_err_px"]   # 0.50
    assert out["motion_err"]["m2m"].shape == (3, 3) and "motion" in out["figures"]


def test_motion_errors_only_where_both_skins_deformed_alike(skins, monkeypatch):
    """Pairs of one mechanical twin (equal force labels) are scored, others are not: their
    target's own frames are not the truth for the source's deformation."""
    monkeypatch.setattr("stages.imagemetrics.inception_features", lambda images, **kw: np.mean(images, axis=2))
    pairs = [["Array3", "Diamond3"], ["Diamond3", "Circle3"]]
    feats = {n: translate.image_features(markers=skins[n], eval_indenters=["wave"], n_eval=8) for n in SKINS}
    warped = {}
    for s, t in pairs:
        chunks, out = run_node(translate.flow_warp_sequence(source_markers=skins[s], target_markers=skins[t],
                                                        eval_indenters=["wave"], n_eval=8))
        warped[study.pair_label(s, t)] = {**out, **{k: np.concatenate([c[k] for c in chunks])
                                                    for k in ("images", "frame")}}
    run = dict(study="s", pairs=pairs, features=feats, translated=warped, kid_subset=4)
    m = study.image_study(**run, markers=skins)["metrics"]
    for s, t in pairs:
        assert m[f"s/{s}_{t}/m2m/motion_err_px"] < 0.5 * m[f"s/{s}_{t}/before/motion_err_px"]
    other = dict(skins, Circle3={**skins["Circle3"], "force": skins["Circle3"]["force"] + 1.0})
    out = study.image_study(**run, markers=other)
    assert "s/Diamond3_Circle3/m2m/motion_err_px" not in out["metrics"]
    assert out["metrics"]["s/mean/m2m/motion_err_px"] == m["s/Array3_Diamond3/m2m/motion_err_px"]
    assert set(study.image_study(**run)["figures"]) == {"fid", "kid", "tsne"}      # no markers: no motion
    assert "motion" in out["figures"] and np.isnan(out["motion_err"]["m2m"][2, 0])
    # a target whose markers do not move (a z-only taxel skin's dots): no score, not NaN
    still = dict(skins, Circle3={**skins["Circle3"], "images": np.broadcast_to(
        skins["Circle3"]["reference"], skins["Circle3"]["images"].shape).copy()})
    out = study.image_study(**run, markers=still)
    assert "s/Diamond3_Circle3/m2m/motion_err_px" not in out["metrics"]
    assert out["metrics"]["s/Array3_Diamond3/m2m/motion_err_px"] == m["s/Array3_Diamond3/m2m/motion_err_px"]


def test_translation_streams_labels_and_matches_flow_warp_layout(skins, trained, monkeypatch):
    """translate streams, with their labels, the whole contacts of the training indenters and
    the scored frames of both splits; translate_sim the scored frames alone; flow_warp, which
    no choice reads, the test split's scored frames alone.  All score the same frames alike."""
    monkeypatch.setattr(translate, "CHUNK", 20)
    monkeypatch.setattr("stages.imagemetrics.inception_features",
                        lambda images, **kw: np.repeat(np.mean(images, axis=(1, 2))[:, None], 4, axis=1))
    src, tgt = skins["Circle3"], skins["Array3"]
    split = dict(eval_indenters=["wave"], n_eval=4)
    rows = eval_frame_indices(src, ["wave"], 4)
    val = eval_frame_indices(src, ["sphere"], 4)               # the validation split's frames too
    sphere = np.flatnonzero(src["indenter_id"] == 0)           # the training indenter's contacts
    assert 0 < len(sphere) < len(src["images"]) - len(rows)
    for gen, kept, has_val in (
            (translate.translate_sequence(model=trained, source_markers=src, target_markers=tgt, sampler_steps=2,
                                          val_indenters=["sphere"], train_indenters=["sphere"], **split),
             np.unique(np.r_[sphere, rows]), True),
            (translate.translate_sim_sequence(model=trained, source_markers=src, target_markers=tgt,
                                              val_indenters=["sphere"], **split), np.unique(np.r_[rows, val]), True),
            (translate.flow_warp_sequence(source_markers=src, target_markers=tgt, **split), rows, False)):
        chunks, out = run_node(gen)
        assert [len(c["images"]) for c in chunks] == [min(20, len(kept) - i) for i in range(0, len(kept), 20)]
        for key in ("force", "depth", "phase", "contact_id", "indenter_id", "paired", "frame"):
            np.testing.assert_array_equal(np.concatenate([c[key] for c in chunks]), src[key][kept])
        images = np.concatenate([c["images"] for c in chunks])
        assert images.shape == (len(kept), *src["images"].shape[1:]) and set(np.unique(images)) <= {0, 255}
        np.testing.assert_array_equal(out["reference"], tgt["reference"])
        at = {int(r): i for i, r in enumerate(kept)}
        np.testing.assert_array_equal(out["eval_frames"], src["frame"][rows])
        np.testing.assert_allclose(out["features"][:, 0], images[[at[r] for r in rows]].mean(axis=(1, 2)))
        assert ("eval_frames_val" in out) == ("features_val" in out) == has_val
        if has_val:
            np.testing.assert_array_equal(out["eval_frames_val"], src["frame"][val])
            np.testing.assert_allclose(out["features_val"][:, 0], images[[at[r] for r in val]].mean(axis=(1, 2)))
        assert out["indenters"] == ["sphere", "wave"] and out["attrs"]["n_eval"] == 4
        assert out["attrs"]["frames"] == len(kept)
        assert bytes(out["figures"]["examples"][:4]) == PNG
    assert out["attrs"]["method"] == "flow_warp"


def test_the_finetune_weighs_changed_pixels_and_the_pretrain_does_not(skins, trained, monkeypatch):
    from stages.m2m import train
    shares = []

    def spy(*args, change_share=0.0, **kw):
        shares.append(change_share)
        raise RuntimeError("stop")
    monkeypatch.setattr(train, "fit", spy)
    with pytest.raises(RuntimeError, match="stop"):
        fit.finetune(base=trained, markers=skins, skins=["Array3", "Circle3"], train_indenters=["sphere"],
                     pairs_per_skin=3, steps=5, batch_size=4, lr=1e-4, seed=1)
    with pytest.raises(RuntimeError, match="stop"):
        fit.pretrain(markers=skins, skins=list(SKINS), train_indenters=["sphere"], size=(64, 64),
                     steps=5, batch_size=4, lr=1e-3, seed=0, width=8, timesteps=100)
    assert shares == [fit.CHANGE_SHARE, 0.0] and fit.CHANGE_SHARE == 0.1


def test_finetune_starts_from_the_base_and_uses_few_pairs(skins, trained):
    two = ["Array3", "Circle3"]
    tuned = fit.finetune(base=trained, markers=skins, skins=two, train_indenters=["sphere"],
                           pairs_per_skin=3, steps=5, batch_size=4, lr=1e-4, seed=1)
    assert tuned["attrs"]["pairs"] == 3 and tuned["attrs"]["base_skins"] == list(SKINS)
    assert tuned["attrs"]["config"] == trained["attrs"]["config"]
    w0, w1 = trained["weights"], tuned["weights"]
    assert set(w0) == set(w1)
    change = max(float(np.abs(w1[k] - w0[k]).max()) for k in w0)
    assert 0 < change < 0.01              # 5 small steps away from the pretrained weights


def test_skins_of_one_marker_style_are_one_target(skins, trained):
    """Before: two skins with identical references stopped the fine-tune.  Now a copy (and a
    near copy: a few pixels flipped, as a re-fabricated gel) is the style of the first: the
    fine-tune trains on the same frames as without them, bit for bit, and names them in its
    attrs; a set of one style alone trains nothing."""
    near = np.array(skins["Circle3"]["reference"], np.uint8)
    near.flat[np.random.default_rng(0).choice(near.size, max(1, near.size // 400), replace=False)] ^= 255
    twin = dict(skins, Copy3=skins["Circle3"], Near3={**skins["Circle3"], "reference": near})
    kw = dict(base=trained, train_indenters=["sphere"], pairs_per_skin=3, steps=5, batch_size=4, lr=1e-4, seed=1)
    plain = fit.finetune(markers=skins, skins=["Array3", "Circle3"], **kw)
    both = fit.finetune(markers=twin, skins=["Array3", "Circle3", "Copy3", "Near3"], **kw)
    assert both["attrs"]["same_style"] == {"Copy3": "Circle3", "Near3": "Circle3"}
    for k, v in plain["weights"].items():
        np.testing.assert_array_equal(both["weights"][k], v, err_msg=k)
    alone = fit.finetune(markers=twin, skins=["Circle3", "Copy3"], **kw)
    assert alone["attrs"]["steps"] == 0 and alone["attrs"]["same_style"] == {"Copy3": "Circle3"}
    for k, v in trained["weights"].items():
        np.testing.assert_array_equal(alone["weights"][k], v, err_msg=k)
    gathered = fit.finetune(markers={s: twin[s] for s in ("Array3", "Circle3", "Copy3")}, **kw)   # skins: all
    assert gathered["attrs"]["skins"] == ["Array3", "Circle3", "Copy3"] and gathered["attrs"]["steps"] == 5
    for k, v in plain["weights"].items():
        np.testing.assert_array_equal(gathered["weights"][k], v, err_msg=k)


def test_a_translation_within_one_marker_style_is_the_identity(skins, trained):
    from stages.m2m.translate import translate_sequence
    from tests.helpers import drain
    src = skins["Circle3"]
    chunks, out = drain(translate_sequence(model=trained, source_markers=src, target_markers=dict(src),
                                           eval_indenters=["wave"], n_eval=4, train_indenters=["sphere"]))
    images = np.concatenate([c["images"] for c in chunks])
    rows = np.concatenate([c["frame"] for c in chunks])
    at = {int(f): i for i, f in enumerate(np.asarray(src["frame"]))}
    np.testing.assert_array_equal(images, np.asarray(src["images"])[[at[int(f)] for f in rows]])
    assert out["attrs"]["same_style"] is True


def test_image_study_metrics_matrices_and_figures():
    rng = np.random.default_rng(0)
    names = ["A", "B", "C"]
    feats = {n: {"features": rng.normal(3 * i, 1.0, (10, 16)), "features_val": rng.normal(i, 1.0, (10, 16))}
             for i, n in enumerate(names)}
    pairs = [["A", "B"], ["B", "A"], ["C", "A"]]
    near = {study.pair_label(s, t): {"features": feats[t]["features"] + rng.normal(0, 0.1, (10, 16)),
                                     "features_val": feats[s]["features_val"]}
            for s, t in pairs}
    far = {study.pair_label(s, t): {"features": feats[t]["features"] + rng.normal(1.0, 0.5, (10, 16)),
                                    "features_val": feats[t]["features_val"]}
           for s, t in pairs}
    out = study.image_study(study="sim-m2m", pairs=pairs, features=feats, translated=near, warped=far,
                            kid_subset=5)
    m = out["metrics"]
    assert m["sim-m2m/A_B/before/fid"] == pytest.approx(fid(feats["A"]["features"], feats["B"]["features"]))
    for method in ("before", "m2m", "flow_warp"):
        vals = [m[f"sim-m2m/{s}_{t}/{method}/fid"] for s, t in pairs]
        assert m[f"sim-m2m/mean/{method}/fid"] == pytest.approx(np.mean(vals))
        assert f"sim-m2m/mean/{method}/kid" in m
    assert m["sim-m2m/mean/m2m/fid"] < m["sim-m2m/mean/flow_warp/fid"] < m["sim-m2m/mean/before/fid"]
    # the validation split, scored alike on its own features: here m2m copies the source's
    assert m["sim-m2m_val/A_B/m2m/fid"] == pytest.approx(fid(feats["A"]["features_val"], feats["B"]["features_val"]))
    assert m["sim-m2m_val/A_B/m2m/fid"] == m["sim-m2m_val/A_B/before/fid"]
    assert m["sim-m2m_val/C_A/flow_warp/fid"] == pytest.approx(0.0, abs=1e-6)
    assert len(m) == 2 * (len(pairs) + 1) * 3 * 2
    f = out["fid"]["m2m"]
    assert f.shape == (3, 3) and np.isnan(f[0, 0]) and np.isnan(f[0, 2]) and np.isfinite(f[2, 0])
    assert f[1, 0] == pytest.approx(m["sim-m2m/B_A/m2m/fid"])
    assert out["skins"] == names and set(out["figures"]) == {"fid", "kid", "tsne"}
    with pytest.raises(KeyError, match="source=C,target=B"):
        study.image_study(study="x", pairs=[["C", "B"]], features=feats, translated=near, warped={},
                          kid_subset=5)
