"""A decoder's output layer on bfloat16 hidden activations, summed and written in float32 (CPU
inference, numba).

In bfloat16 a decoder's last product (``[m, h]`` by ``[h, o]``, ``o`` 1 for density and 3 for
colour) is oneDNN's, which rounds its output to bfloat16: a raw density of 20 then moves by up to
0.06, and a level field's ``g`` times its sharpness by more. Here one loop per sample widens the
row of activations to float32 (a bfloat16 is the top half of a float32) and sums its products with
float32 weights and bias, so the only bfloat16 rounding left is that of the activations: faster
frames, closer to the float32 renderer's (docs/decisions.md#frames.compiled_rows).

The loop releases the GIL, like the other compiled passes (``representation.vm_kernel``).
"""

from typing import no_type_check

import numpy as np
import torch
from jaxtyping import Float, Shaped
from torch import Tensor

from visnerf import compiled


def available(device: torch.device) -> bool:
    """Whether the compiled layer serves ``device`` (``compiled.serves``)."""
    return compiled.serves(device)


@no_type_check  # compiled by numba: no runtime type checks (tests run jaxtyping's import hook)
def _kernel(bits, weight, bias, out):
    """``out[s, k] = sum_j float32(bits[s, j]) * weight[k, j] + bias[k]`` with ``bits`` the
    bfloat16 activations as uint16."""
    m, h = bits.shape
    o = weight.shape[0]
    wide = np.empty(h, np.uint32)
    row = wide.view(np.float32)
    for s in range(m):
        for j in range(h):
            wide[j] = np.uint32(bits[s, j]) << np.uint32(16)
        for k in range(o):
            acc = np.float32(0.0)
            for j in range(h):
                acc += row[j] * weight[k, j]
            out[s, k] = acc + bias[k]


# reassociation lets the row sums run in vector lanes; no flag that assumes finite values, so a
# NaN or an infinity still reaches the output
_compiled = compiled.jit(_kernel, fastmath={"reassoc", "contract"})


class OutputLayer:
    """A decoder's output layer (``weight [o, h]``, ``bias [o]``) kept in float32 for ``__call__``."""

    def __init__(self, weight: Float[Tensor, "o h"], bias: Float[Tensor, " o"]) -> None:
        self._weight = weight.detach().to(torch.float32).contiguous()
        self._bias = bias.detach().to(torch.float32).contiguous()
        self.weight, self.bias = self._weight.numpy(), self._bias.numpy()

    def __call__(self, hidden: Shaped[Tensor, "m h"]) -> Float[Tensor, "m o"]:
        """The layer's float32 output for bfloat16 ``hidden`` (CPU, rows contiguous)."""
        if compiled.numba is None:  # pragma: no cover
            raise RuntimeError("numba is not installed: the compiled output layer is unavailable")
        if hidden.dtype != torch.bfloat16 or hidden.ndim != 2 or hidden.shape[1] != self.weight.shape[1]:
            raise ValueError(f"hidden must be bfloat16 [m, {self.weight.shape[1]}], got {hidden.dtype} "
                             f"{list(hidden.shape)}")
        out = torch.empty(hidden.shape[0], self.weight.shape[0], dtype=torch.float32)
        if hidden.shape[0] > 0:
            bits = hidden.contiguous().view(torch.int16).numpy().view(np.uint16)
            _compiled(bits, self.weight, self.bias, out.numpy())
        return out


def warm_up() -> None:
    """Compile (or load from numba's cache) the loop, so that a server's first frame does not pay."""
    if compiled.numba is None:  # pragma: no cover
        return
    OutputLayer(torch.zeros(1, 2), torch.zeros(1))(torch.zeros(1, 2, dtype=torch.bfloat16))
