"""Fixtures shared by the rendering tests."""

from dataclasses import dataclass

import pytest
import torch
import torch.nn.functional as F
from torch import Tensor


@pytest.fixture()
def two_threads():
    """Two torch threads for the test (the suite runs on one), as the threaded chunk renderer uses."""
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


@dataclass(frozen=True)
class RayBatch:
    """Rays from z = -3 towards +z, spread over a tiny field's box, with one parameter each."""

    rays_o: Tensor  # [n, 3]
    rays_d: Tensor  # [n, 3] unit
    params: Tensor  # [n, 1] in [-1, 1]
    background: Tensor  # [n, 3] white

    def render_with_gradients(self, field, step: float, weight_threshold: float,
                              **options) -> tuple[Tensor, dict[str, Tensor]]:
        """``render_rays`` of these rays (``options``: its sampling of gradients or colours), and the
        gradient of the sum of the squared colours for each of ``field``'s parameters that gets one."""
        from visnerf.rendering.training_render import render_rays

        field.zero_grad(set_to_none=True)
        out = render_rays(field, self.rays_o, self.rays_d, self.params, self.background, step, 512, None,
                          weight_threshold, torch.Generator().manual_seed(1), **options)
        out["rgb"].square().sum().backward()
        return out["rgb"].detach(), {k: p.grad.clone() for k, p in field.named_parameters() if p.grad is not None}


def rays_through_box(n: int, seed: int = 0) -> RayBatch:
    gen = torch.Generator().manual_seed(seed)
    rays_o = torch.tensor([[0.0, 0.0, -3.0]]).repeat(n, 1) + 0.3 * (torch.rand(n, 3, generator=gen) - 0.5)
    rays_d = F.normalize(torch.tensor([[0.0, 0.0, 1.0]]).repeat(n, 1) + 0.2 * (torch.rand(n, 3, generator=gen) - 0.5),
                         dim=-1)
    params = torch.rand(n, 1, generator=gen) * 2 - 1
    return RayBatch(rays_o, rays_d, params, torch.ones(n, 3))


@pytest.fixture()
def box_rays():
    """``rays_through_box``: ``box_rays(n)`` gives ``n`` rays through a tiny field's box."""
    return rays_through_box
