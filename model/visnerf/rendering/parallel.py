"""Marching a frame's ray chunks on several threads (CPU inference).

Within a frame most operations are small (a few thousand samples per segment): too small for
torch's intra-op threads to share well, and each costs a fixed dispatch overhead. The chunks of
rays are independent, so on the CPU they go to one Python thread per core, each running its
operations on a single intra-op thread (torch releases the GIL inside an operation, and so do
the compiled passes of ``march_kernel`` and ``vm_kernel``).
bench/results/render_speed.md measures it against intra-op threads.

The intra-op thread count is process-wide in torch, so it is set to one for the length of the
map and restored after; maps are serialised by a lock. Autograd mode is thread-local, so each
worker runs under the caller's grad / inference mode.
"""

import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor, wait

import torch

_lock = threading.Lock()
_pool: ThreadPoolExecutor | None = None
_pool_size = 0


def _executor(workers: int) -> ThreadPoolExecutor:
    global _pool, _pool_size
    if _pool is None or _pool_size != workers:
        if _pool is not None:
            _pool.shutdown(wait=True)
        _pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="visnerf-chunk")
        _pool_size = workers
    return _pool


def chunk_workers(device: torch.device) -> int:
    """Threads to march chunks on: the intra-op thread count on the CPU, 1 elsewhere."""
    return torch.get_num_threads() if device.type == "cpu" else 1


def map_chunks(fn: Callable[[int], None], n_chunks: int, workers: int) -> None:
    """Call ``fn(i)`` for every chunk ``i``, on ``workers`` threads when more than one. The first
    exception of a chunk reaches the caller once no chunk is running any more; the chunks not
    started by then are skipped."""
    if workers <= 1 or n_chunks <= 1:
        for i in range(n_chunks):
            fn(i)
        return
    grad, inference = torch.is_grad_enabled(), torch.is_inference_mode_enabled()

    def run(i: int) -> None:
        with torch.inference_mode(inference), torch.set_grad_enabled(grad):
            fn(i)

    with _lock:
        previous = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            pool = _executor(workers)
            futures = [pool.submit(run, i) for i in range(n_chunks)]
            try:
                for future in futures:
                    future.result()
            except BaseException:
                # A chunk failed (or the render was cancelled): drop the chunks not started and let
                # the running ones end before the caller goes on (they write into its buffers).
                for future in futures:
                    future.cancel()
                wait(futures)
                raise
            finally:
                # The failed chunk's exception holds this frame in its traceback, and the frame the
                # futures that hold the exceptions: a cycle only the garbage collector frees, with
                # every tensor of the render's frames (65 MB a cancelled 1440x1440 frame, which a
                # server collected rarely and never trimmed).
                futures = future = None  # noqa: F841
        finally:
            torch.set_num_threads(previous)
