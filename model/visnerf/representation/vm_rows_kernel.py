"""The decoders' input rows of training samples and their backward, as compiled loops (CPU, numba).

A training sample's decoder row is ``[F * q_rep, q, encoding]``: the VM features ``F`` of its grid
(plane times line, three modes of ``c`` channels), channel ``i`` scaled by its ray's parameter
feature ``q[i % n_q]`` (``field.modulate``), the parameter features themselves, then either the
positional encoding of the sample (density) or its ray's own columns (the colour decoder's
spherical harmonics). As torch operations that is a tap computation, two ``embedding_bag`` sums,
a product, a ``repeat``, a gather of ``q`` per sample, a product and a ``cat``, and as many again
backwards. Here:

- ``forward`` writes the rows of a range of samples (two threads take a half each) and, for a
  backward, keeps each sample's taps (rows and weights) and plane values;
- ``row_gradients`` (a range of samples) turns a row's gradient into the gradient of each mode's
  plane value and line value (``[3, m, c]`` each, mode-major) and its ray's ``q`` gradient;
- ``gather_gradients`` (a range of table rows) adds into each table row the sum of the gradients
  of the taps that read it, found by a counting sort of the taps by row (``tap_index``), and marks
  it. Each table row is then written once, in order, by one thread: no two threads write a row,
  the sums run in sample order (deterministic), and the random reads go to the small per-sample
  arrays instead of the tables.

The interpolation is ``vm_taps``' (``align_corners=True``, the border read outside [-1, 1], the
lower node at most ``n - 2``, NaN read as -1), the encoding ``vm_kernel``'s (double-angle sines).
The loops are compiled per channel count, parameter-feature count and float type (float32 for
training, float64 for the tests against autograd); all release the GIL.
"""

import functools
from typing import no_type_check

import numpy as np

from visnerf import compiled
from visnerf.representation.vm_kernel import encoding_loop, interpolation_loop, plane_axes


@functools.cache
def _rest_loop(c: int, n_q: int, ft: type):  # an inlined numba helper
    """The columns of a row after its features: ``q``, then the encoding or the ray's tail."""
    nf = 3 * c
    encode = encoding_loop(ft)

    @no_type_check
    def _write_rest(coords, s, q, r, tail, n_freqs, out):
        for j in range(n_q):
            out[s, nf + j] = q[r, j]
        col = nf + n_q
        if n_freqs >= 0:
            encode(coords, s, n_freqs, out, s, col)
            col += 3 + 6 * n_freqs
        for j in range(tail.shape[1]):
            out[s, col + j] = tail[r, j]

    return compiled.jit(_write_rest, inline=True)


PREFETCH_SAMPLES = 2
"""The forward asks for the table rows of the sample this many ahead: a step's samples lie on rays
drawn at random, so their rows are seldom in cache, and one sample's reads would otherwise wait on
memory before the next's begin."""


@functools.cache
def _prefetch_loop(ft: type):  # an inlined numba helper
    """Ask for the plane and line rows that sample ``s`` reads (``compiled.prefetch_row``)."""
    interpolation = interpolation_loop(ft)

    @no_type_check
    def _prefetch_sample(coords, s, res, plane, line, plane_off, line_off, lower, frac):
        interpolation(coords, s, res, lower, frac)
        for i in range(3):
            pa, pb, la = plane_axes(i)
            w = res[pa]
            r00 = plane_off[i] + lower[pb] * w + lower[pa]
            compiled.prefetch_row(plane, r00)
            compiled.prefetch_row(plane, r00 + 1)
            compiled.prefetch_row(plane, r00 + w)
            compiled.prefetch_row(plane, r00 + w + 1)
            compiled.prefetch_row(line, line_off[i] + lower[la])  # a small table: its next row is near

    return compiled.jit(_prefetch_sample, inline=True)


