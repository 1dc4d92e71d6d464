"""Adam that pays only for the rows a step touched (the fused CPU step's optimizer).

A step's rays read a share of the VM tables' rows (a late Nyx step at 200^3: 40 %), yet torch's
Adam passes over every row of every table: its parameters, gradients and both moments, each step,
and the gradient is written, read and zeroed in full. ``RowSparseAdam`` takes a VM table's
gradient from its ``TableGradient`` (``representation.table_gradients``):

- pending taps (one process, no prior that reads a row's neighbours): one pass over the touched
  rows sums each row's taps, adds the L1 prior where one is set, and updates the row, its moments
  and its count; no table-sized gradient exists. A small table (``table_gradients.SCATTER_ROWS``: a grid's
  lines, which every sample reads) takes its taps sample by sample into a row buffer of its
  own instead, then updates the rows they marked: the same sums in the same order;
- a materialized gradient (``.grad`` with row marks: ranks, total variation): the marked rows
  are updated and their gradient rows and marks zeroed.

Each row's bias correction follows its own count of updates, and a row no step touches keeps its
value and moments: lazy Adam. Every other parameter (the decoders, the parameter tables) is
updated whole, as torch's Adam does (tested to float rounding), from its ``.grad``.
"""

import functools
import math
from collections.abc import Iterable
from typing import Any, no_type_check

import numpy as np
import torch
from torch import Tensor, nn

from visnerf import compiled
from visnerf.representation import table_gradients
from visnerf.representation.table_gradients import MIN_ROWS_A_PART, TableGradient, TapIndex
from visnerf.representation.vm_rows_kernel import PREFETCH_ROWS, prefetch_touched, sum_taps

_FLOAT_TYPES = {torch.float32: np.float32, torch.float64: np.float64}
_NO_MARKS = np.zeros(1, np.uint8)
_NO_COEFFICIENTS = np.zeros(1, np.float64)
_NO_PARTS = np.zeros(2, np.int64)


@functools.cache
def _update_loop(ft: type):  # an inlined numba helper
    """One row's Adam update in float type ``ft``."""

    @no_type_check  # compiled by numba
    def _update(param, g, exp_avg, exp_avg_sq, row, steps, lr, b1, b2, b2c, e, inv_bias1, bias2_sqrts):
        """Adam on ``param[row]`` with gradient row ``g``."""
        t = int(steps[row]) + 1
        steps[row] = t
        step_size = ft(lr * inv_bias1[t])
        inv_bias2 = ft(1.0 / bias2_sqrts[t])
        for ch in range(param.shape[1]):
            m = exp_avg[row, ch]
            m = m + b1 * (g[ch] - m)
            v = exp_avg_sq[row, ch] * b2 + b2c * g[ch] * g[ch]
            exp_avg[row, ch] = m
            exp_avg_sq[row, ch] = v
            param[row, ch] -= step_size * m / (math.sqrt(v) * inv_bias2 + e)

    return compiled.jit(_update, inline=True)


@functools.cache
def _row_l1_loop(ft: type):  # an inlined numba helper
    """The L1 prior at one row in float type ``ft``."""

    @no_type_check
    def _row_l1(param, row, g, l1, part_starts, part):
        """Add ``l1[mode] * sign(param[row])`` into ``g`` (``part``: the mode of an earlier row, rows
        in increasing order); returns the row's mode and the prior there, ``l1[mode] * sum |value|``."""
        while row >= part_starts[part + 1]:
            part += 1
        coefficient = ft(l1[part])
        row_sum = 0.0
        for ch in range(param.shape[1]):
            v = param[row, ch]
            g[ch] += coefficient * ((v > 0) - (v < 0))
            row_sum += abs(v)
        return part, l1[part] * row_sum

    return compiled.jit(_row_l1, inline=True)


@no_type_check  # compiled by numba, inlined into both updates' prefetches
def _prefetch_state(param, exp_avg, exp_avg_sq, row):
    """Ask for row ``row``'s value and moments, which its update reads and writes."""
    compiled.prefetch_row(param, row)
    compiled.prefetch_row(exp_avg, row)
    compiled.prefetch_row(exp_avg_sq, row)


prefetch_state = compiled.jit(_prefetch_state, inline=True)


