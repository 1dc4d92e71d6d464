"""Ray-box intersection on axis-parallel rays, signed zeros, origins inside and misses."""

import torch

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