def _forward_source(c: int, n_q: int, ft: type):  # the loop numba compiles
    """``forward`` for tables of ``c`` channels and ``n_q`` parameter features in ``ft``."""
    interpolation = interpolation_loop(ft)
    prefetch_sample = _prefetch_loop(ft)
    write_rest = _rest_loop(c, n_q, ft)
    ahead = PREFETCH_SAMPLES

    @no_type_check
    def _forward(coords, ray, q, tail, plane, line, res, plane_off, line_off, n_freqs, out,
                 save, plane_rows, plane_weights, line_rows, line_weights, plane_values, first, stop):
        """``out[s] = [F(coords[s]) * q_rep[ray[s]], q[ray[s]], encoding(coords[s]) or tail[ray[s]]]``
        for samples ``first <= s < stop``; with ``save``, each mode's first plane row and four
        weights, first line row and two weights, and plane values ``[3, m, c]``."""
        one = ft(1.0)
        lower = np.empty(3, np.int64)
        frac = np.empty(3, ft)
        q_rep = np.empty(c, ft)
        lower_ahead = np.empty(3, np.int64)
        frac_ahead = np.empty(3, ft)
        last_ray = -1
        for s in range(first, stop):
            if s + ahead < stop:
                prefetch_sample(coords, s + ahead, res, plane, line, plane_off, line_off, lower_ahead, frac_ahead)
            interpolation(coords, s, res, lower, frac)
            r = ray[s]
            if r != last_ray:
                for ch in range(c):
                    q_rep[ch] = q[r, ch % n_q]
                last_ray = r
            for i in range(3):
                pa, pb, la = plane_axes(i)
                w = res[pa]
                r00 = plane_off[i] + lower[pb] * w + lower[pa]
                r01 = r00 + w
                fa, fb, fl = frac[pa], frac[pb], frac[la]
                w00, w10 = (one - fa) * (one - fb), fa * (one - fb)
                w01, w11 = (one - fa) * fb, fa * fb
                l0 = line_off[i] + lower[la]
                base = i * c
                if save:
                    plane_rows[s, i] = r00
                    plane_weights[s, i, 0] = w00
                    plane_weights[s, i, 1] = w10
                    plane_weights[s, i, 2] = w01
                    plane_weights[s, i, 3] = w11
                    line_rows[s, i] = l0
                    line_weights[s, i, 0] = one - fl
                    line_weights[s, i, 1] = fl
                    for ch in range(c):
                        p = ((w00 * plane[r00, ch] + w10 * plane[r00 + 1, ch])
                             + (w01 * plane[r01, ch] + w11 * plane[r01 + 1, ch]))
                        v = (one - fl) * line[l0, ch] + fl * line[l0 + 1, ch]
                        plane_values[i, s, ch] = p
                        out[s, base + ch] = p * v * q_rep[ch]
                else:
                    for ch in range(c):
                        p = ((w00 * plane[r00, ch] + w10 * plane[r00 + 1, ch])
                             + (w01 * plane[r01, ch] + w11 * plane[r01 + 1, ch]))
                        v = (one - fl) * line[l0, ch] + fl * line[l0 + 1, ch]
                        out[s, base + ch] = p * v * q_rep[ch]
            write_rest(coords, s, q, r, tail, n_freqs, out)

    return _forward