@no_type_check  # compiled by numba, inlined into the update at marked rows
def _prefetch_marked(param, grad, exp_avg, exp_avg_sq, marks, row, stop):
    """Ask for the first marked row from ``row`` on: its gradient, value and moments
    (``vm_rows_kernel.PREFETCH_ROWS``); returns the row after it."""
    while row < stop and marks[row] == 0:
        row += 1
    if row < stop:
        compiled.prefetch_row(grad, row)
        prefetch_state(param, exp_avg, exp_avg_sq, row)
    return row + 1


prefetch_marked = compiled.jit(_prefetch_marked, inline=True)


def _marked_source(ft: type):  # the loop numba compiles for float type ``ft``
    update = _update_loop(ft)
    row_l1 = _row_l1_loop(ft)
    rows_ahead = PREFETCH_ROWS

    @no_type_check
    def _adam_marked(param, grad, exp_avg, exp_avg_sq, steps, marks, use_marks, part_starts, l1, use_l1,
                     lr, beta1, beta2, eps, inv_bias1, bias2_sqrts, first, stop):
        """Adam at the rows ``first <= row < stop`` whose mark is set (every row without
        ``use_marks``), from ``grad`` plus, with ``use_l1``, ``l1[mode] * sign(value)``; their
        gradient rows and marks are zeroed. Returns the L1 prior's part at those rows.
        ``inv_bias1[t] = 1 / (1 - beta1^t)`` and ``bias2_sqrts[t] = sqrt(1 - beta2^t)`` for a
        row's ``t``-th update (float64)."""
        b1, b2, b2c, e = ft(1.0 - beta1), ft(beta2), ft(1.0 - beta2), ft(eps)
        total = 0.0
        part = 0
        ahead = first
        if use_marks:  # every row in order needs no asking
            for _ in range(rows_ahead):
                ahead = prefetch_marked(param, grad, exp_avg, exp_avg_sq, marks, ahead, stop)
        for row in range(first, stop):
            if use_marks and marks[row] == 0:
                continue
            if use_marks:
                ahead = prefetch_marked(param, grad, exp_avg, exp_avg_sq, marks, ahead, stop)
            g = grad[row]
            if use_l1:
                part, value = row_l1(param, row, g, l1, part_starts, part)
                total += value
            update(param, g, exp_avg, exp_avg_sq, row, steps, lr, b1, b2, b2c, e, inv_bias1, bias2_sqrts)
            for ch in range(param.shape[1]):
                grad[row, ch] = 0
            if use_marks:
                marks[row] = 0
        return total

    return _adam_marked


@no_type_check  # compiled by numba, inlined into the update from taps
def _prefetch_update(param, exp_avg, exp_avg_sq, starts, taps, values, row, stop):
    """Ask for the first touched row from ``row`` on: its taps' gradients, value and moments
    (``vm_rows_kernel.PREFETCH_ROWS``); returns the row after it."""
    row = prefetch_touched(starts, taps, values, row, stop)
    if row < stop:
        prefetch_state(param, exp_avg, exp_avg_sq, row)
    return row + 1


prefetch_update = compiled.jit(_prefetch_update, inline=True)


def _taps_source(ft: type):  # the loop numba compiles for float type ``ft``
    update = _update_loop(ft)
    row_l1 = _row_l1_loop(ft)
    rows_ahead = PREFETCH_ROWS

    @no_type_check
    def _adam_taps(param, exp_avg, exp_avg_sq, steps, starts, taps, tap_weights, values, part_starts,
                   l1, use_l1, lr, beta1, beta2, eps, inv_bias1, bias2_sqrts, first, stop):
        """Adam at the rows ``first <= row < stop`` that pending taps reach (``TapIndex``), their
        gradient the sum of their taps' plus, with ``use_l1``, ``l1[mode] * sign(value)``;
        returns the L1 prior's part at those rows, ``sum l1[mode] |value|``."""
        b1, b2, b2c, e = ft(1.0 - beta1), ft(beta2), ft(1.0 - beta2), ft(eps)
        c = param.shape[1]
        g = np.empty(c, ft)
        total = 0.0
        part = 0
        ahead = first
        for _ in range(rows_ahead):
            ahead = prefetch_update(param, exp_avg, exp_avg_sq, starts, taps, values, ahead, stop)
        for row in range(first, stop):
            a, b = starts[row], starts[row + 1]
            if a == b:
                continue
            ahead = prefetch_update(param, exp_avg, exp_avg_sq, starts, taps, values, ahead, stop)
            sum_taps(g, c, a, b, taps, tap_weights, values)
            if use_l1:
                part, value = row_l1(param, row, g, l1, part_starts, part)
                total += value
            update(param, g, exp_avg, exp_avg_sq, row, steps, lr, b1, b2, b2c, e, inv_bias1, bias2_sqrts)
        return total

    return _adam_taps


