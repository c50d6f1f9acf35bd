"""The M2M network, samplers, weights as arrays and the Translator."""
import numpy as np
import pytest
import torch

from stages.m2m import load_translator
from stages.m2m.model import (Translator, alphas_cumprod, build, default_config, sample, state_arrays,
                              weights_of)
from stages.m2m.train import PairBatches, fit, loss_fn, noisy_input


def _model(size=(32, 32), width=8, seed=0):
    cfg = default_config(size=size, width=width, timesteps=50)
    torch.manual_seed(seed)
    net = build(cfg)
    with torch.no_grad():                 # random, not-near-zero outputs
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return cfg, net


def _images(n, size=32, seed=0):
    rng = np.random.default_rng(seed)
    return np.where(rng.random((n, size, size)) < 0.2, 255, 0).astype(np.uint8)


def test_weights_round_trip_through_arrays_gives_identical_outputs():
    cfg, net = _model()
    weights = state_arrays(net)
    assert all(isinstance(v, np.ndarray) and v.dtype == np.float32 for v in weights.values())
    # as a node returns it, and as a store artifact presents it (flattened names + attrs)
    nested = {"weights": weights, "attrs": {"config": cfg}}

    class Stored(dict):
        attrs = {"config": cfg}
    flat = Stored({f"weights/{k}": v for k, v in weights.items()})
    imgs, refs = _images(5), _images(2, seed=1)
    direct = Translator(cfg, weights).probabilities(imgs, refs[0], refs[1])
    for art in (nested, flat):
        t = load_translator(art)
        np.testing.assert_array_equal(t.probabilities(imgs, refs[0], refs[1]), direct)
    assert 0.05 < (direct >= 0.5).mean() < 0.95          # the random net is not saturated
    with pytest.raises(KeyError, match="do not fit"):
        build(default_config(size=(32, 32), width=16), weights)
    with pytest.raises(ValueError, match=r"not an M2M model artifact \(node m2m_sim or m2m\): its 'config' "
                                         r"attribute is missing"):
        load_translator({"weights": weights})
    with pytest.raises(ValueError, match="its 'config' attribute lacks size/width/timesteps"):
        load_translator({"weights": weights, "attrs": {"config": {"input_size": 64}}})   # a force model's
    bad = [(imgs[:, None], refs[0], r"translator images: expected \(H,W\) or \(N,H,W\) marker images, got shape \(5, 1,"),
           (imgs[0, 0], refs[0], r"translator images: expected \(H,W\) or \(N,H,W\) marker images, got shape \(\d+,\)"),
           (imgs / 255.0, refs[0], r"translator images: expected uint8 marker images \(0/255\), got float64"),
           (imgs.astype(np.int16) - 1, refs[0], r"translator images: values -1\.\.254 outside"),
           (imgs, refs, r"translator source_reference: expected \(H,W\) marker images, got shape \(2,"),
           (imgs, refs[0, :10], r"translator: images \(5, \d+, \d+\) and source_reference \(10, \d+\) must be")]
    for images, ref, message in bad:
        with pytest.raises(ValueError, match=message):
            t.translate(images, ref, refs[1])
    assert t.translate(imgs[:0], refs[0], refs[1]).shape == (0, *refs[1].shape)
    np.testing.assert_array_equal(t.probabilities(imgs > 127, refs[0], refs[1]),
                                  t.probabilities(np.where(imgs > 127, 255, 0).astype(np.uint8), refs[0], refs[1]))
    assert set(weights_of(flat)) == set(weights)


def test_translation_is_binary_deterministic_and_batch_independent():
    cfg, net = _model()
    t = Translator(cfg, state_arrays(net))
    imgs, refs = _images(6), _images(2, seed=1)
    out = t.translate(imgs, refs[0], refs[1], batch=4)
    assert out.shape == (6, 32, 32) and out.dtype == np.uint8 and set(np.unique(out)) <= {0, 255}
    np.testing.assert_array_equal(t.translate(imgs[3:4], refs[0], refs[1]), out[3:4])
    multi = t.translate(imgs, refs[0], refs[1], steps=4)
    assert multi.shape == out.shape and set(np.unique(multi)) <= {0, 255}
    one_p, multi_p = (t.probabilities(imgs, refs[0], refs[1], steps=k) for k in (1, 4))
    assert np.abs(one_p - multi_p).max() > 1e-3          # the multi-step sampler takes another path
    with pytest.raises(ValueError, match="steps"):
        t.translate(imgs, refs[0], refs[1], steps=0)


