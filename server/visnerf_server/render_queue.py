"""A bounded render queue: a fixed pool of render threads and a fixed number of waiting slots.

When every slot is taken, ``submit`` refuses at once (the server answers 503 with Retry-After), so the
backlog never grows without bound. Callers wait with a time limit: a render still queued when the
limit passes is cancelled (503); one still running is abandoned to finish on its own (504).
"""

import asyncio
import concurrent.futures
import threading
from collections.abc import Callable
from typing import TypeVar

from visnerf_server.metrics import Metrics

T = TypeVar("T")

_TIMEOUT_ERRORS = (TimeoutError, asyncio.TimeoutError, concurrent.futures.TimeoutError)


class QueueFullError(RuntimeError):
    """Every render slot is taken."""


class RenderTimeoutError(RuntimeError):
    """The render did not finish within the request's time limit."""

    def __init__(self, started: bool) -> None:
        super().__init__("render still running" if started else "render still waiting in the queue")
        self.started = started


class _Job:
    __slots__ = ("started",)

    def __init__(self) -> None:
        self.started = False


class RenderQueue:
    """``workers`` render threads plus ``queue_size`` waiting slots."""

    def __init__(self, workers: int, queue_size: int, metrics: Metrics) -> None:
        self.capacity = workers + queue_size
        self._metrics = metrics
        self._executor = concurrent.futures.ThreadPoolExecutor(
            max_workers=workers, thread_name_prefix="render"
        )
        self._slots = threading.BoundedSemaphore(self.capacity)
        self._lock = threading.Lock()
        self._waiting = 0
        self._running = 0
        self._closed = False

    @property
    def waiting(self) -> int:
        return self._waiting

    @property
    def running(self) -> int:
        return self._running

    def _update_gauges(self) -> None:
        self._metrics.queue_depth.set(self._waiting)
        self._metrics.in_flight.set(self._running)

    def submit(self, fn: Callable[[], T]) -> "concurrent.futures.Future[T]":
        """Queue ``fn``; raises QueueFullError when no slot is free (never blocks)."""
        if self._closed or not self._slots.acquire(blocking=False):
            self._metrics.rejected.inc()
            raise QueueFullError("render queue is full")
        job = _Job()
        with self._lock:
            self._waiting += 1
            self._update_gauges()

        def run() -> T:
            with self._lock:
                job.started = True
                self._waiting -= 1
                self._running += 1
                self._update_gauges()
            try:
                return fn()
            finally:
                with self._lock:
                    self._running -= 1
                    self._update_gauges()

        def finished(_: concurrent.futures.Future) -> None:
            with self._lock:
                if not job.started:  # cancelled while queued
                    self._waiting -= 1
                    self._update_gauges()
            self._slots.release()

        try:
            future = self._executor.submit(run)
        except RuntimeError as exc:  # executor shut down
            with self._lock:
                self._waiting -= 1
                self._update_gauges()
            self._slots.release()
            raise QueueFullError("server is shutting down") from exc
        future.add_done_callback(finished)
        return future

    def run(self, fn: Callable[[], T], timeout: float) -> T:
        """Render ``fn`` and wait for it at most ``timeout`` seconds (blocking; for sync handlers)."""
        future = self.submit(fn)
        try:
            return future.result(timeout=timeout)
        except _TIMEOUT_ERRORS:
            raise RenderTimeoutError(started=not future.cancel()) from None

    async def run_async(self, fn: Callable[[], T], timeout: float) -> T:
        """``run`` for coroutines: waits without blocking the event loop."""
        future = self.submit(fn)
        waiter = asyncio.wrap_future(future)
        waiter.add_done_callback(lambda f: f.cancelled() or f.exception())  # never "unretrieved"
        try:
            return await asyncio.wait_for(asyncio.shield(waiter), timeout)
        except _TIMEOUT_ERRORS:
            raise RenderTimeoutError(started=not future.cancel()) from None
        except asyncio.CancelledError:
            future.cancel()
            raise

    def shutdown(self) -> None:
        """Refuse new work, drop what is queued and wait for the renders already running."""
        self._closed = True
        self._executor.shutdown(wait=True, cancel_futures=True)