_LOOPS = {ft: (compiled.jit(_marked_source(ft)), compiled.jit(_taps_source(ft))) for ft in (np.float32, np.float64)}


def _rows(t: Tensor) -> Tensor:
    """``t`` as a 2-d view ``[rows, columns]`` (a 0-d tensor as one row of one column)."""
    return t.view(1, 1) if t.dim() == 0 else t.view(t.shape[0], -1)


class RowSparseAdam(torch.optim.Optimizer):
    """Adam (no weight decay, no AMSGrad) on contiguous CPU float tensors; a parameter given a
    ``TableGradient`` (``set_row_source``) is updated only at the rows its gradient reaches.
    State per parameter: ``exp_avg``, ``exp_avg_sq`` and ``step`` (float32, a count per row)."""

    def __init__(self, params: Iterable[Any], lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8) -> None:
        super().__init__(params, {"lr": lr, "betas": tuple(betas), "eps": eps})
        self.sources: dict[int, TableGradient] = {}
        """``id(parameter)``: where its gradient comes from."""
        self._bias: dict[tuple[float, float], tuple[np.ndarray, np.ndarray]] = {}
        self._most_updates: int | None = None
        """A bound on any row's count of updates (from the state at the first step, plus one a step)."""
        self._row_buffers: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        """``id(parameter)``: the gradient rows and marks of a small table (``table_gradients.SCATTER_ROWS``), zero
        between steps."""

    def set_row_source(self, param: nn.Parameter, source: TableGradient) -> None:
        """Take ``param``'s gradient from ``source`` (its ``.grad`` is ``source``'s buffer, kept
        from step to step: ``zero_grad`` leaves it)."""
        if not source.follows(param):
            raise ValueError("the row source's table is not this parameter")
        self.sources[id(param)] = source

    def zero_grad(self, set_to_none: bool = True) -> None:
        for group in self.param_groups:
            for p in group["params"]:
                if id(p) not in self.sources and p.grad is not None:
                    if set_to_none:
                        p.grad = None
                    else:
                        p.grad.zero_()

    def _state_of(self, p: Tensor) -> dict[str, Tensor]:
        state = self.state[p]
        if not state:
            state["exp_avg"] = torch.zeros_like(p)
            state["exp_avg_sq"] = torch.zeros_like(p)
            state["step"] = torch.zeros(_rows(p).shape[0], dtype=torch.float32)
        elif state["step"].dim() == 0:  # a dense Adam's count (a run state written before): every row's
            state["step"] = torch.full((_rows(p).shape[0],), float(state["step"]), dtype=torch.float32)
        return state

    def _bias_tables(self, beta1: float, beta2: float) -> tuple[np.ndarray, np.ndarray]:
        """``1 / (1 - beta1^t)`` and ``sqrt(1 - beta2^t)`` for every count ``t`` a row can reach at
        this step (float64; kept, and grown by doubling)."""
        if self._most_updates is None:
            counts = [int(s["step"].max()) for s in self.state.values() if "step" in s and s["step"].numel()]
            self._most_updates = max(counts, default=0)
        self._most_updates += 1
        key = (beta1, beta2)
        tables = self._bias.get(key)
        if tables is None or tables[0].shape[0] <= self._most_updates:
            t = np.arange(max(1024, 2 * self._most_updates + 1), dtype=np.float64)
            with np.errstate(divide="ignore"):
                tables = (1.0 / (1.0 - beta1**t), np.sqrt(1.0 - beta2**t))
            self._bias[key] = tables
        return tables

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        super().load_state_dict(state_dict)
        self._most_updates = None

    @torch.no_grad()
    def step(self, closure: None = None) -> None:  # type: ignore[override]
        if closure is not None:
            raise ValueError("RowSparseAdam takes no closure")
        tables = None
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            if tables is None or tables[0] != (beta1, beta2):
                tables = ((beta1, beta2), self._bias_tables(beta1, beta2))
            inv_bias1, bias2_sqrts = tables[1]
            hyper = (float(group["lr"]), float(beta1), float(beta2), float(group["eps"]), inv_bias1, bias2_sqrts)
            for p in group["params"]:
                source = self.sources.get(id(p))
                if source is not None and source.pending and source.marks.any():
                    source.materialize()  # some of its gradient is in the buffer already: all of it there
                if source is not None and source.pending:
                    self._update_from_taps(p, source, hyper)
                elif p.grad is not None:
                    self._update_from_grad(p, None if source is None else source.marks, hyper)

    def _check(self, p: Tensor) -> None:
        if p.device.type != "cpu" or not p.is_contiguous() or p.dtype not in _FLOAT_TYPES:
            raise ValueError("RowSparseAdam updates contiguous CPU float32 or float64 tensors")

    def _update_from_grad(self, p: Tensor, marks: np.ndarray | None, hyper: tuple) -> None:
        self._check(p)
        state = self._state_of(p)
        arrays = (_rows(p).numpy(), _rows(p.grad.contiguous()).numpy(), _rows(state["exp_avg"]).numpy(),
                  _rows(state["exp_avg_sq"]).numpy(), state["step"].numpy(), _NO_MARKS if marks is None else marks,
                  marks is not None, _NO_PARTS, _NO_COEFFICIENTS, False, *hyper)
        loop = _LOOPS[_FLOAT_TYPES[p.dtype]][0]
        compiled.run_ranges(lambda a, b: loop(*arrays, a, b), _rows(p).shape[0], MIN_ROWS_A_PART)

    def _update_from_taps(self, p: Tensor, source: TableGradient, hyper: tuple) -> None:
        self._check(p)
        if source.n_rows <= table_gradients.SCATTER_ROWS:
            self._update_from_scattered_taps(p, source, hyper)
            return
        state = self._state_of(p)
        index: TapIndex = source.index()  # type: ignore[assignment]
        use_l1 = source.l1_coefficients is not None
        arrays = (_rows(p).numpy(), _rows(state["exp_avg"]).numpy(), _rows(state["exp_avg_sq"]).numpy(),
                  state["step"].numpy(), index.starts, index.taps, index.weights, index.values,
                  source.part_starts.astype(np.int64), source.l1_coefficients if use_l1 else _NO_COEFFICIENTS,
                  use_l1, *hyper)
        loop = _LOOPS[_FLOAT_TYPES[p.dtype]][1]
        totals = compiled.run_ranges(lambda a, b: loop(*arrays, a, b), _rows(p).shape[0], MIN_ROWS_A_PART)
        source.l1_value = float(sum(totals))

    def _update_from_scattered_taps(self, p: Tensor, source: TableGradient, hyper: tuple) -> None:
        """``_update_from_taps`` for a small table, on one thread: its pending taps added sample by
        sample into a row buffer (kept, outside the optimizer's state), then the touched rows
        updated. The sums and the update are those of the sorted gather, float for float."""
        state = self._state_of(p)
        ft = _FLOAT_TYPES[p.dtype]
        buffer = self._row_buffers.get(id(p))
        if buffer is None or buffer[0].shape != _rows(p).shape or buffer[0].dtype != ft:
            buffer = (np.zeros(_rows(p).shape, ft), np.zeros(_rows(p).shape[0], np.uint8))
            self._row_buffers[id(p)] = buffer
        grad, marks = buffer
        source.scatter(grad, marks)
        use_l1 = source.l1_coefficients is not None
        adam_marked = _LOOPS[ft][0]
        source.l1_value = float(adam_marked(
            _rows(p).numpy(), grad, _rows(state["exp_avg"]).numpy(), _rows(state["exp_avg_sq"]).numpy(),
            state["step"].numpy(), marks, True, source.part_starts.astype(np.int64),
            source.l1_coefficients if use_l1 else _NO_COEFFICIENTS, use_l1, *hyper, 0, grad.shape[0]))