def _row_gradients_source(c: int, n_q: int, ft: type):  # the loop numba compiles
    """``row_gradients`` for tables of ``c`` channels and ``n_q`` parameter features in ``ft``."""
    nf = 3 * c

    @no_type_check
    def _row_gradients(ray, q, grad_out, line, line_rows, line_weights, plane_values,
                       grad_plane_value, grad_line_value, grad_q, first, stop):
        """For samples ``first <= s < stop``: the gradient of each mode's plane value
        (``g * q_rep * v``) and line value (``g * q_rep * p``), ``[3, m, c]`` each, and the rows'
        gradient of their ray's ``q`` (features and the ``q`` columns) added into ``grad_q``."""
        q_rep = np.empty(c, ft)
        last_ray = -1
        for s in range(first, stop):
            r = ray[s]
            if r != last_ray:
                for ch in range(c):
                    q_rep[ch] = q[r, ch % n_q]
                last_ray = r
            for i in range(3):
                l0 = line_rows[s, i]
                gl0, gl1 = line_weights[s, i, 0], line_weights[s, i, 1]
                base = i * c
                for ch in range(c):
                    g = grad_out[s, base + ch]
                    p = plane_values[i, s, ch]
                    v = gl0 * line[l0, ch] + gl1 * line[l0 + 1, ch]
                    grad_plane_value[i, s, ch] = g * q_rep[ch] * v
                    grad_line_value[i, s, ch] = g * q_rep[ch] * p
                    grad_q[r, ch % n_q] += g * p * v
            for j in range(n_q):
                grad_q[r, j] += grad_out[s, nf + j]

    return _row_gradients


@no_type_check  # compiled by numba, inlined into the loops that sum a row's taps
def _sum_taps(acc, c, a, b, taps, tap_weights, values):
    """``acc[:c] = sum_t tap_weights[t] * values[taps[t]]`` over taps ``a <= t < b`` (a table row's,
    in sample order): the one sum of a row's taps, so that a gradient gathered into the table and
    the sparse Adam's update from the same taps add them alike."""
    for ch in range(c):
        acc[ch] = 0
    for t in range(a, b):
        w = tap_weights[t]
        k = taps[t]
        for ch in range(c):
            acc[ch] += w * values[k, ch]


sum_taps = compiled.jit(_sum_taps, inline=True)


PREFETCH_ROWS = 2
"""Loops over the rows that taps reach ask for the rows of the touched row this many ahead: its taps'
gradients (and, in the sparse Adam, its value and moments) lie in random order in memory, and their
reads would otherwise wait on memory one row after another."""


@no_type_check  # compiled by numba, inlined into the loops over touched rows
def _prefetch_touched(starts, taps, values, row, stop):
    """The first row from ``row`` on (before ``stop``) that taps reach, with its taps' rows of
    ``values`` asked for (``compiled.prefetch_row``); ``stop`` where there is none."""
    while row < stop and starts[row] == starts[row + 1]:
        row += 1
    if row < stop:
        for t in range(starts[row], starts[row + 1]):
            compiled.prefetch_row(values, taps[t])
    return row


prefetch_touched = compiled.jit(_prefetch_touched, inline=True)


def _gather_source(c: int, ft: type):  # the loop numba compiles
    rows_ahead = PREFETCH_ROWS

    @no_type_check
    def _gather_gradients(grad_table, marks, starts, taps, tap_weights, grad_values, first, stop):
        """``grad_table[row] += sum_t tap_weights[t] * grad_values[taps[t]]`` over the taps of each
        row ``first <= row < stop`` (``taps[starts[row]:starts[row + 1]]``, flat ``mode * m + s``
        indices into ``grad_values`` viewed ``[3 m, c]``), which are marked."""
        acc = np.empty(c, ft)
        ahead = first
        for _ in range(rows_ahead):
            ahead = prefetch_touched(starts, taps, grad_values, ahead, stop) + 1
        for row in range(first, stop):
            a, b = starts[row], starts[row + 1]
            if a == b:
                continue
            ahead = prefetch_touched(starts, taps, grad_values, ahead, stop) + 1
            sum_taps(acc, c, a, b, taps, tap_weights, grad_values)
            for ch in range(c):
                grad_table[row, ch] += acc[ch]
            marks[row] = 1

    return _gather_gradients


@functools.cache
def gather_loop(c: int, float_type: type):  # a numba dispatcher
    """``_gather_gradients`` for tables of ``c`` channels in ``float_type``."""
    return compiled.jit(_gather_source(c, float_type))


