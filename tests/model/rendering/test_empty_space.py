"""Jumping over empty space: distances against a brute-force reference, sample windows against
testing every lattice sample, and frames with jumps against frames without."""

import itertools
import math

import pytest
import torch

from visnerf.data.cameras import Intrinsics, image_rays, orbit_c2w
from visnerf.rendering import empty_space_kernel
from visnerf.rendering.aabb import intersect_aabb
from visnerf.rendering.empty_space import EmptySpace, distance_to_content
from visnerf.rendering.render_settings import RenderSettings
from visnerf.rendering.renderer import march_rays, ray_windows
from visnerf.representation.frame_field import FrameField
from visnerf.testing import make_tiny_field


def _blobs(shape: tuple[int, int, int], n: int, seed: int) -> torch.Tensor:
    """A few occupied boxes in an empty grid."""
    g = torch.Generator().manual_seed(seed)
    grid = torch.zeros(shape, dtype=torch.bool)
    for _ in range(n):
        lo = [int(torch.randint(0, s - 1, (1,), generator=g)) for s in shape]
        size = [int(torch.randint(1, 4, (1,), generator=g)) for _ in shape]
        grid[lo[0]:lo[0] + size[0], lo[1]:lo[1] + size[1], lo[2]:lo[2] + size[2]] = True
    return grid


@pytest.fixture(params=["compiled", "torch"])
def walk(request, monkeypatch):
    """The compiled walk (the CPU's) or the batched torch walk (every other device's)."""
    if request.param == "compiled" and not empty_space_kernel.available(torch.device("cpu")):
        pytest.skip("numba is not installed")
    if request.param == "torch":
        monkeypatch.setattr(empty_space_kernel, "available", lambda device: False)
    return request.param


def test_distances_equal_the_brute_force_chebyshev_distance() -> None:
    grid = _blobs((9, 7, 11), 3, seed=0)
    cap = 5
    dist = distance_to_content(grid, cap)
    occupied = grid.nonzero().float()  # [o, 3]
    for cell in itertools.product(*(range(s) for s in grid.shape)):
        cheb = (occupied - torch.tensor(cell).float()).abs().amax(dim=1).min()
        assert int(dist[cell]) == min(int(cheb), cap), cell
    assert (distance_to_content(torch.zeros(4, 4, 4, dtype=torch.bool), cap) == cap).all()


def _every_sample_window(space: EmptySpace, rays_o, rays_d, t_near, step, first, last):
    """First and last lattice sample in an occupied cell, testing every sample."""
    n = rays_o.shape[0]
    idx = torch.arange(int(last.max()) + 1)
    t = t_near[:, None] + step * (idx[None].float() + 0.5)  # [n, s]
    inside = (idx[None] >= first[:, None]) & (idx[None] <= last[:, None])
    occ = space.occupied_at((rays_o[:, None] + rays_d[:, None] * t[..., None]).reshape(-1, 3)).reshape(n, -1) & inside
    big = idx.numel() + 10
    lo = torch.where(occ, idx[None], big).amin(dim=1)
    hi = torch.where(occ, idx[None], -1).amax(dim=1)
    return lo, hi, occ.any(dim=1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sample_windows_hold_every_occupied_sample_and_little_else(seed: int, walk: str) -> None:
    aabb = torch.tensor([[-0.5, -0.4, -0.6], [0.5, 0.4, 0.6]])
    grid = _blobs((10, 8, 12), 4, seed)
    space = EmptySpace.of(grid, aabb)
    g = torch.Generator().manual_seed(seed)
    n = 3000
    rays_o = torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, -2.0])
    target = (torch.rand(n, 3, generator=g) - 0.5) * 1.2
    rays_d = torch.nn.functional.normalize(target - rays_o, dim=-1)
    rays_d[:50, :2] = 0.0  # axis-parallel rays, including -0.0 components
    rays_d[:50, 2] = 1.0
    rays_d[50:60, 0] = -0.0
    rays_d = torch.nn.functional.normalize(rays_d, dim=-1)
    rays_o[100:120] = (torch.rand(20, 3, generator=g) - 0.5) * 0.8  # origins inside the box
    step = 0.037
    t_near, t_far, hit = intersect_aabb(rays_o, rays_d, aabb)
    count = torch.ceil((t_far - t_near) / step - 0.5 + 1e-3)
    last0 = torch.where(hit, count.long() - 1, -1)
    first0 = torch.zeros_like(last0)
    first, last = space.sample_window(rays_o, rays_d, t_near, step, first0, last0)
    lo, hi, any_occ = _every_sample_window(space, rays_o, rays_d, t_near, step, first0, last0)
    # Never cut an occupied sample: the window holds [lo, hi].
    assert (first[any_occ] <= lo[any_occ]).all() and (last[any_occ] >= hi[any_occ]).all()
    if walk == "compiled":  # its jumps never run out: the window is exactly [lo, hi], or empty
        assert torch.equal(first[any_occ], lo[any_occ]) and torch.equal(last[any_occ], hi[any_occ])
        assert (first[~any_occ] > last[~any_occ]).all()
    # Rays that meet no occupied cell walk nothing (or, if their jumps ran out, very little).
    assert (first[~any_occ] > last[~any_occ]).float().mean() > 0.95
    # And the window is tight: where there is content it is exactly [lo, hi] but for rays that
    # ran out of jumps.
    assert (first[any_occ] == lo[any_occ]).float().mean() > 0.95
    assert (last[any_occ] == hi[any_occ]).float().mean() > 0.95
    assert any_occ.float().mean() > 0.1 and (~any_occ & hit).any()  # both kinds are there


