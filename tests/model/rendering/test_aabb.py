"""Ray-box intersection on axis-parallel rays, signed zeros, origins inside and misses."""

import pytest
import torch

from visnerf.rendering import aabb
from visnerf.rendering.aabb import intersect_aabb

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def test_aabb_axis_parallel_rays_with_signed_zero():
    o = torch.tensor([[0.0, 0.0, -3.0], [0.0, 0.0, -3.0], [2.0, 0.0, -3.0], [1.0, 0.0, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [-0.0, -0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    tn, tf, hit = intersect_aabb(o, d, BOX)
    assert hit.tolist() == [True, True, False, True]  # the last grazes the face x = 1 exactly
    assert torch.allclose(tn[:2], torch.tensor([2.0, 2.0])) and torch.allclose(tf[:2], torch.tensor([4.0, 4.0]))
    assert torch.isfinite(tn).all() and torch.isfinite(tf).all()


def test_aabb_origin_inside_and_miss():
    o = torch.tensor([[0.0, 0.0, 0.0], [0.0, 5.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    tn, tf, hit = intersect_aabb(o, d, BOX)
    assert hit.tolist() == [True, False]
    assert float(tn[0]) == 0.0 and abs(float(tf[0]) - 1.0) < 1e-6


def _hard_rays(n: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Random rays with every hard case mixed in: zero and negative-zero components, origins on
    a face and inside, directions parallel to faces, tiny and huge components, NaN and infinity."""
    g = torch.Generator().manual_seed(11)
    o = (torch.rand(n, 3, generator=g, dtype=torch.float64) * 6 - 3).to(dtype)
    d = torch.randn(n, 3, generator=g, dtype=torch.float64).to(dtype)
    pick = torch.rand(n, 3, generator=g)
    d = torch.where(pick < 0.15, torch.zeros_like(d), d)
    d = torch.where((pick >= 0.15) & (pick < 0.25), torch.full_like(d, -0.0), d)
    d = torch.where((pick >= 0.25) & (pick < 0.3), d * 1e-30, d)
    o = torch.where((pick >= 0.3) & (pick < 0.4), torch.ones_like(o), o)  # on the face x, y or z = 1
    o = torch.where((pick >= 0.4) & (pick < 0.45), o * 0.1, o)
    o[:3] = torch.tensor([float("nan"), 0.0, 0.0], dtype=dtype)
    d[3:6] = torch.tensor([float("nan"), 1.0, 0.0], dtype=dtype)
    d[6:9] = torch.tensor([float("inf"), 0.0, 1.0], dtype=dtype)
    o[9:12] = torch.tensor([float("-inf"), 0.0, 0.0], dtype=dtype)
    return o.contiguous(), d.contiguous()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("near", [0.0, 0.7])
def test_the_compiled_loop_is_the_torch_twin_bit_for_bit(dtype: torch.dtype, near: float) -> None:
    o, d = _hard_rays(20_000, dtype)
    box = torch.tensor([[-1.0, -0.5, -2.0], [1.0, 1.0, 0.25]])
    assert aabb._compiled_serves(o, d, box)
    one_origin = o[20:21].expand(o.shape[0], 3)  # a camera's origin for every ray: stride 0
    for rays_o, rays_d in ((o, d), (one_origin, d), (o.t().contiguous().t(), d.t().contiguous().t())):
        fast = intersect_aabb(rays_o, rays_d, box, near)
        slow = aabb.intersect_aabb_torch(rays_o, rays_d, box, near)
        for a, b in zip(fast, slow, strict=True):
            assert a.dtype == b.dtype and a.shape == b.shape
            assert torch.equal(a, b)
        assert bool(fast[2].any()) and not bool(fast[2].all())


def test_rays_the_loop_does_not_take_go_to_the_torch_twin() -> None:
    o, d = _hard_rays(50, torch.float32)
    box = BOX
    assert not aabb._compiled_serves(o[:, :2], d[:, :2], box)  # not three components
    assert not aabb._compiled_serves(o.double(), d, box)  # two float types
    assert not aabb._compiled_serves(o.half(), d.half(), box)
    with torch.enable_grad():
        assert not aabb._compiled_serves(o.requires_grad_(True), d, box)