def test_translator_resizes_to_the_model_and_back():
    cfg, net = _model(size=(32, 32))
    t = Translator(cfg, state_arrays(net))
    imgs, refs = _images(2, size=64), _images(2, size=64, seed=1)
    out = t.translate(imgs, refs[0], refs[1])
    assert out.shape == (2, 64, 64) and set(np.unique(out)) <= {0, 255}


def test_sampler_steps_visit_decreasing_timesteps():
    cfg, net = _model()
    seen = []
    forward = net.forward
    net.forward = lambda x, c, t: (seen.append(int(t[0])), forward(x, c, t))[1]
    cond = torch.zeros(1, 3, 32, 32)
    sample(net, cond, cfg, steps=1)
    sample(net, cond, cfg, steps=3)
    assert seen == [49, 49, 24, 0]
    abar = alphas_cumprod(cfg)
    assert abar.shape == (50,) and float(abar[0]) == pytest.approx(1 - 1e-4) and float(abar[-1]) < abar[0]


def test_batches_apply_one_symmetry_to_all_channels_and_loss():
    imgs = _images(8, size=16).reshape(2, 4, 16, 16)
    imgs[1] = imgs[0]                          # skin 1 is skin 0, so target == input image
    refs = _images(2, size=16, seed=3)
    refs[1] = refs[0]
    cond, target = PairBatches(imgs, refs, seed=0)(16)
    assert cond.shape == (16, 3, 16, 16) and target.shape == (16, 1, 16, 16)
    np.testing.assert_array_equal(cond[:, :1] > 0, target > 0.5)     # the same transform on every channel
    np.testing.assert_array_equal(cond[:, 1], cond[:, 2])
    logits_good = (2 * target - 1) * 20
    assert float(loss_fn(logits_good, target)) < 0.01 < float(loss_fn(-logits_good, target))
    cfg = default_config(size=(16, 16), width=8, timesteps=50)
    x_t, t = noisy_input(target, cfg, torch.Generator().manual_seed(0))
    assert x_t.shape == target.shape and (t == 49).float().mean() >= 0.4


def light_and_heavy():
    """Two 8x8 examples on a 2x2-marker reference, 2 and 16 of 64 pixels changed, and a
    confident copy of the reference as the prediction: (reference, target, copy logits, the
    BCE of one wrong pixel, the soft-Dice term of the copy)."""
    from torch.nn import functional as F
    ref = torch.zeros(2, 1, 8, 8)
    ref[..., 2:4, 2:4] = 1.0
    target = ref.clone()
    target[0, 0, 2:4, 4] = 1.0                               # 2 changed pixels
    target[1, 0, 4:6, 0:8] = 1.0                             # 16 changed pixels
    copy = (2 * ref - 1) * 30
    wrong = float(F.binary_cross_entropy_with_logits(copy[0, 0, 2, 4], target[0, 0, 2, 4]))
    dice = 1 - ((2 * 4 + 1) / (4 + 6 + 1) + (2 * 4 + 1) / (4 + 20 + 1)) / 2
    return ref, target, copy, wrong, dice


def test_loss_is_the_mean_bce_plus_the_soft_dice_term():
    """A confident copy of the reference against targets that changed 2 and 16 of 64 pixels:
    the BCE is that of the 18 wrong pixels over all 128, plus the mean soft-Dice term; against
    the reference itself the loss is about 0."""
    ref, target, copy, wrong, dice = light_and_heavy()
    assert float(loss_fn(copy, target)) == pytest.approx(18 * wrong / 128 + dice, rel=1e-3)
    assert float(loss_fn(copy, ref)) < 1e-6


