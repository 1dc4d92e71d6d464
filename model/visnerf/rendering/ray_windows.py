"""A ray's box interval and the window of lattice samples it walks, shared by frames and training
steps (``renderer.march_rays``, ``training.step``)."""

import weakref
from dataclasses import dataclass

import torch
from jaxtyping import Float, Int
from torch import Tensor

from visnerf.rendering.aabb import intersect_aabb
from visnerf.rendering.cancel import CancelCheck
from visnerf.rendering.empty_space import EmptySpace
from visnerf.representation.field import VisNerfField

_EMPTY_SPACE: "weakref.WeakKeyDictionary[VisNerfField, tuple[Tensor, EmptySpace]]" = weakref.WeakKeyDictionary()


def empty_space_of(field: VisNerfField) -> EmptySpace | None:
    """The field's occupancy grid with distances to content, built once per grid (cached)."""
    grid = field.occupancy
    if grid is None:
        return None
    cached = _EMPTY_SPACE.get(field)
    if cached is None or cached[0] is not grid:
        cached = (grid, EmptySpace.of(grid, field.aabb))
        _EMPTY_SPACE[field] = cached
    return cached[1]


@dataclass(frozen=True)
class RayWindows:
    """Per ray: the box interval and the window ``[first, last]`` of lattice samples
    ``t_near + step * (i + 0.5)`` to walk (``first > last``: nothing to walk)."""

    t_near: Float[Tensor, " n"]
    t_far: Float[Tensor, " n"]
    first: Int[Tensor, " n"]
    last: Int[Tensor, " n"]


def ray_windows(
    field: VisNerfField,
    rays_o: Float[Tensor, "n 3"],
    rays_d: Float[Tensor, "n 3"],
    step: float,
    max_samples: int | None,
    empty_space: EmptySpace | None,
    near: int = 0,
    cancel: CancelCheck | None = None,
) -> RayWindows:
    """Box interval of every ray and its window of lattice samples (``t_near + step * (i + 0.5)``):
    the whole lattice inside the box (at most ``max_samples`` unless None), narrowed to the span
    of the samples in occupied cells when ``empty_space`` is given (``near = 1``: within one cell
    of an occupied one, ``EmptySpace.sample_window``, which asks ``cancel`` between its jumps)."""
    t_near, t_far, hit = intersect_aabb(rays_o, rays_d, field.aabb)
    count = torch.ceil((t_far - t_near) / step - 0.5 + 1e-3).clamp_min(0)  # may count one beyond t_far
    if max_samples is not None:
        count = count.clamp_max(max_samples)
    last = torch.where(hit, count.long() - 1, -1)
    first = torch.zeros_like(last)
    if empty_space is not None:
        first, last = empty_space.sample_window(rays_o, rays_d, t_near, step, first, last, near, cancel)
    return RayWindows(t_near, t_far, first, last)
