"""The networks run wholly on the device their weights are on: a check of the GPU paths that
needs no GPU.  torch's `meta` device holds shapes and no data, and refuses to meet a tensor
made on the CPU, as a CUDA tensor does; a tensor the code creates without naming the device
(torch.arange(n) inside forward, say) fails here as it would on a GPU.  (The M2M network's time
embedding did until it was run on one.)"""
import pytest
import torch

from stages.force.model import ForceRegressor
from stages.m2m.model import build, default_config, sample
from stages.m2m.train import loss_fn

META = torch.device("meta")


def test_a_cpu_tensor_meeting_a_meta_one_raises():
    """The premise: on meta, a device mix-up is an error (else the tests below prove nothing)."""
    with pytest.raises(RuntimeError, match="meta"):
        torch.arange(4.0) * torch.ones(4, device=META)


def test_m2m_forward_loss_and_sampler_stay_on_the_weights_device():
    cfg = default_config(size=(32, 32), width=8, timesteps=1000)
    net = build(cfg).to(META)
    b = 2
    x_t = torch.zeros(b, 1, 32, 32, device=META)
    cond = torch.zeros(b, 3, 32, 32, device=META)
    t = torch.full((b,), 999, dtype=torch.long, device=META)
    logits = net(x_t, cond, t)
    assert logits.device == META and tuple(logits.shape) == (b, 1, 32, 32)
    loss = loss_fn(logits, torch.zeros_like(logits))
    assert loss.device == META and loss.shape == ()
    prob = sample(net, cond, cfg, steps=3)                      # the multi-step sampler too
    assert prob.device == META and tuple(prob.shape) == (b, 1, 32, 32)


def test_force_regressor_forward_and_state_stay_on_the_weights_device():
    model = ForceRegressor({"input_size": 16, "stem_channels": 4, "encoder_channels": [8], "hidden": 8,
                            "head_channels": [16, 16]}).to(META)
    x = torch.zeros(2, 5, 1, 16, 16, device=META)
    y, h = model(x)
    assert y.device == META and tuple(y.shape) == (2, 5, 3)
    y2, _ = model(x[:, :1], h)                                   # streaming: the state carried on
    assert y2.device == META and model.denormalise(y2).device == META
