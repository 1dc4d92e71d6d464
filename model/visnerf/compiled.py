"""numba for the CPU inference loops (``representation.vm_kernel``, ``rendering.empty_space_kernel``,
``rendering.march_kernel``): whether it serves a device, and compiling a loop.

numba is a core dependency; where its import fails (a broken install) every caller takes its torch
path, as every device but the CPU does.
"""

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

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
    without numba.

    Division follows numpy's error model (a zero divisor gives inf or NaN, as torch's does): numba's
    default checks every divisor and raises, which keeps LLVM from vectorising any loop that
    divides (an Adam update over 5.8 million floats: 13 ms checked, 2.3 ms with numpy's model).
    The loops guard their divisions themselves."""
    if numba is None:  # pragma: no cover
        return fn
    if inline:
        return numba.njit(inline="always", boundscheck=False, error_model="numpy")(fn)
    flags = {"fastmath": fastmath} if fastmath else {}
    flags["error_model"] = "numpy"
    try:
        return numba.njit(nogil=True, cache=True, boundscheck=False, **flags)(fn)
    except RuntimeError:  # no writable cache directory
        return numba.njit(nogil=True, boundscheck=False, **flags)(fn)


_helpers: "ThreadPoolExecutor | None" = None
T = TypeVar("T")


def parts(n: int, least: int) -> int:
    """Threads for a call over ``n`` items: one per torch thread, each with at least ``least``."""
    return max(1, min(torch.get_num_threads(), n // least))


def run_parts(fn: Callable[[int], None], parts: int) -> None:
    """``fn(i)`` for ``i < parts``, part 0 on the calling thread and the others on helper threads
    (made once): for compiled loops that release the GIL, each given a disjoint share of a call's
    work (one part per core the process may use). The first exception reaches the caller."""
    global _helpers
    if parts <= 1:
        fn(0)
        return
    if _helpers is None:
        _helpers = ThreadPoolExecutor(max_workers=max(1, (os.cpu_count() or 2) - 1), thread_name_prefix="visnerf-part")
    futures = [_helpers.submit(fn, i) for i in range(1, parts)]
    try:
        fn(0)
    finally:
        for future in futures:
            future.result()


def run_ranges(fn: Callable[[int, int], T], n: int, least: int) -> list[T]:
    """``fn(start, stop)`` over consecutive ranges that cover ``range(n)`` in order, one per thread
    with at least ``least`` items each (``parts``, ``run_parts``); returns each range's result in
    range order, so that a caller that sums them sums in the same order on any thread count."""
    count = parts(n, least)
    results: list[Any] = [None] * count

    def part(i: int) -> None:
        results[i] = fn(n * i // count, n * (i + 1) // count)

    run_parts(part, count)
    return results