@no_type_check  # compiled by numba
def _tap_counts(rows, corner_offsets, counts, first, stop):
    """``counts[row + 1]``: the taps of samples ``first <= s < stop`` that read table row ``row``
    (tap ``(s, i, k)`` reads row ``rows[s, i] + corner_offsets[i, k]``); ``counts`` is zeroed here."""
    counts[:] = 0
    for s in range(first, stop):
        for i in range(3):
            for k in range(corner_offsets.shape[1]):
                counts[rows[s, i] + corner_offsets[i, k] + 1] += 1


@no_type_check
def _tap_starts(counts, starts):
    """Each row's first tap over all parts (``starts``, ``n_rows + 1``), and in place of the counts
    where each part's taps of that row begin (``counts[p, row]``): after the parts before it."""
    total = 0
    for row in range(starts.shape[0] - 1):
        starts[row] = total
        for p in range(counts.shape[0]):
            n = counts[p, row + 1]  # this row's count; counts[p, row], the row before's, is read
            counts[p, row] = total
            total += n
    starts[starts.shape[0] - 1] = total


@no_type_check
def _tap_place(rows, weights, corner_offsets, cursor, taps, tap_weights, first, stop):
    """The taps of samples ``first <= s < stop`` into ``taps`` (the flat index ``i * m + s``) and
    ``tap_weights`` at their row's ``cursor``, in sample order."""
    m = rows.shape[0]
    for s in range(first, stop):
        for i in range(3):
            for k in range(corner_offsets.shape[1]):
                row = rows[s, i] + corner_offsets[i, k]
                at = cursor[row]
                taps[at] = i * m + s
                tap_weights[at] = weights[s, i, k]
                cursor[row] = at + 1


_tap_counts_loop = compiled.jit(_tap_counts)
_tap_starts_loop = compiled.jit(_tap_starts)
_tap_place_loop = compiled.jit(_tap_place)
MIN_SAMPLES_A_SORT_PART = 4096
"""Fewest samples worth a thread of their own in ``tap_index``."""


def tap_index(rows: np.ndarray, weights: np.ndarray, corner_offsets: np.ndarray, n_rows: int, starts: np.ndarray,
              taps: np.ndarray, tap_weights: np.ndarray, counts: np.ndarray) -> None:
    """Counting sort of the taps by table row: tap ``(s, i, k)`` reads row ``rows[s, i] +
    corner_offsets[i, k]`` with weight ``weights[s, i, k]``. Writes each row's first tap into
    ``starts`` (``n_rows + 1``) and the taps, row by row in sample order, into ``taps`` (the flat
    index ``i * m + s``) and ``tap_weights``. The samples are counted and placed in consecutive
    parts on every thread (``counts``: scratch of at least ``[threads, n_rows + 1]``); part ``p``'s
    taps of a row follow those of the parts before it, so the order is sample order on any thread
    count."""
    m = rows.shape[0]
    parts = min(compiled.parts(m, MIN_SAMPLES_A_SORT_PART), counts.shape[0])

    def count(p: int) -> None:
        _tap_counts_loop(rows, corner_offsets, counts[p], m * p // parts, m * (p + 1) // parts)

    def place(p: int) -> None:
        _tap_place_loop(rows, weights, corner_offsets, counts[p], taps, tap_weights, m * p // parts,
                        m * (p + 1) // parts)

    compiled.run_parts(count, parts)
    _tap_starts_loop(counts[:parts], starts)
    compiled.run_parts(place, parts)


@functools.cache
def loops(c: int, n_q: int, float_type: type):  # two numba dispatchers
    """(forward, row_gradients) for ``c`` channels, ``n_q`` parameter features,
    ``float_type`` (``np.float32`` or ``np.float64``), compiled once per process (and cached on
    disk by numba)."""
    if compiled.numba is None:  # pragma: no cover
        raise RuntimeError("numba is not installed: the compiled training lookups are unavailable")
    if float_type not in (np.float32, np.float64):
        raise ValueError(f"the training lookups compute in float32 or float64, not {float_type}")
    return (compiled.jit(_forward_source(c, n_q, float_type)),
            compiled.jit(_row_gradients_source(c, n_q, float_type)))