def test_change_share_gives_a_skins_changed_pixels_their_share():
    """Two examples of one skin whose mean contact changes 18 of 128 pixels, 2 and 16 of 64
    changed, a confident copy of the reference: at s = 0.5 both examples' changed pixels weigh
    w = (1 - 18/128) / (18/128) ~ 6.1 (the skin's, not each example's own); a skin that never
    changes gets one changed pixel's weight, not a division by 0; s = 0 is the plain loss."""
    ref, target, copy, wrong, dice = light_and_heavy()
    c = torch.full((2,), 18 / 128)
    w = (1 - 18 / 128) / (18 / 128)
    expect = (w * 2 * wrong / (62 + 2 * w) + w * 16 * wrong / (48 + 16 * w)) / 2 + dice
    assert float(loss_fn(copy, target, ref, 0.5, c)) == pytest.approx(expect, rel=1e-3)
    assert float(loss_fn(copy, target, ref, 0.5, c)) > 2 * float(loss_fn(copy, target))   # the copy pays more
    # s = 0.1 on a skin that changes 12% of its pixels: w = max(1, 0.81) = 1, the plain BCE
    assert float(loss_fn(copy, target, ref, 0.1, torch.full((2,), 0.12))) == pytest.approx(
        float(loss_fn(copy, target)), rel=1e-6)
    assert float(loss_fn(copy, target, ref, 0.0, c)) == float(loss_fn(copy, target))
    zero = float(loss_fn(copy, ref, ref, 0.5, torch.zeros(2)))
    assert np.isfinite(zero) and zero == pytest.approx(float(loss_fn(copy, ref)), rel=1e-6)


def test_pair_batches_know_each_skins_changed_fraction_and_the_last_targets():
    """Skin 0's frames change 2 and 16 of 64 pixels (mean 18/128), skin 1's none; last_b names
    each example's target skin: skin 1's targets are its 4-pixel reference, skin 0's have 6 or 20."""
    ref = np.zeros((8, 8), np.uint8)
    ref[2:4, 2:4] = 255
    light, heavy = ref.copy(), ref.copy()
    light[2:4, 4] = 255
    heavy[4:6, 0:8] = 255
    batches = PairBatches(np.stack([np.stack([light, heavy]), np.stack([ref, ref])]), np.stack([ref, ref]), seed=0)
    np.testing.assert_allclose(batches.changed_fraction, [18 / 128, 0.0])
    _, target = batches(64)
    from_skin1 = (target.sum((1, 2, 3)) == 4).numpy()
    assert 0 < from_skin1.sum() < 64
    np.testing.assert_array_equal(batches.last_b, from_skin1.astype(int))


def test_fit_weighs_changed_pixels_only_when_given_a_change_share(monkeypatch):
    """With a change share, fit hands loss_fn the target reference (the condition's third
    channel), the share and the target skins' changed fractions; without, the plain loss."""
    from stages.m2m import fit as m2m_fit
    from stages.m2m import train
    seen = []
    real = train.loss_fn

    def spy(logits, target, *args):
        seen.append(args)
        return real(logits, target, *args)
    monkeypatch.setattr(train, "loss_fn", spy)
    cfg, net, batches = _fit_setup()
    train.fit(net, cfg, batches, steps=2, batch_size=4, lr=1e-3, seed=0, change_share=m2m_fit.CHANGE_SHARE)
    assert len(seen) == 2 and all(a[1] == 0.1 for a in seen)
    ref, frac = seen[-1][0], seen[-1][2]
    assert set(torch.unique(ref).tolist()) <= {0.0, 1.0} and ref.shape == (4, 1, *batches.images.shape[2:])
    np.testing.assert_allclose(frac.numpy(), batches.changed_fraction[batches.last_b])
    seen.clear()
    train.fit(net, cfg, batches, steps=1, batch_size=4, lr=1e-3, seed=0)
    assert seen == [()]


def test_pair_batches_draw_targets_evenly_and_never_the_source():
    """Skin i's reference marks line i, so the reference channels of a batch tell which skin was
    the source (channel 1) and which the target (channel 2); 4000 draws land within 2% of even."""
    s, size = 4, 8
    levels = np.array([0, 255, 0, 255], np.uint8)       # binary skins: tell them by their reference
    images = np.repeat(levels[:, None, None, None], 3, 1).repeat(size, 2).repeat(size, 3)
    refs = np.zeros((s, size, size), np.uint8)
    for i in range(s):
        refs[i, i, :] = 255                             # row i marks skin i
    cond, _ = PairBatches(images, refs, seed=0)(4000)

    def skin(channel):
        """The marked line of each reference: a full row, or a full column after a transpose;
        a flip maps line i to size-1-i."""
        ref = cond[:, channel].numpy() > 0
        rows, cols = ref.all(2), ref.all(1)
        line = np.where(rows.any(1), rows.argmax(1), cols.argmax(1))
        return np.minimum(line, size - 1 - line)

    target, source = skin(2), skin(1)
    np.testing.assert_allclose(np.bincount(target, minlength=s) / 4000, np.full(s, 0.25), atol=0.02)
    assert (target != source).all()


