"""Compositing against closed forms: weights, transmittance, opacity, stiff cases."""

import math

import numpy as np
import pytest
import torch

from visnerf.rendering.volume import render_transmittance_from_density, render_weight_from_density


def test_piecewise_constant_compositing_is_exact():
    # sigma = [1, 2, 0.5], delta = [0.1, 0.2, 0.4]: tau = [0.1, 0.4, 0.2]
    # T = [1, e^-0.1, e^-0.5], alpha = 1 - e^-tau, T_final = e^-0.7
    sig = torch.tensor([[1.0, 2.0, 0.5]], dtype=torch.float64)
    dl = torch.tensor([[0.1, 0.2, 0.4]], dtype=torch.float64)
    w, t, a = render_weight_from_density(sig, dl)
    assert torch.allclose(t, torch.tensor([[1.0, math.exp(-0.1), math.exp(-0.5)]], dtype=torch.float64), atol=1e-12)
    assert abs(float(w.sum()) - (1 - math.exp(-0.7))) < 1e-6
    colors = torch.tensor([[[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]], dtype=torch.float64)
    rgb = (w[..., None] * colors).sum(1)
    expected = [1 - math.exp(-0.1), math.exp(-0.1) * (1 - math.exp(-0.4)), math.exp(-0.5) * (1 - math.exp(-0.2))]
    assert np.allclose(rgb[0].numpy(), expected, atol=1e-6)


def test_constant_density_opacity_closed_form():
    sigma, length, n = 3.0, 0.7, 1000
    sig = torch.full((1, n), sigma, dtype=torch.float64)
    dl = torch.full((1, n), length / n, dtype=torch.float64)
    w, _, _ = render_weight_from_density(sig, dl)
    assert abs(float(w.sum()) - (1 - math.exp(-sigma * length))) < 1e-9


@pytest.mark.parametrize("sigma", [0.0, 1e4, 1e6])
def test_stiff_cases_are_finite_with_finite_gradients(sigma):
    sig = torch.full((2, 8), sigma, dtype=torch.float32, requires_grad=True)
    dl = torch.full((2, 8), 1.0)
    w, t, _ = render_weight_from_density(sig, dl)
    (w.sum() + t.sum()).backward()
    assert torch.isfinite(w).all() and torch.isfinite(sig.grad).all()
    assert float(w.sum(-1).max()) <= 1.0 + 1e-6


def test_single_opaque_sample_takes_everything():
    sig = torch.tensor([[0.0, 1e5, 0.0]])
    w, _, _ = render_weight_from_density(sig, torch.ones(1, 3))
    assert torch.allclose(w, torch.tensor([[0.0, 1.0, 0.0]]))


def test_transmittance_non_increasing():
    sig = torch.rand(16, 64) * 5
    t = render_transmittance_from_density(sig, torch.full((16, 64), 0.05))
    assert (t[:, 1:] <= t[:, :-1] + 1e-7).all()


def test_weights_of_segments_equal_the_whole_ray_and_never_exceed_one():
    """The renderers composite a ray segment by segment, carrying the optical depth before each:
    the weights must be the whole ray's, against a float64 reference, for optical depths from
    1e-8 to 1e8 per sample."""
    from visnerf.rendering.volume import weights_from_optical_depth

    g = torch.Generator().manual_seed(0)
    tau = torch.rand(32, 48, generator=g) * 10.0 ** torch.randint(-8, 9, (32, 48), generator=g).float()
    whole = weights_from_optical_depth(tau)
    parts, before = [], torch.zeros(32)
    for start in range(0, 48, 16):
        seg = tau[:, start:start + 16]
        parts.append(weights_from_optical_depth(seg, before))
        before = before + seg.sum(-1)
    assert torch.allclose(torch.cat(parts, dim=1), whole, atol=1e-6)
    t64 = tau.double()
    ref = torch.exp(-(torch.cumsum(t64, -1) - t64)) * -torch.expm1(-t64)
    assert torch.allclose(whole.double(), ref, atol=1e-6)
    assert float(whole.sum(-1).max()) <= 1.0 + 1e-6 and bool((whole >= 0).all())
