"""numba for the CPU inference loops (``representation.vm_kernel``, ``rendering.empty_space_kernel``,
``rendering.march_kernel``): whether it serves a device, and compiling a loop.

numba is a core dependency; where its import fails (a broken install) every caller takes its torch
path, as every device but the CPU does.
"""

from collections.abc import Callable
from typing import Any

import torch

try:
    import numba
except ImportError:  # pragma: no cover - numba is a core dependency
    numba = None


def serves(device: torch.device) -> bool:
    """Whether the compiled loops serve ``device`` (the CPU, with numba importable)."""
    return numba is not None and device.type == "cpu"


def jit(fn: Callable[..., Any], inline: bool = False, fastmath: set[str] | None = None) -> Callable[..., Any]:
    """``fn`` compiled in nopython mode, releasing the GIL, cached on disk by numba where a cache
    directory is writable (else compiled once per process); ``inline=True`` for a helper that the
    loops inline (not callable from Python on its own); ``fastmath``: LLVM's fast-math flags for the
    loop (numba's names, e.g. ``{"reassoc"}`` to sum in vector lanes). Returns ``fn`` itself
    without numba."""
    if numba is None:  # pragma: no cover
        return fn
    if inline:
        return numba.njit(inline="always", boundscheck=False)(fn)
    flags = {"fastmath": fastmath} if fastmath else {}
    try:
        return numba.njit(nogil=True, cache=True, boundscheck=False, **flags)(fn)
    except RuntimeError:  # no writable cache directory
        return numba.njit(nogil=True, boundscheck=False, **flags)(fn)