@pytest.mark.parametrize("azimuth", [10.0, 130.0])
def test_frames_with_jumps_equal_frames_walking_every_sample(azimuth: float, walk: str) -> None:
    field, _ = make_tiny_field([("a", [0.0, 1.0])], seed=4, resolution=12)
    field.eval()
    grid = _blobs((12, 12, 12), 5, seed=7)
    field.set_occupancy(grid)
    space = EmptySpace.of(grid, field.aabb)
    intr = Intrinsics.from_fov(32, 32, math.radians(40.0))
    c2w = torch.from_numpy(orbit_c2w(azimuth, 25.0, 2.0)).float()
    rays_o, rays_d = (r.reshape(-1, 3) for r in image_rays(c2w, intr))
    settings = RenderSettings(segment_samples=8)
    step = field.voxel_size() * settings.step_ratio
    with torch.inference_mode():
        q_d, q_a = field.param_features(torch.tensor([[0.4]]))
        frame = FrameField(field, q_d, q_a)
        bg = torch.ones(3)
        walked = ray_windows(field, rays_o, rays_d, step, settings.max_samples, None)
        jumped = ray_windows(field, rays_o, rays_d, step, settings.max_samples, space)
        a = march_rays(field, rays_o, rays_d, frame, bg, settings, space, walked)
        b = march_rays(field, rays_o, rays_d, frame, bg, settings, space, jumped)
    walk_len = (walked.last - walked.first + 1).clamp_min(0).sum()
    jump_len = (jumped.last - jumped.first + 1).clamp_min(0).sum()
    assert jump_len < 0.7 * walk_len  # the jumps leave samples out
    assert (a - 1.0).abs().amax() > 0.05  # and there is something in the picture
    assert float((a - b).abs().max()) < 1e-5


def test_a_window_near_content_is_the_window_of_the_grid_grown_by_one_cell(walk: str) -> None:
    aabb = torch.tensor([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]])
    grid = _blobs((12, 12, 12), 3, seed=5)
    grown = torch.nn.functional.max_pool3d(grid.float()[None, None], 3, 1, 1)[0, 0] > 0
    g = torch.Generator().manual_seed(9)
    rays_o = torch.randn(2000, 3, generator=g) * 0.3 + torch.tensor([0.2, -0.1, -2.0])
    rays_d = torch.nn.functional.normalize((torch.rand(2000, 3, generator=g) - 0.5) - rays_o, dim=-1)
    step = 0.03
    t_near, t_far, hit = intersect_aabb(rays_o, rays_d, aabb)
    last0 = torch.where(hit, torch.ceil((t_far - t_near) / step - 0.5 + 1e-3).long() - 1, -1)
    first0 = torch.zeros_like(last0)
    near = EmptySpace.of(grid, aabb).sample_window(rays_o, rays_d, t_near, step, first0, last0, near=1)
    lo, hi, any_occ = _every_sample_window(EmptySpace.of(grown, aabb), rays_o, rays_d, t_near, step, first0, last0)
    assert any_occ.float().mean() > 0.2
    assert (near[0][any_occ] <= lo[any_occ]).all() and (near[1][any_occ] >= hi[any_occ]).all()
    if walk == "compiled":
        assert torch.equal(near[0][any_occ], lo[any_occ]) and torch.equal(near[1][any_occ], hi[any_occ])
        assert (near[0][~any_occ] > near[1][~any_occ]).all()
    assert (near[0][any_occ] == lo[any_occ]).float().mean() > 0.95
    assert (near[1][any_occ] == hi[any_occ]).float().mean() > 0.95


@pytest.mark.skipif(not empty_space_kernel.available(torch.device("cpu")), reason="numba not importable")
def test_the_compiled_walk_shared_by_threads_equals_the_walk_on_one(monkeypatch) -> None:
    aabb = torch.tensor([[-0.5, -0.4, -0.6], [0.5, 0.4, 0.6]])
    space = EmptySpace.of(_blobs((10, 8, 12), 4, 3), aabb)
    g = torch.Generator().manual_seed(3)
    n = 2500
    rays_o = torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, -2.0])
    rays_d = torch.nn.functional.normalize((torch.rand(n, 3, generator=g) - 0.5) * 1.2 - rays_o, dim=-1)
    step = 0.037
    t_near, t_far, hit = intersect_aabb(rays_o, rays_d, aabb)
    last0 = torch.where(hit, torch.ceil((t_far - t_near) / step - 0.5 + 1e-3).long() - 1, -1)
    first0 = torch.zeros_like(last0)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        monkeypatch.setattr(empty_space_kernel, "RAYS_PER_PART", 10**9)
        one = space.sample_window(rays_o, rays_d, t_near, step, first0, last0)
        monkeypatch.setattr(empty_space_kernel, "RAYS_PER_PART", 7)
        monkeypatch.setattr(empty_space_kernel, "RAYS_PER_CALL", 1001)  # calls of 1001, 1001 and 498 rays, two parts each
        shared = space.sample_window(rays_o, rays_d, t_near, step, first0, last0)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(one[0], shared[0]) and torch.equal(one[1], shared[1])
    assert (one[0] <= one[1]).any() and (one[0] > one[1]).any()
