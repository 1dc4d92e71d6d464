"""Process-wide settings: thread count, how glibc keeps freed memory, and handing it back to the system."""

import ctypes
import ctypes.util
import os
import sys

import torch

from visnerf.cpu_quota import quota_cores

_libc: ctypes.CDLL | None = None


def _glibc() -> ctypes.CDLL | None:
    """The C library where it is glibc (has ``malloc_trim`` and ``mallopt``), else None."""
    global _libc
    if not sys.platform.startswith("linux"):
        return None
    try:
        if _libc is None:
            _libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        _libc.malloc_trim, _libc.mallopt  # noqa: B018 (AttributeError where not glibc)
    except (OSError, AttributeError):
        return None
    return _libc


def release_free_memory() -> bool:
    """Return the allocator's free pages to the system (glibc ``malloc_trim``).

    Training allocates tensors of varying size every step; glibc keeps the freed blocks in its
    heap, so resident memory creeps up to several times what is live
    (docs/decisions.md#runtime.trim). Trimming between steps keeps resident memory
    near what is live. Returns False where there is no glibc.
    """
    libc = _glibc()
    if libc is None:
        return False
    libc.malloc_trim(0)
    return True


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # mallopt parameters (malloc.h)
KEEP_BLOCKS_BELOW = 32 << 20
"""Freed blocks up to this size (glibc's largest mmap threshold on 64-bit) stay in the heap."""
TRIM_ABOVE = 1 << 30
"""free() hands the heap's top back to the system only above this (``release_free_memory`` does
it between steps instead)."""


def keep_freed_blocks() -> bool:
    """Serve blocks of up to 32 MiB from glibc's heap and keep them there once freed (``mallopt``).

    With glibc's defaults (a sliding mmap threshold, and the heap's top handed back to the
    system above twice that), the table-sized tensors of a training step (each micro-batch's
    gradient of a plane table, Adam's temporaries) kept faulting their pages in; kept, a step
    is faster at the same peak memory (docs/decisions.md#runtime.keep_freed_blocks).
    ``release_free_memory`` still returns free pages between steps. Process-wide; returns False
    where there is no glibc.
    """
    libc = _glibc()
    if libc is None:
        return False
    return (bool(libc.mallopt(_M_MMAP_THRESHOLD, KEEP_BLOCKS_BELOW))
            and bool(libc.mallopt(_M_TRIM_THRESHOLD, TRIM_ABOVE)))


def default_threads() -> int:
    """Threads for torch: ``VISNERF_THREADS``, else ``OMP_NUM_THREADS`` (the convention torch and
    OpenMP programs follow: a job started with it set to 1 beside another must not take two
    threads; two 2-thread trainings on 2 busy cores made a tenth of their 1-thread steps), else the
    cores this process may use (``available_cores``)."""
    for name in ("VISNERF_THREADS", "OMP_NUM_THREADS"):
        env = os.environ.get(name, "").strip()
        if env:
            try:
                return max(1, int(env))
            except ValueError:
                raise ValueError(f"{name} must be a whole number of threads, got {env!r}") from None
    return available_cores()


def available_cores() -> int:
    """The cores this process may use: its affinity, capped by its cgroup's CPU quota (``cpu_quota``)."""
    return quota_cores()


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


ACCELERATOR_BATCH_FACTOR = 16
"""How many times more rays a frame's chunk, and samples a decoder pass, hold on a GPU than on the
CPU: each segment of a chunk launches some hundred small kernels and waits for a few counts
(``nonzero``), so a GPU frame in CPU-sized batches is bound by launches, not by its work
(docs/decisions.md#runtime.accelerator_batch_factor)."""


def batch_factor(device: torch.device) -> int:
    """1 on the CPU, where batches are sized for a core's cache; ``ACCELERATOR_BATCH_FACTOR`` elsewhere."""
    return 1 if device.type == "cpu" else ACCELERATOR_BATCH_FACTOR


def bf16_native(device: torch.device) -> bool:
    """Whether ``device`` has bfloat16 matrix units (AMX / AVX512-BF16 on CPU, Ampere+ on CUDA)."""
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported()
    if device.type == "cpu":
        return bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())
    return False


def pick_device(name: str) -> torch.device:
    """``auto`` takes CUDA when present. The torch thread count is set (``configure``) on every
    device: a CUDA run's ray draws, carving and image work run on the CPU too. Set only for CPU
    runs, ``VISNERF_THREADS`` was ignored on CUDA and each process took every core (torch's
    default): five 2-thread trainings on one 16-core GPU node ran 16 threads each and stalled
    (bench/results/cuda_check/README.md)."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("error: --device cuda asked for, but no CUDA device is available")
    configure()
    return device
