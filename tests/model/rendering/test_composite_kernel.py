"""The compiled compositing of compact samples against ``rendering.volume`` through autograd, in
float64: colours, optical depths, and the gradients of the traced densities and of the colours."""

import torch

from visnerf.rendering.composite_kernel import composite, sample_weights
from visnerf.rendering.volume import weights_from_optical_depth


def _twin(sigma, traced_sigma, traced, traced_gain, colour, offsets, step, shade, gain, background):
    """Padded per-ray compositing with ``volume.weights_from_optical_depth``; the traced densities
    carry ``traced_gain`` times their gradient, the others none."""
    full = sigma.index_copy(0, traced, traced_sigma + (traced_sigma - traced_sigma.detach()) * (traced_gain - 1.0))
    out, depths = [], []
    for r in range(offsets.shape[0] - 1):
        a, b = int(offsets[r]), int(offsets[r + 1])
        tau = full[a:b] * step
        w = weights_from_optical_depth(tau[None])[0]
        c = torch.zeros(3, dtype=sigma.dtype)
        for j, s in enumerate(shade.tolist()):
            if a <= s < b:
                c = c + w[s - a] * gain[j] * colour[j]
        opacity = -torch.expm1(-tau.sum())
        out.append(c + background[r] * (1.0 - opacity))
        depths.append(tau.sum())
    return torch.stack(out), torch.stack(depths)


def test_colours_depths_and_gradients_equal_autograd_through_the_volume_functions() -> None:
    g = torch.Generator().manual_seed(0)
    dt = torch.float64
    counts = torch.tensor([3, 0, 5, 1, 7, 12])
    offsets = torch.cat([torch.zeros(1, dtype=torch.long), counts.cumsum(0)])
    m, n = int(counts.sum()), counts.shape[0]
    sigma = torch.rand(m, generator=g, dtype=dt) * 3.0
    sigma[5] = 1e4  # an opaque sample: everything behind it has weight ~0
    step = 0.37
    traced = torch.tensor([0, 2, 3, 5, 7, 8, 9, 12, 15, 20, 27])
    traced_gain = torch.rand(traced.shape[0], generator=g, dtype=dt) + 0.5
    shade = torch.tensor([1, 2, 4, 5, 6, 8, 10, 11, 14, 15, 22, 27])
    gain = torch.rand(shade.shape[0], generator=g, dtype=dt) + 0.5
    background = torch.rand(n, 3, generator=g, dtype=dt)
    colour = torch.rand(shade.shape[0], 3, generator=g, dtype=dt, requires_grad=True)
    traced_sigma = sigma[traced].clone().requires_grad_(True)
    rgb, depth = composite(traced_sigma, colour, sigma, traced, traced_gain, offsets, step, shade, gain, background)
    colour_twin = colour.detach().clone().requires_grad_(True)
    traced_twin = traced_sigma.detach().clone().requires_grad_(True)
    expected, expected_depth = _twin(sigma, traced_twin, traced, traced_gain, colour_twin, offsets, step, shade, gain,
                                     background)
    assert torch.allclose(rgb, expected, rtol=0, atol=1e-14)
    assert torch.allclose(depth, expected_depth, rtol=1e-14, atol=0)
    assert torch.equal(rgb[1], background[1])  # a ray without samples: the background
    cotangent = torch.randn(n, 3, generator=g, dtype=dt)
    (rgb * cotangent).sum().backward()
    (expected * cotangent).sum().backward()
    assert torch.allclose(traced_sigma.grad, traced_twin.grad, rtol=0, atol=1e-13)
    assert torch.allclose(colour.grad, colour_twin.grad, rtol=1e-12, atol=1e-14)


def test_weights_are_non_negative_and_sum_to_the_opacity() -> None:
    g = torch.Generator().manual_seed(1)
    counts = torch.tensor([4, 9, 1])
    offsets = torch.cat([torch.zeros(1, dtype=torch.long), counts.cumsum(0)])
    sigma = torch.rand(int(counts.sum()), generator=g, dtype=torch.float64) * 5.0
    w = sample_weights(offsets, sigma, 0.2)
    assert bool((w >= 0).all())
    for r in range(3):
        a, b = int(offsets[r]), int(offsets[r + 1])
        # closed form: the weights of a ray sum to 1 - exp(-sum sigma * step)
        assert abs(float(w[a:b].sum()) + float(torch.expm1(-0.2 * sigma[a:b].sum()))) < 1e-14
