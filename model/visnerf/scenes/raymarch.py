"""Ray intervals for the reference renderer: box and ball intersection, uniform segments.

Rays are ``rays_o + t * rays_d`` with unit ``rays_d``; ``t`` is the distance from the origin. The
marched interval of a ray is its intersection with the box, the optional support ball (where the
field can be non-zero) and ``t >= near``; so a camera inside the volume starts at ``near``. Each
interval is cut into ``ceil(length / step)`` equal segments, so the segments tile it exactly.
"""

import math

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor


def intersect_box(
    rays_o: Float[Tensor, "n 3"],
    rays_d: Float[Tensor, "n 3"],
    box_min: tuple[float, float, float],
    box_max: tuple[float, float, float],
) -> tuple[Float[Tensor, " n"], Float[Tensor, " n"]]:
    """Entry and exit distances of the slab test; ``t_far < t_near`` when the ray misses.

    A zero direction component is handled explicitly: the ray then meets that slab everywhere
    (origin inside it, boundary included) or nowhere.
    """
    lo = torch.tensor(box_min, dtype=rays_o.dtype, device=rays_o.device)
    hi = torch.tensor(box_max, dtype=rays_o.dtype, device=rays_o.device)
    parallel = rays_d == 0  # [n, 3]
    safe_d = torch.where(parallel, torch.ones_like(rays_d), rays_d)
    t0 = (lo - rays_o) / safe_d  # [n, 3]
    t1 = (hi - rays_o) / safe_d
    inside = (rays_o >= lo) & (rays_o <= hi)  # [n, 3]
    inf = torch.full_like(t0, math.inf)
    t_enter = torch.where(parallel, torch.where(inside, -inf, inf), torch.minimum(t0, t1))
    t_exit = torch.where(parallel, torch.where(inside, inf, -inf), torch.maximum(t0, t1))
    return t_enter.amax(dim=-1), t_exit.amin(dim=-1)


def intersect_ball(
    rays_o: Float[Tensor, "n 3"], rays_d: Float[Tensor, "n 3"], radius: float
) -> tuple[Float[Tensor, " n"], Float[Tensor, " n"]]:
    """Entry and exit distances of a ball of ``radius`` at the origin; ``t_far < t_near`` on a miss."""
    b = (rays_o * rays_d).sum(dim=-1)  # [n]
    c = rays_o.square().sum(dim=-1) - radius**2  # [n]
    disc = b.square() - c  # [n]
    root = torch.sqrt(disc.clamp_min(0.0))
    miss = disc < 0
    t_near = torch.where(miss, torch.full_like(b, math.inf), -b - root)
    t_far = torch.where(miss, torch.full_like(b, -math.inf), -b + root)
    return t_near, t_far


def ray_intervals(
    rays_o: Float[Tensor, "n 3"],
    rays_d: Float[Tensor, "n 3"],
    box_min: tuple[float, float, float],
    box_max: tuple[float, float, float],
    support_radius: float | None,
    near: float,
) -> tuple[Float[Tensor, " n"], Float[Tensor, " n"], Bool[Tensor, " n"]]:
    """``(t_near, t_far, valid)``: the part of each ray inside box, support ball and beyond ``near``."""
    t_near, t_far = intersect_box(rays_o, rays_d, box_min, box_max)
    if support_radius is not None:
        s_near, s_far = intersect_ball(rays_o, rays_d, support_radius)
        t_near, t_far = torch.maximum(t_near, s_near), torch.minimum(t_far, s_far)
    t_near = t_near.clamp_min(near)
    valid = t_far > t_near
    zero = torch.zeros_like(t_near)
    return torch.where(valid, t_near, zero), torch.where(valid, t_far, zero), valid


def uniform_segments(
    t_near: Float[Tensor, " n"], t_far: Float[Tensor, " n"], valid: Bool[Tensor, " n"], step: float
) -> tuple[Int[Tensor, " n"], Float[Tensor, " n"]]:
    """Segment count ``ceil(length / step)`` (0 for invalid rays) and segment length per ray."""
    if not step > 0.0:
        raise ValueError(f"step must be positive, got {step}")
    length = t_far - t_near  # [n]
    count = torch.ceil(length / step - 1e-6).clamp_min(1.0)  # tolerance: L = k * step gives k
    count = torch.where(valid, count, torch.zeros_like(count))
    delta = torch.where(valid, length / count.clamp_min(1.0), torch.zeros_like(length))
    return count.long(), delta
