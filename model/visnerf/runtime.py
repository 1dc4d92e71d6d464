"""Process-wide settings: thread count, and handing freed memory back to the system."""

import ctypes
import ctypes.util
import os
import sys

import torch

_libc: ctypes.CDLL | None = None


def release_free_memory() -> bool:
    """Return the allocator's free pages to the system (glibc ``malloc_trim``).

    Training allocates tensors of varying size every step; glibc keeps the freed blocks in its
    heap, so resident memory creeps up to several times what is live (measured on Nyx: 2.8 GB
    resident against 1.4 GB live after 100 steps). Trimming between steps keeps resident memory
    near what is live. Returns False where there is no glibc.
    """
    global _libc
    if not sys.platform.startswith("linux"):
        return False
    try:
        if _libc is None:
            _libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        _libc.malloc_trim(0)
    except (OSError, AttributeError):
        return False
    return True


def default_threads() -> int:
    """Threads for torch: the cores this process may use (``VISNERF_THREADS`` overrides)."""
    env = os.environ.get("VISNERF_THREADS")
    if env:
        return max(1, int(env))
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:
        return max(1, os.cpu_count() or 1)


_explicit_threads: int | None = None


def configure(threads: int | None = None) -> None:
    """Thread settings, once per process, before heavy work.

    An explicit ``threads`` is kept: a later call without one (``commands.pick_device`` makes one)
    leaves it alone instead of resetting to ``default_threads()``. bench/eval_scenes.py asked for
    one thread and ran with two because of that reset.
    """
    global _explicit_threads
    if threads is not None:
        if threads < 1:
            raise ValueError(f"threads must be at least 1, got {threads}")
        _explicit_threads = threads
    torch.set_num_threads(_explicit_threads or default_threads())


def bf16_native(device: torch.device) -> bool:
    """Whether ``device`` has bfloat16 matrix units (AMX / AVX512-BF16 on CPU, Ampere+ on CUDA)."""
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported()
    if device.type == "cpu":
        return bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())
    return False
