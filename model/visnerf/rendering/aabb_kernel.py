"""The ray / box slab test of ``aabb.intersect_aabb`` as one compiled loop over the rays (CPU, numba);
``aabb.intersect_aabb_torch`` is its twin, equal bit for bit."""

import math
from typing import no_type_check

from visnerf import compiled


@no_type_check  # compiled by numba
def _intersect(rays_o, rays_d, lower, upper, near, t_near, t_far, hit):
    """``intersect_aabb`` ray by ray: NaN propagates through the minima and maxima as in torch's
    ``minimum``, ``maximum``, ``amax``, ``amin`` and ``clamp_min``."""
    ft = rays_o.dtype.type
    inf = ft(math.inf)
    zero = ft(0.0)
    near_f = ft(near)
    for r in range(rays_o.shape[0]):
        lo, hi = -inf, inf
        for a in range(3):
            o, d = rays_o[r, a], rays_d[r, a]
            if d == 0:  # +0.0 and -0.0: the whole axis when the origin lies in its slab, else nothing
                inside = o >= lower[a] and o <= upper[a]
                a_lo, a_hi = (-inf, inf) if inside else (inf, -inf)
            else:
                t0 = (lower[a] - o) / d
                t1 = (upper[a] - o) / d
                a_lo = t0 if (t0 < t1 or t0 != t0) else t1  # torch.minimum
                a_hi = t0 if (t0 > t1 or t0 != t0) else t1  # torch.maximum
            lo = lo if (lo > a_lo or lo != lo) else a_lo  # amax
            hi = hi if (hi < a_hi or hi != hi) else a_hi  # amin
        tn = lo if (lo > near_f or lo != lo) else near_f  # clamp_min
        h = hi > tn
        tf = hi if h else tn
        if not (tn > -inf and tn < inf):  # not finite: NaN or an infinity
            tn = zero
        t_near[r] = tn
        t_far[r] = tf if h else tn
        hit[r] = h


intersect_loop = compiled.jit(_intersect)
