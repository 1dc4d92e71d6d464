"""Ray / axis-aligned box intersection (slab method), exact for axis-parallel rays.

On the CPU one compiled loop over the rays (``aabb_kernel.intersect_loop``) replaces the torch
version's two dozen small operations (four calls a training step;
docs/decisions.md#step.compiled_loops); it does the same float arithmetic in the rays' own type,
so the two agree bit for bit (tested).
"""

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from visnerf import compiled
from visnerf.rendering.aabb_kernel import intersect_loop


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
    if _compiled_serves(rays_o, rays_d, aabb):
        n = rays_o.shape[0]
        t_near = torch.empty(n, dtype=rays_o.dtype)
        t_far = torch.empty(n, dtype=rays_o.dtype)
        hit = torch.empty(n, dtype=torch.bool)
        box = aabb.detach().to(rays_o.dtype).numpy()
        intersect_loop(rays_o.detach().numpy(), rays_d.detach().numpy(), box[0], box[1], float(near),
                        t_near.numpy(), t_far.numpy(), hit.numpy())
        return t_near, t_far, hit
    return intersect_aabb_torch(rays_o, rays_d, aabb, near)


def _compiled_serves(rays_o: Tensor, rays_d: Tensor, aabb: Tensor) -> bool:
    """The compiled loop takes CPU rays of one float type (any strides: a batch's origins are often
    one camera's, expanded) with no gradient wanted."""
    return (compiled.serves(rays_o.device) and aabb.device.type == "cpu" and rays_o.dtype in _LOOP_TYPES
            and rays_d.dtype == rays_o.dtype and rays_o.dim() == 2 and rays_o.shape == rays_d.shape
            and rays_o.shape[1] == 3
            and not (torch.is_grad_enabled() and (rays_o.requires_grad or rays_d.requires_grad)))


_LOOP_TYPES = (torch.float32, torch.float64)


def intersect_aabb_torch(
    rays_o: Float[Tensor, "n 3"],
    rays_d: Float[Tensor, "n 3"],
    aabb: Float[Tensor, "2 3"],
    near: float = 0.0,
) -> tuple[Float[Tensor, " n"], Float[Tensor, " n"], Bool[Tensor, " n"]]:
    """``intersect_aabb`` as torch operations (every device; the compiled loop's slow twin)."""
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
