"""The compiled segment loops of the inference march (``march_kernel``) against the torch
operations they replace, and whole frames marched both ways."""

import math

import pytest
import torch

from visnerf.data.cameras import Intrinsics, orbit_c2w
from visnerf.rendering import march_kernel
from visnerf.rendering.aabb import intersect_aabb
from visnerf.rendering.empty_space import EmptySpace
from visnerf.rendering.render_settings import RenderSettings
from visnerf.rendering.renderer import render_image
from visnerf.rendering.volume import weights_from_optical_depth
from visnerf.testing import make_tiny_field

pytestmark = pytest.mark.skipif(not march_kernel.available(torch.device("cpu")), reason="numba is not installed")


def _rays(n: int, seed: int, aabb: torch.Tensor):
    g = torch.Generator().manual_seed(seed)
    rays_o = torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, -2.0])
    rays_d = torch.nn.functional.normalize((torch.rand(n, 3, generator=g) - 0.5) - rays_o, dim=-1)
    t_near, t_far, hit = intersect_aabb(rays_o, rays_d, aabb)
    return rays_o, rays_d, t_near, t_far, hit, g


@pytest.mark.parametrize("with_grid,occupied,step", [(True, 0.3, 0.031), (False, 0.3, 0.031), (True, 0.01, 0.004),
                                                   (True, 0.002, 0.011), (True, 0.0, 0.02)])
def test_placed_samples_are_the_valid_lattice_samples_in_order(with_grid: bool, occupied: float, step: float) -> None:
    """Every lattice sample of the window in an occupied cell, and no other: with dense grids,
    sparse ones (long empty runs between occupied cells, with steps a fraction of a cell) and an
    empty one."""
    aabb = torch.tensor([[-0.5, -0.4, -0.6], [0.5, 0.4, 0.6]])
    rays_o, rays_d, t_near, t_far, hit, g = _rays(500, 0, aabb)
    first = torch.randint(0, 8, (500,), generator=g)
    last = torch.where(hit, first + torch.randint(-2, round(1.9 / step), (500,), generator=g), -1)
    grid = torch.rand(20, 16, 24, generator=g) < occupied
    space = EmptySpace.of(grid, aabb)
    occupancy = space.tables(space.occupied).arrays()
    for s0, seg in ((0, 16), (16, 32), (20, 7), (0, 400)):
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
        assert (expected_flat.numel() > 0) == (occupied > 0 or not with_grid)
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


def test_accumulated_colours_equal_index_add() -> None:
    g = torch.Generator().manual_seed(3)
    n, m, k = 40, 500, 300
    weights = torch.rand(m, generator=g)
    shade = torch.randperm(m, generator=g)[:k].sort().values
    ray_idx = torch.randint(0, n, (k,), generator=g)  # rays repeat: sums of several samples
    colors = torch.rand(k, 3, generator=g)
    start = torch.rand(n, 4, generator=g)
    got = start.clone()
    march_kernel.accumulate(got, ray_idx, weights, shade, colors)
    shaded = weights.index_select(0, shade)[:, None]
    expected = start.clone().index_add_(0, ray_idx, torch.cat([shaded * colors, shaded], dim=1))
    assert torch.allclose(got, expected, rtol=1e-6, atol=1e-7)
    untouched = got.clone()
    march_kernel.accumulate(got, ray_idx[:0], weights, shade[:0], colors[:0])
    assert torch.equal(got, untouched)


def test_accumulate_refuses_mismatched_or_foreign_arrays_and_changes_nothing() -> None:
    rgbw = torch.zeros(4, 4)
    idx, w, colors = torch.tensor([0, 1]), torch.ones(3), torch.ones(2, 3)
    with pytest.raises(ValueError, match="differ"):
        march_kernel.accumulate(rgbw, idx, w, torch.tensor([0]), colors)
    with pytest.raises(ValueError, match="float32"):
        march_kernel.accumulate(rgbw.double(), idx, w, torch.tensor([0, 2]), colors)
    with pytest.raises(ValueError, match="contiguous"):
        march_kernel.accumulate(torch.zeros(4, 8)[:, ::2], idx, w, torch.tensor([0, 2]), colors)
    assert torch.equal(rgbw, torch.zeros(4, 4))


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
