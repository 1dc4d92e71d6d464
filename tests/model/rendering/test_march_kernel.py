"""The compiled segment loops of the inference march (``march_kernel``) against the torch
operations they replace, and whole frames marched both ways."""

import math

import pytest
import torch

from visnerf.data.cameras import Intrinsics, orbit_c2w
from visnerf.rendering import march_kernel
from visnerf.rendering.aabb import intersect_aabb
from visnerf.rendering.empty_space import EmptySpace
from visnerf.rendering.renderer import RenderSettings, render_image
from visnerf.rendering.volume import weights_from_optical_depth
from visnerf.testing import make_tiny_field

pytestmark = pytest.mark.skipif(not march_kernel.available(torch.device("cpu")), reason="numba is not installed")


def _rays(n: int, seed: int, aabb: torch.Tensor):
    g = torch.Generator().manual_seed(seed)
    rays_o = torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, -2.0])
    rays_d = torch.nn.functional.normalize((torch.rand(n, 3, generator=g) - 0.5) - rays_o, dim=-1)
    t_near, t_far, hit = intersect_aabb(rays_o, rays_d, aabb)
    return rays_o, rays_d, t_near, t_far, hit, g


@pytest.mark.parametrize("with_grid", [True, False])
def test_placed_samples_are_the_valid_lattice_samples_in_order(with_grid: bool) -> None:
    aabb = torch.tensor([[-0.5, -0.4, -0.6], [0.5, 0.4, 0.6]])
    rays_o, rays_d, t_near, t_far, hit, g = _rays(500, 0, aabb)
    step = 0.031
    first = torch.randint(0, 8, (500,), generator=g)
    last = torch.where(hit, first + torch.randint(-2, 60, (500,), generator=g), -1)
    grid = torch.rand(10, 8, 12, generator=g) < 0.3
    space = EmptySpace.of(grid, aabb)
    occupancy = space.tables(space.occupied).arrays()
    for s0, seg in ((0, 16), (16, 32), (20, 7)):
        points, flat = march_kernel.place(rays_o, rays_d, t_near, t_far, first, last, s0, seg, step,
                                          occupancy if with_grid else None)
        # the torch operations of ``march_rays``
        idx = (first + s0)[:, None] + torch.arange(seg)[None]
        t = t_near[:, None] + step * (idx.float() + 0.5)
        valid = (idx <= last[:, None]) & (t < t_far[:, None])
        every = rays_o[:, None, :] + rays_d[:, None, :] * t[..., None]  # [a, s, 3]
        if with_grid:
            valid = valid & space.occupied_at(every.view(-1, 3)).view_as(valid)
        expected_flat = valid.view(-1).nonzero()[:, 0]
        assert expected_flat.numel() > 0
        assert torch.equal(flat, expected_flat)
        assert torch.equal(points, every.view(-1, 3).index_select(0, expected_flat))


def test_composited_weights_equal_the_log_space_formula() -> None:
    g = torch.Generator().manual_seed(1)
    a, seg, step = 60, 9, 0.05
    valid = torch.rand(a, seg, generator=g) < 0.6
    # transparent, ordinary and stiff (nearly opaque in one sample) densities
    sigma_all = torch.rand(a, seg, generator=g) * torch.tensor([0.01, 10.0, 1e6])[torch.randint(0, 3, (a, 1), generator=g)]
    flat = valid.view(-1).nonzero()[:, 0]
    sigma = sigma_all.view(-1).index_select(0, flat)
    tau_before = torch.rand(a, generator=g) * 3.0
    tau = tau_before.clone()
    threshold = 1e-3
    weights, shade = march_kernel.composite(flat, sigma, seg, step, tau, threshold)
    depth = torch.where(valid, sigma_all, 0.0) * step
    expected = weights_from_optical_depth(depth, tau_before).view(-1).index_select(0, flat)
    assert torch.allclose(weights, expected, rtol=1e-5, atol=1e-7)
    assert torch.allclose(tau, tau_before + depth.sum(dim=1), rtol=1e-6)
    assert torch.equal(shade, (expected > threshold).nonzero()[:, 0])
    assert torch.isfinite(weights).all() and (weights >= 0).all()
    # nothing to composite changes nothing
    untouched = tau.clone()
    w, s = march_kernel.composite(flat[:0], sigma[:0], seg, step, tau, threshold)
    assert w.numel() == s.numel() == 0 and torch.equal(tau, untouched)


@pytest.mark.parametrize("with_grid", [True, False])
@pytest.mark.parametrize("density_scale", [1.0, 1e4])
def test_frames_marched_by_the_compiled_loops_equal_the_torch_march(monkeypatch, with_grid: bool, density_scale: float) -> None:
    field, _ = make_tiny_field([("a", [0.0, 1.0])], seed=6, resolution=12)
    field.eval()
    if with_grid:
        grid = torch.zeros(12, 12, 12, dtype=torch.bool)
        grid[2:9, 3:10, 1:8] = True
        field.set_occupancy(grid)
    with torch.no_grad():
        field.density_decoder.out.bias.add_(math.log(density_scale))
    intr = Intrinsics.from_fov(40, 30, math.radians(40.0))
    c2w = torch.from_numpy(orbit_c2w(35.0, 25.0, 2.2)).float()
    settings = RenderSettings(segment_samples=16, first_segment_samples=4, weight_threshold_per_voxel=1e-4)
    params = torch.tensor([0.6])
    with torch.inference_mode():
        compiled = render_image(field, c2w, intr, params, settings)
        monkeypatch.setattr(march_kernel, "available", lambda device: False)
        plain = render_image(field, c2w, intr, params, settings)
    assert (plain - 1.0).abs().amax() > 0.05  # something is in the picture
    assert float((compiled - plain).abs().max()) < 1e-5
