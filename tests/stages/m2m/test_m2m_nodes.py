"""Node functions: training, translation streams, features and the image study."""
import numpy as np
import pytest
from m2m_synthetic import SKINS

from stages.imagemetrics import fid, kid
from stages.m2m import nodes
from stages.m2m.data import eval_frame_indices
from tests.helpers import drain as run_node

N_EVAL = 6
PNG = bytes([0x89, 0x50, 0x4E, 0x47])


@pytest.fixture(scope="module")
def trained(skins):
    """A width-8 generator trained from scratch for 1200 steps on the 3 tiny skins (~40 s; at
    400 steps it drew the target's markers but kept little of their motion)."""
    return nodes.pretrain(markers=skins, skins=list(SKINS), train_indenters=["sphere"], size=(64, 64),
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
    real = nodes.image_features(markers=tgt, eval_indenters=["wave"], n_eval=N_EVAL)
    before = nodes.image_features(markers=src, eval_indenters=["wave"], n_eval=N_EVAL)
    chunks, out = run_node(nodes.translate_sequence(model=trained, source_markers=src, target_markers=tgt,
                                                    eval_indenters=["wave"], n_eval=N_EVAL))
    np.testing.assert_array_equal(out["eval_frames"], real["eval_frames"])
    fid_before, fid_m2m = fid(before["features"], real["features"]), fid(out["features"], real["features"])
    kid_before, kid_m2m = kid(before["features"], real["features"]), kid(out["features"], real["features"])
    assert fid_before > 100 and fid_m2m < 0.5 * fid_before
    assert kid_m2m < 0.5 * kid_before
    rows = eval_frame_indices(src, ["wave"], N_EVAL)
    images = np.concatenate([c["images"] for c in chunks])
    assert _iou(images[rows], tgt["images"][rows]) > _iou(tgt["reference"][None], tgt["images"][rows]) + 0.02


def test_trained_model_keeps_the_deformation(skins, trained, monkeypatch):
    """On the held-out indenter's frames the translations' markers move as the target's own
    do: image_study's motion_err_px (the mean |measured - true| displacement of the markers
    that move > 1 px) is well below the undeformed reference's, which keeps none of it and
    so scores their mean motion (1.5-1.7 px here)."""
    monkeypatch.setattr("stages.imagemetrics.inception_features",   # FID is not this test's
                        lambda images, **kw: np.mean(images, axis=2) / 255.0)
    pairs = [["Array3", "Diamond3"], ["Circle3", "Array3"], ["Diamond3", "Circle3"]]
    feats = {n: nodes.image_features(markers=skins[n], eval_indenters=["wave"], n_eval=24) for n in SKINS}
    translated = {nodes.pair_label(s, t): dict(zip(("chunks", "out"), run_node(nodes.translate_sequence(
        model=trained, source_markers=skins[s], target_markers=skins[t], eval_indenters=["wave"], n_eval=24))))
        for s, t in pairs}
    translated = {k: {"images": np.concatenate([c["images"] for c in v["chunks"]]),
                      "frame": np.concatenate([c["frame"] for c in v["chunks"]]), **v["out"]}
                  for k, v in translated.items()}
    out = nodes.image_study(study="s", pairs=pairs, features=feats, translated=translated, kid_subset=10,
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
    feats = {n: nodes.image_features(markers=skins[n], eval_indenters=["wave"], n_eval=8) for n in SKINS}
    warped = {}
    for s, t in pairs:
        chunks, out = run_node(nodes.flow_warp_sequence(source_markers=skins[s], target_markers=skins[t],
                                                        eval_indenters=["wave"], n_eval=8))
        warped[nodes.pair_label(s, t)] = {**out, **{k: np.concatenate([c[k] for c in chunks])
                                                    for k in ("images", "frame")}}
    run = dict(study="s", pairs=pairs, features=feats, translated=warped, kid_subset=4)
    m = nodes.image_study(**run, markers=skins)["metrics"]
    for s, t in pairs:
        assert m[f"s/{s}_{t}/m2m/motion_err_px"] < 0.5 * m[f"s/{s}_{t}/before/motion_err_px"]
    other = dict(skins, Circle3={**skins["Circle3"], "force": skins["Circle3"]["force"] + 1.0})
    out = nodes.image_study(**run, markers=other)
    assert "s/Diamond3_Circle3/m2m/motion_err_px" not in out["metrics"]
    assert out["metrics"]["s/mean/m2m/motion_err_px"] == m["s/Array3_Diamond3/m2m/motion_err_px"]
    assert set(nodes.image_study(**run)["figures"]) == {"fid", "kid", "tsne"}      # no markers: no motion
    assert "motion" in out["figures"] and np.isnan(out["motion_err"]["m2m"][2, 0])
    # a target whose markers do not move (a z-only taxel skin's dots): no score, not NaN
    still = dict(skins, Circle3={**skins["Circle3"], "images": np.broadcast_to(
        skins["Circle3"]["reference"], skins["Circle3"]["images"].shape).copy()})
    out = nodes.image_study(**run, markers=still)
    assert "s/Diamond3_Circle3/m2m/motion_err_px" not in out["metrics"]
    assert out["metrics"]["s/Array3_Diamond3/m2m/motion_err_px"] == m["s/Array3_Diamond3/m2m/motion_err_px"]


def test_translation_streams_labels_and_matches_flow_warp_layout(skins, trained, monkeypatch):
    monkeypatch.setattr(nodes, "CHUNK", 20)
    monkeypatch.setattr("stages.imagemetrics.inception_features",
                        lambda images, **kw: np.repeat(np.mean(images, axis=(1, 2))[:, None], 4, axis=1))
    src, tgt = skins["Circle3"], skins["Array3"]
    for gen in (nodes.translate_sequence(model=trained, source_markers=src, target_markers=tgt, eval_indenters=["wave"],
                                         n_eval=4, sampler_steps=2),
                nodes.flow_warp_sequence(source_markers=src, target_markers=tgt, eval_indenters=["wave"], n_eval=4)):
        chunks, out = run_node(gen)
        assert [len(c["images"]) for c in chunks] == [20, 20, 8]
        for key in ("force", "depth", "phase", "contact_id", "indenter_id", "paired", "frame"):
            np.testing.assert_array_equal(np.concatenate([c[key] for c in chunks]), src[key])
        images = np.concatenate([c["images"] for c in chunks])
        assert images.shape == src["images"].shape and set(np.unique(images)) <= {0, 255}
        np.testing.assert_array_equal(out["reference"], tgt["reference"])
        rows = eval_frame_indices(src, ["wave"], 4)
        np.testing.assert_array_equal(out["eval_frames"], src["frame"][rows])
        np.testing.assert_allclose(out["features"][:, 0], images[rows].mean(axis=(1, 2)))
        assert out["indenters"] == ["sphere", "wave"] and out["attrs"]["n_eval"] == 4
        assert bytes(out["figures"]["examples"][:4]) == PNG
    assert out["attrs"]["method"] == "flow_warp"


def test_finetune_starts_from_the_base_and_uses_few_pairs(skins, trained):
    two = ["Array3", "Circle3"]
    tuned = nodes.finetune(base=trained, markers=skins, skins=two, train_indenters=["sphere"],
                           pairs_per_skin=3, steps=5, batch_size=4, lr=1e-4, seed=1)
    assert tuned["attrs"]["pairs"] == 3 and tuned["attrs"]["base_skins"] == list(SKINS)
    assert tuned["attrs"]["config"] == trained["attrs"]["config"]
    w0, w1 = trained["weights"], tuned["weights"]
    assert set(w0) == set(w1)
    change = max(float(np.abs(w1[k] - w0[k]).max()) for k in w0)
    assert 0 < change < 0.01              # 5 small steps away from the pretrained weights


def test_finetune_refuses_two_skins_drawn_alike(skins, trained):
    twin = dict(skins, Copy3=skins["Circle3"])
    with pytest.raises(ValueError, match="skins 'Circle3' and 'Copy3' have identical reference images"):
        nodes.finetune(base=trained, markers=twin, skins=["Array3", "Circle3", "Copy3"],
                       train_indenters=["sphere"], pairs_per_skin=3, steps=5, batch_size=4, lr=1e-4, seed=1)


def test_image_study_metrics_matrices_and_figures():
    rng = np.random.default_rng(0)
    names = ["A", "B", "C"]
    feats = {n: {"features": rng.normal(3 * i, 1.0, (10, 16))} for i, n in enumerate(names)}
    pairs = [["A", "B"], ["B", "A"], ["C", "A"]]
    near = {nodes.pair_label(s, t): {"features": feats[t]["features"] + rng.normal(0, 0.1, (10, 16))}
            for s, t in pairs}
    far = {nodes.pair_label(s, t): {"features": feats[t]["features"] + rng.normal(1.0, 0.5, (10, 16))}
           for s, t in pairs}
    out = nodes.image_study(study="sim-m2m", pairs=pairs, features=feats, translated=near, warped=far,
                            kid_subset=5)
    m = out["metrics"]
    assert m["sim-m2m/A_B/before/fid"] == pytest.approx(fid(feats["A"]["features"], feats["B"]["features"]))
    for method in ("before", "m2m", "flow_warp"):
        vals = [m[f"sim-m2m/{s}_{t}/{method}/fid"] for s, t in pairs]
        assert m[f"sim-m2m/mean/{method}/fid"] == pytest.approx(np.mean(vals))
        assert f"sim-m2m/mean/{method}/kid" in m
    assert m["sim-m2m/mean/m2m/fid"] < m["sim-m2m/mean/flow_warp/fid"] < m["sim-m2m/mean/before/fid"]
    f = out["fid"]["m2m"]
    assert f.shape == (3, 3) and np.isnan(f[0, 0]) and np.isnan(f[0, 2]) and np.isfinite(f[2, 0])
    assert f[1, 0] == pytest.approx(m["sim-m2m/B_A/m2m/fid"])
    assert out["skins"] == names and set(out["figures"]) == {"fid", "kid", "tsne"}
    with pytest.raises(KeyError, match="source=C,target=B"):
        nodes.image_study(study="x", pairs=[["C", "B"]], features=feats, translated=near, warped={},
                          kid_subset=5)


def test_translations_into_a_listed_taxel_skin_are_redrawn_as_its_dots(skins, monkeypatch):
    """flow_warp into a z-only taxel skin named in redraw_taxels: the warp moved the dots, the
    output has them back at their taxel centres (exactly uskin.redraw of the plain output);
    a skin not listed is left alone, and a listed skin that is not taxel dots is refused."""
    from stages.markers.uskin import MID_SCALE, read_dots, redraw, signal_to_marker, taxel_centres
    monkeypatch.setattr("stages.imagemetrics.inception_features",
                        lambda images, **kw: np.zeros((len(images), 4)))
    src = skins["Circle3"]
    size = src["images"].shape[1:]
    settings = {"size": list(size), "pad_mm": [24.6, 22.6], "z_only": True, "base_area": 2.0,
                "max_area": 16.0, "max_offset": 0.8}
    base = np.full((16, 3), MID_SCALE)
    raw = base + np.random.default_rng(0).uniform(0, 900, (len(src["images"]), 16, 3))
    kw = {k: v for k, v in settings.items() if k != "size"}
    tgt = {**src, "images": signal_to_marker(raw, base, size=size, **kw),
           "reference": signal_to_marker(base, base, size=size, **kw),
           "attrs": {"look": "taxel", "settings": settings}}
    run = dict(source_markers=src, target_markers=tgt, eval_indenters=["wave"], n_eval=4, target="uskin-z")
    plain_chunks, plain = run_node(nodes.flow_warp_sequence(**run))
    chunks, out = run_node(nodes.flow_warp_sequence(**run, redraw_taxels=["uskin-3axis", "uskin-z"]))
    warped = np.concatenate([c["images"] for c in plain_chunks])
    images = np.concatenate([c["images"] for c in chunks])
    assert "redraw_taxels" not in plain["attrs"] and out["attrs"]["redraw_taxels"] is True
    centres, _ = read_dots(warped)
    assert np.abs(centres - taxel_centres()).max() > 0.3          # the warp moved dots (mm)
    np.testing.assert_array_equal(images, redraw(warped, settings))
    centres, _ = read_dots(images)
    assert np.abs(centres - taxel_centres()).max() < 0.1
    with pytest.raises(ValueError, match=r"m2m.redraw_taxels names 'Array3', whose markers are not taxel dots"):
        run_node(nodes.flow_warp_sequence(source_markers=src, target_markers=skins["Array3"],
                                          eval_indenters=["wave"], n_eval=4, target="Array3",
                                          redraw_taxels=["Array3"]))


def _taxel_skin(like, seed=0, shift=0.0):
    """A 3-axis taxel skin on `like`'s frames at its size: dots moved and grown at random, and
    with shift > 0 all 16 of a frame's dots moved together by a random common shift (signal
    units, sd `shift`)."""
    from stages.markers.uskin import MID_SCALE, signal_to_marker
    size = like["images"].shape[1:]
    settings = {"size": list(size), "pad_mm": [24.6, 22.6], "z_only": False, "base_area": 4.0,
                "max_area": 16.0, "max_offset": 0.8}
    base = np.full((16, 3), MID_SCALE)
    rng = np.random.default_rng(seed)
    n = len(like["images"])
    raw = base + np.concatenate([rng.normal(0, 2000, (n, 16, 2)), rng.uniform(0, 600, (n, 16, 1))], -1)
    if shift > 0:
        raw[..., :2] += rng.normal(0, shift, (n, 1, 2))
    kw = dict(s_xy=20000.0, s_z=150.0, **{k: v for k, v in settings.items() if k != "size"})
    return {**like, "images": signal_to_marker(raw, base, size=size, **kw),
            "reference": signal_to_marker(base, base, size=size, **kw),
            "attrs": {"look": "taxel", "settings": settings}}, settings


def test_matched_gain_restores_the_spread_of_a_timid_translators_dots(skins):
    """A 'translator' that draws the skin's own dots at half their motion and area change gets
    gains ~2 on its paired training frames; one that copies gets 1; one that barely moves them
    is capped at the range's top."""
    from stages.markers.uskin import redraw
    tgt, settings = _taxel_skin(skins["Circle3"])
    gain = lambda convert, pairs=0: nodes.matched_gain(convert, tgt, tgt, ["sphere"], pairs, settings)
    assert gain(lambda ims: ims) == pytest.approx((1.0, 1.0, 1.0), rel=0.03)
    assert gain(lambda ims: redraw(ims, settings, gain=(0.5, 0.5, 0.5))) == pytest.approx((2.0, 2.0, 2.0), rel=0.1)
    assert gain(lambda ims: redraw(ims, settings, gain=(0.5, 1.0, 1.0)), pairs=8) == pytest.approx((2.0, 1.0, 1.0), rel=0.1)
    assert gain(lambda ims: redraw(ims, settings, gain=(0.01, 1.0, 1.0)))[0] == nodes.MATCH_GAIN_RANGE[1]


def test_matched_shift_gain_restores_the_common_shift_of_a_timid_translator(skins):
    """A 'translator' that draws the dots' common shift at half its size (x) and as it is (y)
    gets shift gains ~(2, 1), whatever it does to the rest of their motion; one that copies
    gets 1."""
    from stages.markers.uskin import redraw
    tgt, settings = _taxel_skin(skins["Circle3"], shift=4000.0)
    gain = lambda convert: nodes.matched_shift_gain(convert, tgt, tgt, ["sphere"], 0, settings)
    assert gain(lambda ims: ims) == pytest.approx((1.0, 1.0), rel=0.03)
    assert gain(lambda ims: redraw(ims, settings, shift_gain=(0.5, 1.0))) == pytest.approx((2.0, 1.0), rel=0.1)
    assert gain(lambda ims: redraw(ims, settings, gain=(0.5, 0.5, 1.0), shift_gain=(0.5, 1.0))) == \
        pytest.approx((2.0, 1.0), rel=0.1)


def test_matched_tilt_finds_the_tilt_that_made_a_z_only_skins_load(skins):
    """A z-only skin whose load pattern is a 3-axis skin's redrawn with a known tilt: matched_tilt
    of a 'translator' that draws the 3-axis skin (moving dots) finds that tilt again."""
    from stages.markers.uskin import redraw
    src, settings = _taxel_skin(skins["Circle3"], shift=4000.0)
    z_settings, tilt = {**settings, "z_only": True, "min_area": 0.5}, ((0.8, 20.0), (0.6, -25.0))
    tgt = {**src, "images": redraw(src["images"], z_settings, tilt=tilt),
           "attrs": {"look": "taxel", "settings": z_settings}}
    got = nodes.matched_tilt(lambda ims: ims, src, tgt, ["sphere"], 0, z_settings)
    for (a, b), (ga, gb) in zip(tilt, got):
        assert ga == pytest.approx(a, abs=0.1) and gb == pytest.approx(b, rel=0.15)


def _sheared_loads(n=120, compress=1.0, seed=0):
    """(area changes (N,16), shear (N,2), which is also the dots' drawn common shift): a z-only
    skin's load under a contact at a random place (x within +-4 mm, y +-1 mm; `compress` times
    that where it is drawn) with a random shear, which tilts the load by a plane across the pad
    that lowers it ahead of the contact (as Cerruti's solution), so that the dots there shrink."""
    from stages.markers.uskin import _taxel_positions
    rng = np.random.default_rng(seed)
    grid = _taxel_positions((24.6, 22.6))
    place = rng.uniform([-4.0, -1.0], [4.0, 1.0], (n, 2))
    load = rng.uniform(2.0, 6.0, n)
    shear = rng.normal(0.0, 1.0, (n, 2))
    blob = np.exp(-((grid[None] - compress * place[:, None]) ** 2).sum(-1) / (2 * 4.0 ** 2))
    blob *= (load / blob.sum(1))[:, None] * 16
    return blob - 0.15 * shear @ grid.T, shear


def test_shrink_guard_keeps_a_fit_that_shrinks_the_dots_where_the_skin_does():
    """Translations that draw the skin's load with its moment along one axis halved by a plane:
    the least-squares tilt (2, 0) restores the skin's load, shrunk dots and all, and is kept; so
    is a fit with a <= 1, and any fit on a skin whose dots cannot shrink (min_area = base_area)."""
    from stages.markers.uskin import load_moments, tilt_changes
    real, shift = _sheared_loads()
    offsets = np.repeat(shift[:, None], 16, 1)
    moment, drawn = load_moments(offsets, real)
    z = {"base_area": 2.0, "min_area": 0.5, "max_area": 16.0, "z_only": True}
    for k in (0, 1):
        halved = moment.copy()
        halved[:, k] *= 0.5
        fake = tilt_changes(real, moment, halved, (24.6, 22.6))
        fake_moment, _ = load_moments(offsets, fake)
        fit = tuple(float(c) for c in np.linalg.lstsq(np.stack([fake_moment[:, k], drawn[:, k]], 1),
                                                      moment[:, k], rcond=None)[0])
        assert fit == pytest.approx((2.0, 0.0), abs=1e-6)
        assert nodes.shrink_guard(k, fit, fake, fake_moment, drawn, real, moment, z, (24.6, 22.6)) == fit
        assert nodes.shrink_guard(k, (0.4, -3.0), fake, fake_moment, drawn, real, moment, z,
                                  (24.6, 22.6)) == (0.4, -3.0)
    assert nodes.shrink_guard(0, (1.7, -3.0), fake, fake_moment, drawn, real, moment,
                              {**z, "min_area": 2.0}, (24.6, 22.6)) == (1.7, -3.0)


def test_shrink_guard_refuses_a_tilt_that_moves_the_shrunk_dots_with_the_contact():
    """Translations that draw the contact 0.55 as far from the pad's centre as the skin, and its
    shear only as the dots' common shift: the least-squares fit scales their load's moment up
    (a ~1.8), and the plane that adds moves the shrunk dots with where the contact is.
    shrink_guard replaces it with an a between 0.8 and 1.4, whose shrunk dots follow the skin's
    (correlation above 0.9 where the fit's is below 0.8), its b the least-squares fit given that a."""
    from stages.markers.uskin import _taxel_positions, load_moments, shrink_centroids, tilt_changes
    real, shift = _sheared_loads()
    fake, _ = _sheared_loads(compress=0.55)
    fake = fake + 0.15 * shift @ _taxel_positions((24.6, 22.6)).T      # no tilt drawn
    offsets = np.repeat(shift[:, None], 16, 1)
    fake_moment, drawn = load_moments(offsets, fake)
    real_moment, _ = load_moments(offsets, real)
    z = {"base_area": 2.0, "min_area": 0.5, "max_area": 16.0, "z_only": True}
    pad = (24.6, 22.6)
    x = np.stack([fake_moment[:, 0], drawn[:, 0]], 1)
    fit = tuple(float(c) for c in np.linalg.lstsq(x, real_moment[:, 0], rcond=None)[0])
    assert fit[0] > 1.5
    a, b = nodes.shrink_guard(0, fit, fake, fake_moment, drawn, real, real_moment, z, pad)
    assert 0.8 <= a <= 1.4 and a in nodes.TILT_WEIGHTS
    assert b == pytest.approx(float(drawn[:, 0] @ (real_moment[:, 0] - a * fake_moment[:, 0])
                                    / (drawn[:, 0] @ drawn[:, 0])))
    real_c, _ = shrink_centroids(real, z, pad)

    def corr(a_, b_):
        want = fake_moment.copy()
        want[:, 0] = a_ * fake_moment[:, 0] + b_ * drawn[:, 0]
        c, lost = shrink_centroids(tilt_changes(fake, fake_moment, want, pad), z, pad)
        return np.corrcoef(c[lost > 1e-3, 0], real_c[lost > 1e-3, 0])[0, 1]
    assert corr(a, b) > 0.9 and corr(*fit) < 0.8


@pytest.mark.parametrize("mode,z_only", [("spread", False), ("shift", False), ("shift", True)])
def test_translate_redraw_match_draws_with_the_matched_gain(skins, trained, monkeypatch, mode, z_only):
    """translate with redraw_match into a listed taxel skin: attrs carry the gains, which are
    matched_gain ("spread"), matched_shift_gain ("shift") or for a z-only skin matched_tilt
    ("shift") on the model's training indenters, and the images are the plain translation
    redrawn with them; an unknown mode is refused."""
    from stages.m2m.model import load_translator
    from stages.markers.uskin import redraw
    monkeypatch.setattr("stages.imagemetrics.inception_features",
                        lambda images, **kw: np.zeros((len(images), 4)))
    src = skins["Circle3"]
    tgt, settings = _taxel_skin(src, seed=1, shift=3000.0)
    if z_only:
        settings = {**settings, "z_only": True}
        tgt = {**tgt, "attrs": {"look": "taxel", "settings": settings}}
    run = dict(model=trained, source_markers=src, target_markers=tgt, eval_indenters=["wave"], n_eval=4,
               target="uskin-3axis", redraw_taxels=["uskin-3axis"])
    chunks, out = run_node(nodes.translate_sequence(**run, redraw_match=mode))
    translator = load_translator(trained)
    plain = lambda ims: translator.translate(ims, src["reference"], tgt["reference"], 1)
    if mode == "spread":
        g = tuple(out["attrs"]["redraw_gain"])
        assert g == nodes.matched_gain(plain, src, tgt, ["sphere"], 0, settings) and g != (1.0, 1.0, 1.0)
        assert "redraw_shift_gain" not in out["attrs"]
        expected = redraw(plain(src["images"]), settings, gain=g)
    elif z_only:
        g = tuple(tuple(row) for row in out["attrs"]["redraw_tilt"])
        assert g == nodes.matched_tilt(plain, src, tgt, ["sphere"], 0, settings)
        assert out["attrs"]["redraw_gain"] == [1.0, 1.0, 1.0] and "redraw_shift_gain" not in out["attrs"]
        expected = redraw(plain(src["images"]), settings, tilt=g)
    else:
        g = tuple(out["attrs"]["redraw_shift_gain"])
        assert g == nodes.matched_shift_gain(plain, src, tgt, ["sphere"], 0, settings) and g != (1.0, 1.0)
        assert out["attrs"]["redraw_gain"] == [1.0, 1.0, 1.0]
        expected = redraw(plain(src["images"]), settings, shift_gain=g)
    np.testing.assert_array_equal(np.concatenate([c["images"] for c in chunks]), expected)
    _, unmatched = run_node(nodes.translate_sequence(**run))
    assert unmatched["attrs"]["redraw_gain"] == [1.0, 1.0, 1.0] and "redraw_shift_gain" not in unmatched["attrs"]
    with pytest.raises(ValueError, match=r"m2m.redraw_match must be one of none, spread, shift, got True"):
        run_node(nodes.translate_sequence(**run, redraw_match=True))


def _z_source(skins, tilt=((0.3, 60.0), (0.3, -60.0))):
    """(z-only source skin, its settings, 3-axis target skin, its settings): the target's dots
    move with a random common shift, and the source is the same frames drawn z-only with that
    shift turned into a tilt of the load (uskin.redraw's tilt), as a shear shows on a z-only
    skin."""
    from stages.markers.uskin import redraw
    tgt, settings = _taxel_skin(skins["Circle3"], seed=2, shift=4000.0)
    z_settings = {**settings, "z_only": True, "min_area": 0.5}
    src = {**tgt, "images": redraw(tgt["images"], z_settings, tilt=tilt),
           "reference": redraw(tgt["reference"][None], z_settings)[0],
           "attrs": {"look": "taxel", "settings": z_settings}}
    return src, z_settings, tgt, settings


def test_source_shift_read_reads_the_common_shift_off_a_z_only_sources_load(skins):
    """The common shift of a 3-axis skin's dots, read by ridge regression off a z-only skin's
    dots whose load it tilted, fitted on the paired frames: follows the skin's own common shift
    at correlation > 0.95 on both axes (the z-only dots themselves do not move)."""
    from stages.markers.uskin import dot_changes, load_moments
    src, z_settings, tgt, settings = _z_source(skins)
    read = nodes.source_shift_read(src, tgt, ["sphere"], 0, z_settings, settings)
    assert np.asarray(read["coef"]).shape == (2, 48) and len(read["intercept"]) == len(read["alpha"]) == 2
    assert all(a in nodes.SHIFT_READ_ALPHAS for a in read["alpha"])
    got = nodes.read_source_shift(read, src["images"], z_settings)
    _, shift = load_moments(*dot_changes(tgt["images"], settings))
    _, z_shift = load_moments(*dot_changes(src["images"], z_settings))
    assert np.abs(z_shift).max() < 1e-9
    for k in (0, 1):
        assert np.corrcoef(got[:, k], shift[:, k])[0, 1] > 0.95


def test_translate_redraw_source_shift_reads_the_shift_off_a_taxel_source(skins, trained, monkeypatch):
    """translate from a taxel skin into a listed 3-axis taxel skin with redraw_source_shift: the
    images are the plain translation redrawn with the common shift source_shift_read reads off
    the source's dots (attrs redraw_source_shift), with no matched shift gain; without it, or
    from a camera skin, the shift gain as before; a value that is not a bool is refused."""
    from stages.m2m.model import load_translator
    from stages.markers.uskin import redraw
    monkeypatch.setattr("stages.imagemetrics.inception_features",
                        lambda images, **kw: np.zeros((len(images), 4)))
    src, z_settings, tgt, settings = _z_source(skins)
    run = dict(model=trained, target_markers=tgt, eval_indenters=["wave"], n_eval=4, target="uskin-3axis",
               redraw_taxels=["uskin-3axis"], redraw_match="shift")
    chunks, out = run_node(nodes.translate_sequence(**run, source_markers=src, redraw_source_shift=True))
    read = nodes.source_shift_read(src, tgt, ["sphere"], 0, z_settings, settings)
    assert out["attrs"]["redraw_source_shift"] == read
    assert out["attrs"]["redraw_gain"] == [1.0, 1.0, 1.0] and "redraw_shift_gain" not in out["attrs"]
    translator = load_translator(trained)
    plain = translator.translate(src["images"], src["reference"], tgt["reference"], 1)
    np.testing.assert_array_equal(np.concatenate([c["images"] for c in chunks]),
                                  redraw(plain, settings, shift=nodes.read_source_shift(read, src["images"], z_settings)))
    _, off = run_node(nodes.translate_sequence(**run, source_markers=src, redraw_source_shift=False))
    _, camera = run_node(nodes.translate_sequence(**run, source_markers=skins["Circle3"], redraw_source_shift=True))
    for attrs in (off["attrs"], camera["attrs"]):
        assert "redraw_source_shift" not in attrs and len(attrs["redraw_shift_gain"]) == 2
    with pytest.raises(ValueError, match=r"m2m.redraw_source_shift must be true or false, got 'yes'"):
        run_node(nodes.translate_sequence(**run, source_markers=src, redraw_source_shift="yes"))
