"""Densities whose backward pass samples the near-empty samples (``rendering.density_gradients``)."""

import dataclasses

import pytest
import torch
import torch.nn.functional as F

from visnerf.config import TrainConfig
from visnerf.rendering.density_gradients import DensityGradientSampling, density_with_sampled_gradients
from visnerf.testing import make_tiny_field


def _per_sample_density(theta):
    """A density with one parameter per sample: point ``i`` carries ``i`` in its first coordinate,
    so sample ``i``'s gradient lands in ``theta[i]`` alone."""

    def density(points, q):
        return F.softplus(theta[points[:, 0].long()]) * q[:, 0]

    return density


def test_values_are_the_density_and_each_traced_gradient_is_its_own_times_its_gain():
    m, keep, floor = 4000, 0.25, 1e-3
    theta = torch.full((m,), -12.0, dtype=torch.float64)
    theta[::10] = 2.0  # every tenth sample holds content
    theta.requires_grad_(True)
    points = torch.zeros(m, 3, dtype=torch.float64)
    points[:, 0] = torch.arange(m, dtype=torch.float64)
    q = torch.ones(m, 1, dtype=torch.float64)
    deltas = torch.full((m,), 0.01, dtype=torch.float64)
    weights = torch.rand(m, dtype=torch.float64) + 0.5  # the loss's weight of each sample
    density = _per_sample_density(theta)
    sampling = DensityGradientSampling(floor, keep, torch.Generator().manual_seed(3))
    sigma = density_with_sampled_gradients(density, points, q, deltas, sampling)
    assert torch.equal(sigma.detach(), density(points, q).detach())
    (grad,) = torch.autograd.grad((weights * sigma).sum(), theta)
    full = weights * torch.sigmoid(theta.detach())  # d/dtheta_i of weights_i * softplus(theta_i)
    low = (-torch.expm1(-F.softplus(theta.detach()) * deltas)) < floor
    assert not bool(low[::10].any()) and bool(low[1::10].all())
    traced = grad != 0
    # Content is always traced, exactly; a near-empty sample is traced with gain 1 / keep, or not at all.
    assert torch.allclose(grad[~low], full[~low], rtol=1e-12, atol=0)
    assert torch.allclose(grad[low & traced], full[low & traced] / keep, rtol=1e-12, atol=0)
    # Each near-empty sample is traced with probability ``keep``: 3600 draws, 4 standard deviations.
    fraction = float(traced[low].double().mean())
    assert abs(fraction - keep) < 4 * (keep * (1 - keep) / int(low.sum())) ** 0.5


def test_the_mean_gradient_over_draws_is_the_full_gradient():
    """Unbiased: the mean over 4000 draws of the sampled gradient of four near-empty samples and
    one solid one, against the full gradient (each mean's standard error is 1.6 %)."""
    theta = torch.tensor([-9.0, -10.0, -11.0, -9.5, 1.0], dtype=torch.float64, requires_grad=True)
    points = torch.zeros(5, 3, dtype=torch.float64)
    points[:, 0] = torch.arange(5, dtype=torch.float64)
    q, deltas = torch.ones(5, 1, dtype=torch.float64), torch.full((5,), 0.1, dtype=torch.float64)
    density = _per_sample_density(theta)
    sampling = DensityGradientSampling(1e-3, 0.5, torch.Generator().manual_seed(0))
    total = torch.zeros(5, dtype=torch.float64)
    draws = 4000
    for _ in range(draws):
        sigma = density_with_sampled_gradients(density, points, q, deltas, sampling)
        total += torch.autograd.grad(sigma.sum(), theta)[0]
    full = torch.sigmoid(theta.detach())
    assert torch.allclose(total / draws, full, rtol=0.06)
    assert float(total[4] / draws) == pytest.approx(float(full[4]), rel=1e-12)  # the solid sample: exact


def test_keep_one_or_no_grad_is_the_plain_call():
    calls = []

    def density(points, q):
        calls.append(torch.is_grad_enabled())
        return points[:, 0] * q[:, 0]

    pts, q, d = torch.rand(7, 3, requires_grad=True), torch.ones(7, 1), torch.full((7,), 0.1)
    out = density_with_sampled_gradients(density, pts, q, d, DensityGradientSampling(1e-4, 1.0, torch.Generator()))
    assert calls == [True] and out.requires_grad
    with torch.no_grad():
        density_with_sampled_gradients(density, pts, q, d, DensityGradientSampling(1e-4, 0.5, torch.Generator()))
    assert calls == [True, False]
    with pytest.raises(ValueError, match="keep"):
        density_with_sampled_gradients(density, pts, q, d, DensityGradientSampling(1e-4, 0.0, torch.Generator()))


def test_render_rays_with_sampled_density_gradients(box_rays):
    """Same colours; keep = 1 gives the plain gradients; keep < 1 traces fewer samples yet every
    factor the solid samples read still gets a finite gradient."""
    field, _ = make_tiny_field([("a", [0.0, 1.0])], resolution=12)
    rays = box_rays(64)
    step = field.voxel_size() * 0.5

    def run(sampling):
        return rays.render_with_gradients(field, step, 1e-4, density_grads=sampling)

    plain_rgb, plain = run(None)
    one_rgb, one = run(DensityGradientSampling(1e-4, 1.0, torch.Generator().manual_seed(2)))
    assert torch.equal(one_rgb, plain_rgb)
    assert all(torch.equal(one[n], plain[n]) for n in plain)
    with torch.no_grad():  # make part of the box near-empty: the density shift is a plain bias
        field.density_decoder.out.bias -= 9.0
    plain_rgb, plain = run(None)
    some_rgb, some = run(DensityGradientSampling(0.05, 0.25, torch.Generator().manual_seed(2)))
    assert torch.allclose(some_rgb, plain_rgb, atol=1e-6)
    assert set(some) == set(plain)
    assert all(bool(torch.isfinite(g).all()) for g in some.values())
    assert any(not torch.equal(some[n], plain[n]) for n in plain)  # the draw left samples out


def test_train_config_refuses_bad_sampling_settings():
    with pytest.raises(ValueError, match="density_grad_keep"):
        dataclasses.replace(TrainConfig(), density_grad_keep=0.0)
    with pytest.raises(ValueError, match="density_grad_floor"):
        dataclasses.replace(TrainConfig(), density_grad_floor=-1e-3)
