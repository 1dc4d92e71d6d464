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
    divides (docs/decisions.md#compiled.error_model). The loops guard their divisions themselves."""
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


PREFETCH_LINES = 4
"""``prefetch_row`` asks for at most this many 64-byte lines of a row (the tables' rows hold at most
48 float32 channels: 3 lines)."""


def _prefetch_row_intrinsic():  # a numba intrinsic
    """``prefetch_row(table, row)``: ask the CPU for the cache lines of ``table[row]`` (2-d,
    C-contiguous) up to ``PREFETCH_LINES``, to be read soon and kept in every cache level (LLVM's
    ``prefetch``: no fault, no value; the lines' count is decided by branches, not a loop)."""
    from llvmlite import ir
    from numba import types
    from numba.core import cgutils
    from numba.extending import intrinsic

    @intrinsic
    def prefetch_row(typingctx, table, row):  # numba's signature
        def codegen(context, builder, signature, args):
            table_type = signature.args[0]
            data = context.make_array(table_type)(context, builder, args[0])
            zero = context.get_constant(types.intp, 0)
            first = cgutils.get_item_pointer(context, builder, table_type, data, [args[1], zero], wraparound=False)
            i32, i64 = ir.IntType(32), ir.IntType(64)
            declared = ir.FunctionType(ir.VoidType(), [first.type, i32, i32, i32])
            name = f"llvm.prefetch.{first.type.intrinsic_name}"  # p0 (opaque pointers) or p0f32 (typed)
            call = cgutils.get_or_insert_function(builder.module, declared, name)
            columns = cgutils.unpack_tuple(builder, data.shape, 2)[1]
            row_bytes = builder.mul(columns, context.get_constant(types.intp, table_type.dtype.bitwidth // 8))
            address = builder.ptrtoint(first, i64)
            for line in range(PREFETCH_LINES):
                offset = context.get_constant(types.intp, 64 * line)
                with builder.if_then(builder.icmp_signed("<", offset, row_bytes), likely=True):
                    pointer = builder.inttoptr(builder.add(address, offset), first.type)
                    # read (0), kept in every level (3), data (1)
                    builder.call(call, [pointer, ir.Constant(i32, 0), ir.Constant(i32, 3), ir.Constant(i32, 1)])
            return context.get_dummy_value()

        return types.void(table, row), codegen

    return prefetch_row


if numba is not None:
    prefetch_row = _prefetch_row_intrinsic()
    """``prefetch_row(table, row)``: ask for the lines of ``table[row]`` a few iterations before a
    loop reads it in random order (a lookup's next sample, an update's next row), so that the
    reads overlap instead of waiting on memory one after another. Compiled loops only."""
else:  # pragma: no cover - numba is a core dependency

    def prefetch_row(table: Any, row: int) -> None:
        """Nothing to ask for without numba."""


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
