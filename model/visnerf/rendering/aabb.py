"""Ray / axis-aligned box intersection (slab method), exact for axis-parallel rays."""

import torch
from jaxtyping import Bool, Float
from torch import Tensor


def intersect_aabb(
    rays_o: Float[Tensor, "n 3"],
    rays_d: Float[Tensor, "n 3"],
    aabb: Float[Tensor, "2 3"],
    near: float = 0.0,
) -> tuple[Float[Tensor, " n"], Float[Tensor, " n"], Bool[Tensor, " n"]]:
    """Entry and exit distances of rays through a box, and whether the ray meets it.

    ``t_near`` is clipped to ``near`` (so an origin inside the box enters at ``near``). Direction
    components equal to zero (+0.0 or -0.0) are handled explicitly: the slab of that axis is all
    of R when the origin lies inside it, and empty otherwise, so no 0 * inf appears. Rays that miss
    get ``t_near == t_far`` and ``hit == False``. Not differentiable in a useful way.
    """
    lower, upper = aabb[0], aabb[1]
    zero = rays_d == 0  # [n, 3]; True for -0.0 too
    safe_d = torch.where(zero, torch.ones_like(rays_d), rays_d)
    t0 = (lower - rays_o) / safe_d  # [n, 3]
    t1 = (upper - rays_o) / safe_d
    t_lo, t_hi = torch.minimum(t0, t1), torch.maximum(t0, t1)
    inside = (rays_o >= lower) & (rays_o <= upper)  # [n, 3]
    inf = torch.full_like(t_lo, float("inf"))
    t_lo = torch.where(zero, torch.where(inside, -inf, inf), t_lo)
    t_hi = torch.where(zero, torch.where(inside, inf, -inf), t_hi)
    t_near = t_lo.amax(dim=-1).clamp_min(near)  # [n]
    t_far = t_hi.amin(dim=-1)  # [n]
    hit = t_far > t_near
    t_far = torch.where(hit, t_far, t_near)
    t_near = torch.where(torch.isfinite(t_near), t_near, torch.zeros_like(t_near))
    t_far = torch.where(hit, t_far, t_near)
    return t_near, t_far, hit
