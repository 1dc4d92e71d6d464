"""The trainer's Adam against the closed form of its first two steps, fused (CPU, CUDA) or not.

From a zero state, Adam's bias-corrected moments after step 1 are ``m = g`` and ``v = g^2``, so
each parameter moves by ``-lr * g / (|g| + eps)``; after a second step with gradient ``h`` the move
is the same recurrence once more (written out in ``_adam_closed_form``)."""

import math

import pytest
import torch

from visnerf.config import TrainConfig
from visnerf.testing import make_tiny_field
from visnerf.training.step import FUSED_ADAM_DEVICES, make_optimizer


def _adam_closed_form(p0: torch.Tensor, grads: list[torch.Tensor], lr: float, betas: tuple[float, float],
                      eps: float) -> torch.Tensor:
    """Adam written out in float64, one line per quantity, for the given gradients in turn."""
    b1, b2 = betas
    p, m, v = p0.double().clone(), torch.zeros_like(p0, dtype=torch.float64), torch.zeros_like(p0, dtype=torch.float64)
    for t, g in enumerate(grads, start=1):
        g = g.double()
        m = b1 * m + (1 - b1) * g
        v = b2 * v + (1 - b2) * g * g
        m_hat, v_hat = m / (1 - b1 ** t), v / (1 - b2 ** t)
        p = p - lr * m_hat / (v_hat.sqrt() + eps)
    return p


@pytest.mark.parametrize("scale", [1.0, 0.3])
def test_two_steps_match_the_closed_form(scale: float) -> None:
    field, _ = make_tiny_field([("t", [0.0, 1.0])], seed=3, resolution=8)
    cfg = TrainConfig()
    opt = make_optimizer(field, cfg, scale)
    assert opt.defaults["fused"] is (field.device.type in FUSED_ADAM_DEVICES)
    params = [p for g in opt.param_groups for p in g["params"]]
    lrs = [g["lr"] for g in opt.param_groups for _ in g["params"]]
    assert math.isclose(opt.param_groups[0]["lr"], cfg.lr_factors * scale)
    assert math.isclose(opt.param_groups[1]["lr"], cfg.lr_networks * scale)
    gen = torch.Generator().manual_seed(0)
    grads = [[torch.randn(p.shape, generator=gen) for p in params] for _ in range(2)]
    start = [p.detach().clone() for p in params]
    for step_grads in grads:
        for p, g in zip(params, step_grads, strict=True):
            p.grad = g.clone()
        opt.step()
    eps = opt.defaults["eps"]
    for i, (p, p0, lr) in enumerate(zip(params, start, lrs, strict=True)):
        expected = _adam_closed_form(p0, [grads[0][i], grads[1][i]], lr, cfg.betas, eps)
        assert torch.allclose(p.detach().double(), expected, rtol=0, atol=1e-6), i
        assert not torch.equal(p.detach(), p0)  # it moved: the check above is not of an idle optimizer
