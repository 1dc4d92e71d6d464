"""The decoders' input rows of training samples and their backward, as compiled loops (CPU, numba).

A training sample's decoder row is ``[F * q_rep, q, encoding]``: the VM features ``F`` of its grid
(plane times line, three modes of ``c`` channels), channel ``i`` scaled by its ray's parameter
feature ``q[i % n_q]`` (``field.modulate``), the parameter features themselves, then either the
positional encoding of the sample (density) or its ray's own columns (the colour decoder's
spherical harmonics). As torch operations that is a tap computation, two ``embedding_bag`` sums,
a product, a ``repeat``, a gather of ``q`` per sample, a product and a ``cat``, and as many again
backwards; here one loop over the samples writes the row, and one loop scatters a row's gradient
into the rows of the tables it read and into its ray's ``q``.

The interpolation is ``vm_taps``' (``align_corners=True``, the border read outside [-1, 1], the
lower node at most ``n - 2``, NaN read as -1), the encoding ``vm_kernel``'s (double-angle sines).
Both loops are compiled per channel count, parameter-feature count and float type (float32 for
training, float64 for the tests against autograd); both release the GIL.
"""

import functools
import math
from typing import no_type_check

import numpy as np

from visnerf import compiled
from visnerf.representation.vm_kernel import plane_axes


def _sources(c: int, n_q: int, float_type: type):  # noqa: ANN202 - the two loops numba compiles
    """Forward and backward loops for tables of ``c`` channels and ``n_q`` parameter features in
    ``float_type`` (constants of the compiled loops)."""
    ft = float_type
    nf = 3 * c

    @no_type_check
    def _interpolation(coords, s, res, lower, frac):  # noqa: ANN001, ANN202
        one = ft(1.0)
        for a in range(3):
            x = coords[s, a]
            if not x >= -one:  # NaN reads the border too: no index outside the tables
                x = -one
            elif x > one:
                x = one
            half = ft(0.5) * ft(res[a] - 1)
            pos = half * x + half
            lo = min(math.floor(pos), res[a] - 2)
            lower[a] = lo
            frac[a] = pos - ft(lo)

    interpolation = compiled.jit(_interpolation, inline=True)

    @no_type_check
    def _forward(coords, ray, q, tail, plane, line, res, plane_off, line_off, n_freqs, out):  # noqa: ANN001, ANN202
        """``out[s] = [F(coords[s]) * q_rep[ray[s]], q[ray[s]], encoding(coords[s]) or tail[ray[s]]]``."""
        one = ft(1.0)
        lower = np.empty(3, np.int64)
        frac = np.empty(3, ft)
        e = tail.shape[1]
        for s in range(coords.shape[0]):
            interpolation(coords, s, res, lower, frac)
            r = ray[s]
            for i in range(3):
                pa, pb, la = plane_axes(i)
                w = res[pa]
                r00 = plane_off[i] + lower[pb] * w + lower[pa]
                fa, fb, fl = frac[pa], frac[pb], frac[la]
                w00, w10 = (one - fa) * (one - fb), fa * (one - fb)
                w01, w11 = (one - fa) * fb, fa * fb
                l0 = line_off[i] + lower[la]
                for ch in range(c):
                    p = ((w00 * plane[r00, ch] + w10 * plane[r00 + 1, ch])
                         + (w01 * plane[r00 + w, ch] + w11 * plane[r00 + w + 1, ch]))
                    v = (one - fl) * line[l0, ch] + fl * line[l0 + 1, ch]
                    out[s, i * c + ch] = p * v * q[r, (i * c + ch) % n_q]
            for j in range(n_q):
                out[s, nf + j] = q[r, j]
            col = nf + n_q
            if n_freqs >= 0:
                for a in range(3):
                    out[s, col + a] = coords[s, a]
                for a in range(3):
                    angle = coords[s, a] * ft(math.pi)
                    sn, cs = ft(math.sin(angle)), ft(math.cos(angle))
                    for level in range(n_freqs):
                        out[s, col + 3 + 6 * level + a] = sn
                        out[s, col + 6 + 6 * level + a] = cs
                        sn, cs = ft(2.0) * sn * cs, (cs - sn) * (cs + sn)
                col += 3 + 6 * n_freqs
            for j in range(e):
                out[s, col + j] = tail[r, j]

    @no_type_check
    def _backward(coords, ray, q, grad_out, plane, line, res, plane_off, line_off,  # noqa: ANN001, ANN202
                  grad_plane, grad_line, grad_q, plane_marks, line_marks):
        """Add the gradient of ``_forward``'s rows, ``grad_out[s, :3c + n_q]``, into the tables'
        gradients (``grad_plane``, ``grad_line``), marking every row it touches, and into
        ``grad_q`` of each sample's ray. Samples in order: the sums are deterministic."""
        one = ft(1.0)
        lower = np.empty(3, np.int64)
        frac = np.empty(3, ft)
        for s in range(coords.shape[0]):
            interpolation(coords, s, res, lower, frac)
            r = ray[s]
            for i in range(3):
                pa, pb, la = plane_axes(i)
                w = res[pa]
                r00 = plane_off[i] + lower[pb] * w + lower[pa]
                fa, fb, fl = frac[pa], frac[pb], frac[la]
                w00, w10 = (one - fa) * (one - fb), fa * (one - fb)
                w01, w11 = (one - fa) * fb, fa * fb
                l0 = line_off[i] + lower[la]
                gl0, gl1 = one - fl, fl
                for ch in range(c):
                    k = (i * c + ch) % n_q
                    g = grad_out[s, i * c + ch]
                    p = ((w00 * plane[r00, ch] + w10 * plane[r00 + 1, ch])
                         + (w01 * plane[r00 + w, ch] + w11 * plane[r00 + w + 1, ch]))
                    v = gl0 * line[l0, ch] + gl1 * line[l0 + 1, ch]
                    grad_q[r, k] += g * p * v
                    gf = g * q[r, k]
                    gp, gv = gf * v, gf * p
                    grad_plane[r00, ch] += w00 * gp
                    grad_plane[r00 + 1, ch] += w10 * gp
                    grad_plane[r00 + w, ch] += w01 * gp
                    grad_plane[r00 + w + 1, ch] += w11 * gp
                    grad_line[l0, ch] += gl0 * gv
                    grad_line[l0 + 1, ch] += gl1 * gv
                plane_marks[r00] = 1
                plane_marks[r00 + 1] = 1
                plane_marks[r00 + w] = 1
                plane_marks[r00 + w + 1] = 1
                line_marks[l0] = 1
                line_marks[l0 + 1] = 1
            for j in range(n_q):
                grad_q[r, j] += grad_out[s, nf + j]

    return compiled.jit(_forward), compiled.jit(_backward)


@functools.cache
def loops(c: int, n_q: int, float_type: type):  # noqa: ANN201 - two numba dispatchers
    """(forward, backward) for ``c`` channels, ``n_q`` parameter features, ``float_type``
    (``np.float32`` or ``np.float64``), compiled once per process (and cached on disk by numba)."""
    if compiled.numba is None:  # pragma: no cover
        raise RuntimeError("numba is not installed: the compiled training lookups are unavailable")
    if float_type not in (np.float32, np.float64):
        raise ValueError(f"the training lookups compute in float32 or float64, not {float_type}")
    return _sources(c, n_q, float_type)
