"""Marching a frame's ray chunks on several threads (CPU inference).

Within a frame most operations are small (a few thousand samples per segment): too small for
torch's intra-op threads to share well, and each costs a fixed dispatch overhead. The chunks of
rays are independent, so on the CPU they go to one Python thread per core, each running its
operations on a single intra-op thread (torch releases the GIL inside an operation, and so do
the compiled passes of ``march_kernel``, ``vm_kernel`` and ``empty_space_kernel``).
bench/results/render_speed.md measures it against intra-op threads.

The cores are shared by every frame being rendered at once (a server renders several). The
caller of ``map_chunks`` marches chunks itself and borrows helper threads only for the cores no
other frame's marching holds: a frame alone spreads over every core, two frames at once on two
cores march one core each, with no thread waiting for another frame's chunks to finish. On two
cores, 128x128 frames of the bundled scenes in two threads at once made 14.6 to 16.0 frames/s
against 12.8 to 13.6 for one thread of frames on both cores (the notes of
bench/results/server_load.md).

A participating thread runs one intra-op thread while it marches (``torch.set_num_threads`` acts
on the calling thread's OpenMP team, so frames at once do not disturb each other); the caller's
count comes back after. Autograd mode is thread-local, so each helper runs under the caller's
grad / inference mode.
"""

import itertools
import os
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor, wait

import torch

MAX_HELPERS = max(64, os.cpu_count() or 1)
"""Helper threads at most, over every frame at once (a thread is made when first needed); at
most ``workers - 1`` are borrowed at any time."""

_lock = threading.Lock()
_busy = 0
"""Threads marching chunks now, every frame's callers and helpers together."""
_pool: ThreadPoolExecutor | None = None


def _executor() -> ThreadPoolExecutor:
    global _pool
    with _lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=MAX_HELPERS, thread_name_prefix="visnerf-chunk")
        return _pool


def chunk_workers(device: torch.device) -> int:
    """Threads to march a frame's chunks on: the intra-op thread count on the CPU, 1 elsewhere."""
    return torch.get_num_threads() if device.type == "cpu" else 1


def busy_threads() -> int:
    """Threads marching chunks now, over every frame (0 when none is)."""
    return _busy


def _claim(workers: int, n_chunks: int) -> int:
    """Count the caller and the helpers it may borrow (the cores of ``workers`` that no other
    frame's marching holds, at most one per chunk beyond the caller's); returns the helpers."""
    global _busy
    with _lock:
        helpers = max(0, min(workers - 1 - _busy, n_chunks - 1))
        _busy += 1 + helpers
    return helpers


def _release() -> None:
    global _busy
    with _lock:
        _busy -= 1


def _submit(helper: Callable[[], None], helpers: int, futures: "list[Future[None]]") -> None:
    """Start ``helpers`` helpers on the pool, appending each to ``futures`` as it starts (so that
    the caller waits for those that did); the cores of those not started are released."""
    pool = _executor()
    try:
        for _ in range(helpers):
            futures.append(pool.submit(helper))
    finally:
        for _ in range(helpers - len(futures)):  # not started: their cores were never taken
            _release()


def map_chunks(fn: Callable[[int], None], n_chunks: int, workers: int) -> None:
    """Call ``fn(i)`` for every chunk ``i``, on up to ``workers`` threads (the caller's and helpers
    for the cores no other frame's chunks hold). The first exception of a chunk reaches the caller
    once no chunk is running any more; the chunks not started by then are skipped."""
    if workers <= 1 or n_chunks <= 1:
        for i in range(n_chunks):
            fn(i)
        return
    helpers = _claim(workers, n_chunks)
    grad, inference = torch.is_grad_enabled(), torch.is_inference_mode_enabled()
    order = itertools.count()  # the next chunk; next() on it is atomic under the GIL
    failed = threading.Event()

    def march() -> None:
        for i in order:
            if i >= n_chunks or failed.is_set():
                return
            try:
                fn(i)
            except BaseException:
                failed.set()
                raise

    def helper() -> None:
        try:
            if torch.get_num_threads() != 1:
                torch.set_num_threads(1)
            with torch.inference_mode(inference), torch.set_grad_enabled(grad):
                march()
        finally:
            _release()  # this core is free for another frame as soon as no chunk is left

    futures: list[Future[None]] = []
    error: BaseException | None = None
    previous = torch.get_num_threads()
    try:
        _submit(helper, helpers, futures)
        torch.set_num_threads(1)
        march()
    except BaseException as caught:  # a chunk failed (or the render was cancelled)
        error = caught
    finally:
        torch.set_num_threads(previous)
        _release()
        # The running chunks end before the caller goes on (they write into its buffers).
        wait(futures)
    try:
        if error is None:
            error = next((e for e in (f.exception() for f in futures) if e is not None), None)
        if error is not None:
            raise error
    finally:
        # The exception holds this frame in its traceback, and the frame the futures that hold
        # exceptions: a cycle only the garbage collector frees, with every tensor of the render's
        # frames (tens of megabytes for a cancelled large frame, which a server collected rarely
        # and never trimmed).
        futures = error = None  # noqa: F841