def test_the_logits_are_a_residual_on_the_target_reference():
    """With the network's own output zeroed, the translation is the target reference, whatever
    the source shows; a model's weights with a parameter the net does not have do not load."""
    cfg = default_config(size=(32, 32), width=8, timesteps=50)
    net = build(cfg)
    with torch.no_grad():
        net.out.weight.zero_()
        net.out.bias.zero_()
    weights = state_arrays(net)
    ref, other = np.zeros((32, 32), np.uint8), np.zeros((32, 32), np.uint8)
    ref[4::8, 4::8] = ref[5::8, 4::8] = 255                     # 16 two-pixel markers
    other[2::8, 6::8] = other[2::8, 7::8] = 255                 # elsewhere
    moved = np.roll(ref, 1, axis=1)[None]                       # every marker one pixel right
    t = Translator(cfg, weights)
    np.testing.assert_array_equal(t.translate(moved, ref, ref), ref[None])
    np.testing.assert_array_equal(t.translate(moved, ref, other), other[None])
    with pytest.raises(KeyError, match="do not fit"):
        build(cfg, {**weights, "gate_at": np.float32(0.75)})


class _Stop(Exception):
    pass


def _fit_setup():
    imgs = _images(12, size=16).reshape(3, 4, 16, 16)
    refs = _images(3, size=16, seed=3)
    cfg = default_config(size=(16, 16), width=8, timesteps=50)
    torch.manual_seed(0)
    return cfg, build(cfg), PairBatches(imgs, refs, seed=5)


def test_fit_resumed_from_a_checkpoint_ends_where_an_uninterrupted_fit_does(tmp_path):
    """A fit killed after step 4 (a checkpoint saved at every step's end) and run again resumes
    at step 4 and gives the uninterrupted fit's weights and losses bit for bit; the loss at
    the step after the resume differs from the first step's, so the resume did not restart."""
    kw = dict(steps=9, batch_size=4, lr=1e-3, seed=2)
    cfg, whole_net, batches = _fit_setup()
    whole = fit(whole_net, cfg, batches, **kw)
    path = str(tmp_path / "m2m.ckpt")

    cfg, net, batches = _fit_setup()
    calls = {"n": 0}

    def dying(b):                            # the machine is lost while drawing step 5's batch
        calls["n"] += 1
        if calls["n"] == 5:
            raise _Stop
        return batches(b)
    dying.state, dying.restore = batches.state, batches.restore
    with pytest.raises(_Stop):
        fit(net, cfg, dying, checkpoint=path, checkpoint_every_s=0.0, **kw)
    assert torch.load(path, weights_only=True)["step"] == 4

    cfg, net, batches = _fit_setup()
    again = fit(net, cfg, batches, checkpoint=path, checkpoint_every_s=0.0, **kw)
    assert again["resumed_at"] == 4 and whole["resumed_at"] == 0
    np.testing.assert_array_equal(again["loss"], whole["loss"])
    assert whole["loss"][4] != whole["loss"][0]
    ref = state_arrays(whole_net)
    for name, value in state_arrays(net).items():
        np.testing.assert_array_equal(value, ref[name], err_msg=name)


def test_an_unreadable_or_foreign_checkpoint_is_set_aside_and_training_starts_over(tmp_path):
    path = tmp_path / "m2m.ckpt"
    path.write_bytes(b"\x80\x02 truncated")
    cfg, net, batches = _fit_setup()
    with pytest.warns(UserWarning, match=r"m2m.ckpt set aside as .bad and training starts over"):
        out = fit(net, cfg, batches, steps=3, batch_size=4, lr=1e-3, seed=2, checkpoint=str(path))
    assert out["resumed_at"] == 0 and not path.exists()
    assert (tmp_path / "m2m.ckpt.bad").read_bytes() == b"\x80\x02 truncated"

    cfg, net, batches = _fit_setup()     # a checkpoint of a 9-step fit does not serve a 12-step one
    fit(net, cfg, batches, steps=9, batch_size=4, lr=1e-3, seed=2, checkpoint=str(path),
        checkpoint_every_s=0.0)
    cfg, net, batches = _fit_setup()
    with pytest.warns(UserWarning, match=r"saved for 9 steps of 4, not 12 of 4"):
        out = fit(net, cfg, batches, steps=12, batch_size=4, lr=1e-3, seed=2, checkpoint=str(path))
    assert out["resumed_at"] == 0
