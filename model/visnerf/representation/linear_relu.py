"""``relu(x @ weight.T + bias)`` in one pass where oneDNN can fuse it (CPU inference, no grad).

A decoder's hidden layer is a matrix product, a bias and a ReLU. As ``addmm`` then ``relu_`` it
writes the bias into the output, runs the product on it, and reads and writes the whole
``[m, 128]`` activation once more for the ReLU. oneDNN's fused linear (``torch.ops.mkldnn.
_linear_pointwise`` with the ``relu`` post-op, the kernel torch's own CPU compiler emits) does
all three in the product's epilogue, faster and with the same values (docs/decisions.md#frames.compiled_rows).

The fused op is private to torch and exists only in builds with oneDNN, so it is probed once per
dtype (run on a small input and compared with the plain path) and the plain path is used where it
is missing, fails, or disagrees, and on every device but the CPU. A CPU without bf16 instructions
(AVX2 only) has the float32 kernel and no bfloat16 one: oneDNN refuses to create
it, and bfloat16 products there take the plain path.
"""

import torch
from jaxtyping import Float
from torch import Tensor

_fused_ok: dict[torch.dtype, bool] = {}
"""Per dtype: whether the fused op ran and matched the plain path (probed once per process)."""
PROBE_TOLERANCE = {torch.float32: 1e-5, torch.bfloat16: 2e-2}
"""Relative and absolute tolerance of the probe's comparison, per dtype."""


def _fused_op():  # a torch op overload packet
    return torch.ops.mkldnn._linear_pointwise


def plain_linear_relu(
    x: Float[Tensor, "m i"], weight: Float[Tensor, "o i"], bias: Float[Tensor, " o"]
) -> Float[Tensor, "m o"]:
    """The unfused reference: ``addmm`` then an in-place ReLU."""
    return torch.addmm(bias, x, weight.t()).relu_()


def fused_available(dtype: torch.dtype = torch.float32) -> bool:
    """Whether the fused op exists here for ``dtype`` and reproduces the plain path (probed once
    per process and dtype)."""
    if dtype not in _fused_ok:
        ok = False
        if torch.backends.mkldnn.is_available() and dtype in PROBE_TOLERANCE:
            try:
                g = torch.Generator().manual_seed(0)
                x, w, b = (torch.randn(*s, generator=g).to(dtype) for s in ((37, 11), (5, 11), (5,)))
                with torch.no_grad():
                    got = _fused_op()(x, w, b, "relu", [], "")
                tol = PROBE_TOLERANCE[dtype]
                ok = bool(torch.allclose(got.float(), plain_linear_relu(x, w, b).float(), rtol=tol, atol=tol))
            except (AttributeError, RuntimeError, NotImplementedError):
                ok = False
        _fused_ok[dtype] = ok
    return _fused_ok[dtype]


def linear_relu(
    x: Float[Tensor, "m i"], weight: Float[Tensor, "o i"], bias: Float[Tensor, " o"]
) -> Float[Tensor, "m o"]:
    """``relu(x @ weight.T + bias)``; all three in one dtype (float32 or bfloat16), no grad."""
    if x.device.type == "cpu" and not torch.is_grad_enabled() and fused_available(x.dtype):
        return _fused_op()(x, weight, bias, "relu", [], "")
    return plain_linear_relu(x, weight, bias)
