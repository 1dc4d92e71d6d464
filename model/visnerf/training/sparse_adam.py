"""Adam that pays only for the rows a step touched (the fused CPU step's optimizer).

A step's rays read a small share of the VM tables' rows (a late Nyx step: a few per cent), yet
torch's Adam passes over every row of every table: its parameters, gradients and both moments,
about 30 bytes a factor, each step. ``RowSparseAdam`` updates a table registered with row marks
(``vm_rows.RowGradients``) only at the marked rows, with the bias correction of each row's own
count of updates, then zeroes those gradient rows and marks (the gradient buffer is kept from
step to step). A row no step touches keeps its value and moments: lazy Adam. Every other
parameter (the decoders, the parameter tables) is updated whole, as torch's Adam does (tested
to float rounding), and keeps its ``.grad`` handling (``zero_grad`` sets it to None).
"""

import math
from collections.abc import Iterable
from typing import Any, no_type_check

import numpy as np
import torch
from torch import Tensor, nn

from visnerf import compiled


@no_type_check  # compiled by numba
def _adam_rows(param, grad, exp_avg, exp_avg_sq, steps, marks, use_marks, lr, beta1, beta2, eps):  # noqa: ANN001, ANN202
    """Adam at the rows of ``param`` ``[rows, c]`` whose mark is set (every row without
    ``use_marks``); their gradient rows and marks are zeroed."""
    for row in range(param.shape[0]):
        if use_marks and marks[row] == 0:
            continue
        t = steps[row] + 1.0
        steps[row] = t
        step_size = lr / (1.0 - beta1 ** t)
        bias2_sqrt = math.sqrt(1.0 - beta2 ** t)
        for ch in range(param.shape[1]):
            g = grad[row, ch]
            m = exp_avg[row, ch]
            m = m + (1.0 - beta1) * (g - m)
            v = exp_avg_sq[row, ch] * beta2 + (1.0 - beta2) * g * g
            exp_avg[row, ch] = m
            exp_avg_sq[row, ch] = v
            param[row, ch] -= step_size * m / (math.sqrt(v) / bias2_sqrt + eps)
            grad[row, ch] = 0.0
        if use_marks:
            marks[row] = 0


_adam_rows_loop = compiled.jit(_adam_rows)
_NO_MARKS = np.zeros(1, np.uint8)


def _rows(t: Tensor) -> Tensor:
    """``t`` as a 2-d view ``[rows, columns]`` (a 0-d tensor as one row of one column)."""
    return t.view(1, 1) if t.dim() == 0 else t.view(t.shape[0], -1)


class RowSparseAdam(torch.optim.Optimizer):
    """Adam (no weight decay, no AMSGrad) on CPU float tensors; the parameters given row marks
    (``set_row_marks``) are updated only at their marked rows. State per parameter: ``exp_avg``,
    ``exp_avg_sq`` and ``step`` (float32, one count per row)."""

    def __init__(self, params: Iterable[Any], lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8) -> None:
        super().__init__(params, {"lr": lr, "betas": tuple(betas), "eps": eps})
        self.row_marks: dict[int, np.ndarray] = {}
        """``id(parameter)``: the marks of its rows that hold a gradient."""

    def set_row_marks(self, param: nn.Parameter, marks: np.ndarray) -> None:
        """Update ``param`` only at the rows whose mark is set, then clear them; its ``.grad`` is
        a buffer kept from step to step (``zero_grad`` leaves it)."""
        if marks.shape != (_rows(param).shape[0],):
            raise ValueError(f"{marks.shape[0]} row marks for a parameter of {_rows(param).shape[0]} rows")
        self.row_marks[id(param)] = marks

    def zero_grad(self, set_to_none: bool = True) -> None:
        for group in self.param_groups:
            for p in group["params"]:
                if id(p) not in self.row_marks and p.grad is not None:
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

    @torch.no_grad()
    def step(self, closure: None = None) -> None:  # type: ignore[override]
        if closure is not None:
            raise ValueError("RowSparseAdam takes no closure")
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                if p.device.type != "cpu" or not p.is_contiguous() or not p.grad.is_contiguous():
                    raise ValueError("RowSparseAdam updates contiguous CPU tensors")
                state = self._state_of(p)
                marks = self.row_marks.get(id(p))
                _adam_rows_loop(_rows(p).numpy(), _rows(p.grad).numpy(), _rows(state["exp_avg"]).numpy(),
                                _rows(state["exp_avg_sq"]).numpy(), state["step"].numpy(),
                                _NO_MARKS if marks is None else marks, marks is not None, float(group["lr"]),
                                float(beta1), float(beta2), float(group["eps"]))
