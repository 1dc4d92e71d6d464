"""Colour at light samples drawn at random for training (``rendering.colour_sampling``)."""

import dataclasses

import pytest
import torch

from visnerf.config import TrainConfig
from visnerf.rendering.colour_sampling import ColourSampling, pick_coloured
from visnerf.testing import make_tiny_field


def test_without_sampling_every_candidate_counts_with_its_weight():
    weights = torch.tensor([0.5, 1e-3, 0.2, 1e-5])
    candidates = torch.tensor([0, 1, 3])
    picked, counted = pick_coloured(weights, candidates, None)
    assert torch.equal(picked, candidates)
    assert torch.equal(counted, weights[candidates])


def test_heavy_samples_are_exact_and_light_ones_count_with_the_floor():
    floor, m = 0.02, 6000
    gen = torch.Generator().manual_seed(0)
    weights = torch.rand(m, generator=gen, dtype=torch.float64) * 0.01  # light: below the floor
    weights[::6] = 0.02 + torch.rand(len(weights[::6]), generator=gen, dtype=torch.float64)  # heavy
    candidates = torch.arange(m)
    picked, counted = pick_coloured(weights, candidates, ColourSampling(floor, torch.Generator().manual_seed(1)))
    heavy = weights >= floor
    chosen = torch.zeros(m, dtype=torch.bool)
    chosen[picked] = True
    assert bool(chosen[heavy].all())  # every heavy sample is coloured ...
    is_heavy = heavy[picked]
    assert torch.equal(counted[is_heavy], weights[picked][is_heavy])  # ... with its own weight
    assert torch.allclose(counted[~is_heavy], torch.full_like(counted[~is_heavy], floor), rtol=1e-12, atol=0)
    # a light sample is drawn with probability weight / floor: the count of draws, 4 standard deviations
    p = weights[~heavy] / floor
    expected, spread = float(p.sum()), float((p * (1 - p)).sum()) ** 0.5
    assert abs(int((~is_heavy).sum()) - expected) < 4 * spread


def test_the_mean_over_draws_is_the_exact_colour_sum_and_its_gradient():
    """Unbiased in value and gradient: the mean over 20000 draws of sum(w_i c_i) over a ray of six
    light samples and one heavy one, and of its gradient with respect to the weights, against the
    exact sum and the colours (closed forms)."""
    floor = 0.05
    weights = torch.tensor([0.004, 0.01, 0.02, 0.03, 0.045, 0.001, 0.3], dtype=torch.float64, requires_grad=True)
    colours = torch.tensor([0.9, 0.1, 0.5, 0.7, 0.3, 1.0, 0.6], dtype=torch.float64)
    sampling = ColourSampling(floor, torch.Generator().manual_seed(5))
    candidates = torch.arange(7)
    draws, total, grad_total = 20000, 0.0, torch.zeros(7, dtype=torch.float64)
    for _ in range(draws):
        picked, counted = pick_coloured(weights, candidates, sampling)
        value = (counted * colours[picked]).sum()
        total += float(value.detach())
        grad_total += torch.autograd.grad(value, weights)[0]
    exact = float((weights.detach() * colours).sum())
    # each light sample's term has a standard deviation of at most floor * colour: 6 of them
    stderr = (6 * floor**2 / draws) ** 0.5
    assert abs(total / draws - exact) < 4 * stderr
    # a light sample's gradient is colour / p with probability p = weight / floor, else 0
    p = (weights.detach() / floor).clamp(max=1.0)
    grad_stderr = colours * ((1.0 / p - 1.0) / draws).sqrt()
    assert bool(((grad_total / draws - colours).abs() <= 4 * grad_stderr + 1e-12).all())
    assert float(grad_total[6] / draws) == pytest.approx(float(colours[6]), rel=1e-12)  # the heavy one: exact


def test_render_rays_with_colour_sampling(box_rays):
    """A floor below every weight is the exact render and gradient; a floor above most colours
    fewer samples, gives finite gradients and a render whose mean over draws is the exact one."""
    field, _ = make_tiny_field([("a", [0.0, 1.0])], resolution=12)
    rays = box_rays(48)
    step = field.voxel_size() * 0.5
    with torch.no_grad():  # a faint fog: every sample light
        field.density_decoder.out.bias -= 4.0

    def run(sampling):
        return rays.render_with_gradients(field, step, 1e-6, colour_sampling=sampling)

    plain_rgb, plain = run(None)
    tiny_rgb, tiny = run(ColourSampling(1e-9, torch.Generator().manual_seed(2)))
    assert torch.equal(tiny_rgb, plain_rgb)
    assert all(torch.equal(tiny[k], plain[k]) for k in plain)
    sampling = ColourSampling(0.2, torch.Generator().manual_seed(3))
    some_rgb, some = run(sampling)
    assert not torch.equal(some_rgb, plain_rgb)  # the draw left samples out
    assert set(some) == set(plain) and all(bool(torch.isfinite(g).all()) for g in some.values())
    mean = torch.stack([run(sampling)[0] for _ in range(200)]).mean(0)
    assert float((mean - plain_rgb).abs().mean()) < 0.25 * float((some_rgb - plain_rgb).abs().mean())


def test_bad_floors_are_refused():
    with pytest.raises(ValueError, match="floor"):
        ColourSampling(0.0, torch.Generator())
    with pytest.raises(ValueError, match="floor"):
        ColourSampling(1.0, torch.Generator())
    with pytest.raises(ValueError, match="colour_weight_floor"):
        dataclasses.replace(TrainConfig(), colour_weight_floor=-0.1)
    with pytest.raises(ValueError, match="colour_weight_floor"):
        dataclasses.replace(TrainConfig(), colour_weight_floor=1.0)
