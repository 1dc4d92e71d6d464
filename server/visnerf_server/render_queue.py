"""A bounded render queue: a fixed pool of render threads, a fixed number of waiting slots, and
three lanes served in order of priority.

When every slot is taken, ``submit`` refuses at once (the server answers 503 with Retry-After), so the
backlog never grows without bound. A free worker takes the oldest job of the first non-empty lane:
interactive previews, then full-quality frames, then background work (occupancy grid builds), so
a preview never waits behind a queued full frame. ``preview_workers`` more threads take previews
only, so that a preview does not wait for the full frames running either: 1440x1440 frames that
kept every general worker busy for seconds each left previews unanswered (server_load.md). A
steady stream of previews delays full frames; each client's share is bounded by its rate limit.

A job marked ``large`` (a frame of many pixels) never runs beside another large one: two at once
would each take twice as long and hold twice the memory, while small frames beside a large one
keep the other cores busy. A worker passes over a large job that must wait and takes the next
small one; the large job starts as soon as the large one running ends. Large jobs thus wait for
each other in turn, so ``run`` and ``run_async`` refuse a large job at once
(``WouldOutwaitError``, a QueueFullError with the wait as its Retry-After) when the large jobs
ahead of it would hold it past its caller's limit: its caller would otherwise wait out the
limit and get a 504 for a frame stopped half drawn, its cores spent for nothing. The wait is
estimated from the seconds per unit of cost of the large jobs finished so far (none yet: no
refusal), and a large job with nothing ahead of it is never refused.

Each job may carry a ``threading.Event`` its work polls (a render asks it between chunks of rays,
``visnerf.rendering.cancel``). Callers wait with a time limit: a job still queued when the limit
passes is dropped (503); one running is told to stop through its event (504), which frees the
worker within a chunk of rays instead of when the frame is done. A caller that goes away (its
task cancelled: the HTTP client disconnected, the stream closed) stops its job the same way.
``close`` (``visnerf serve`` calls it on SIGTERM) and ``shutdown`` stop every running job and fail
the queued ones with QueueFullError, so a stop never waits for a large frame to finish.
"""

import asyncio
import concurrent.futures
import threading
import time
import weakref
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any, TypeVar

from visnerf.inference import RenderCancelled
from visnerf_server.metrics import Metrics

T = TypeVar("T")

_TIMEOUT_ERRORS = (TimeoutError, asyncio.TimeoutError, concurrent.futures.TimeoutError)


class QueueFullError(RuntimeError):
    """Every render slot is taken (or the server is stopping)."""


class WouldOutwaitError(QueueFullError):
    """A large job would wait behind the large jobs ahead of it past its caller's limit."""

    def __init__(self, wait_s: float, limit_s: float) -> None:
        super().__init__(f"a large frame would wait about {wait_s:.0f} s for the large frames ahead of it "
                         f"and not be done within the limit of {limit_s:g} s")
        self.retry_after_s = wait_s
        """Seconds until the large frames ahead are estimated to be done."""


LARGE_RATE_WEIGHT = 0.5
"""Weight of the newest finished large job in the estimate of seconds per unit of cost."""


class RenderTimeoutError(RuntimeError):
    """The render did not finish within the request's time limit."""

    def __init__(self, started: bool) -> None:
        super().__init__("render still running" if started else "render still waiting in the queue")
        self.started = started


class Lane(IntEnum):
    """Priority of a job: lower values are served first."""

    PREVIEW = 0
    """Interactive previews (cheap by their pixel budget)."""
    FULL = 1
    """Full-quality frames."""
    BACKGROUND = 2
    """Work no request waits for (occupancy grids of parameter settings)."""

    @classmethod
    def of_quality(cls, quality: str) -> "Lane":
        return cls.PREVIEW if quality == "preview" else cls.FULL


@dataclass(eq=False)
class _Job:
    fn: Callable[[], Any]
    lane: Lane
    cancel: threading.Event
    future: concurrent.futures.Future = field(default_factory=concurrent.futures.Future)
    started: bool = False
    large: bool = False
    cost: float = 0.0
    """What the job costs (a frame's pixels, ``costs.FrameLimits.cost``); 0: unknown."""
    started_at: float = 0.0


class RenderQueue:
    """``workers`` render threads for every lane, ``preview_workers`` for previews only, and
    ``queue_size`` waiting slots shared by all lanes."""

    def __init__(self, workers: int, queue_size: int, metrics: Metrics, preview_workers: int = 0) -> None:
        self.capacity = workers + preview_workers + queue_size
        self._workers = workers
        self._preview_workers = preview_workers
        self._preview_threads: list[threading.Thread] = []
        self._metrics = metrics
        self._cond = threading.Condition()
        self._lanes: dict[Lane, deque[_Job]] = {lane: deque() for lane in Lane}
        self._active: set[_Job] = set()
        self._threads: list[threading.Thread] = []
        self._waiting = 0
        self._running = 0
        self._large_running = 0
        self._large_rate: float | None = None
        """Seconds per unit of cost of the large jobs finished so far (weighted to the newest)."""
        self._closed = False

    @property
    def waiting(self) -> int:
        return self._waiting

    @property
    def running(self) -> int:
        return self._running

    @property
    def closed(self) -> bool:
        return self._closed

    def _update_gauges(self) -> None:
        self._metrics.queue_depth.set(self._waiting)
        self._metrics.in_flight.set(self._running)

    def submit(
        self,
        fn: Callable[[], T],
        lane: Lane = Lane.FULL,
        cancel: threading.Event | None = None,
        large: bool = False,
        cost: float = 0.0,
        limit_s: float | None = None,
    ) -> "concurrent.futures.Future[T]":
        """Queue ``fn`` in ``lane``; raises QueueFullError when no slot is free (never blocks).

        ``cancel`` is set when the job should stop (its caller's deadline passed or it left, or the
        queue shuts down); ``fn`` should poll it. Cancelling the future drops a job not yet started.
        A ``large`` job never runs beside another large one; with its ``cost`` and its caller's
        ``limit_s`` it is refused (WouldOutwaitError) when the large jobs ahead would hold it past
        that limit.
        """
        job = _Job(fn, lane, cancel if cancel is not None else threading.Event(), large=large, cost=cost)
        with self._cond:
            if self._closed or self._waiting + self._running >= self.capacity:
                self._metrics.rejected.inc()
                raise QueueFullError("server is shutting down" if self._closed else "render queue is full")
            if large and limit_s is not None and cost > 0.0 and self._large_rate is not None:
                wait = self._large_wait_s()
                if wait > 0.0 and wait + cost * self._large_rate > limit_s:
                    self._metrics.rejected.inc()
                    raise WouldOutwaitError(wait, limit_s)
            self._lanes[lane].append(job)
            self._waiting += 1
            self._update_gauges()
            if len(self._threads) < min(self._workers, self._waiting + self._running):
                thread = threading.Thread(target=self._work, name=f"render-{len(self._threads)}", daemon=True)
                self._threads.append(thread)
                thread.start()
            if lane == Lane.PREVIEW and len(self._preview_threads) < self._preview_workers:
                thread = threading.Thread(target=self._work, args=(True,), daemon=True,
                                          name=f"render-preview-{len(self._preview_threads)}")
                self._preview_threads.append(thread)
                thread.start()
            self._cond.notify_all()  # a preview-only worker woken for a full frame would leave it
        # a weak reference: a future keeps its callbacks once done, and the job holds the future,
        # whose exception holds the render's frames (the cycle ``_work`` explains); a job dropped
        # before it started is still in its lane when the callback runs
        dropped = weakref.ref(job)
        job.future.add_done_callback(lambda _: self._forget_if_dropped(dropped()))
        return job.future

    def _large_wait_s(self) -> float:
        """Seconds until the large jobs running and queued are estimated to be done (under the lock)."""
        assert self._large_rate is not None
        now = time.monotonic()
        running = sum(max(0.0, job.cost * self._large_rate - (now - job.started_at))
                      for job in self._active if job.large)
        queued = sum(job.cost * self._large_rate for lane in self._lanes.values() for job in lane
                     if job.large and not job.future.cancelled())
        return running + queued

    def _forget_if_dropped(self, job: _Job | None) -> None:
        """A job cancelled before it started gives its slot back at once (None: a job no longer
        held anywhere, so in no lane)."""
        if job is None:
            return
        with self._cond:
            if job.started or not job.future.cancelled():
                return
            try:
                self._lanes[job.lane].remove(job)
                taken_off_here = True
            except ValueError:  # a worker or shutdown took it off, and notifies
                taken_off_here = False
            self._waiting -= 1
            self._update_gauges()
        if taken_off_here:
            job.future.set_running_or_notify_cancel()  # so that concurrent.futures.wait() sees it done

    def _next_job(self, previews_only: bool = False) -> _Job | None:
        """The job to run next (waits for one); None once the queue is closed and empty."""
        lanes = [self._lanes[Lane.PREVIEW]] if previews_only else list(self._lanes.values())
        with self._cond:
            while True:
                for lane in lanes:
                    i = 0
                    while i < len(lane):
                        job = lane[i]
                        if job.large and self._large_running and not job.future.cancelled():
                            i += 1  # waits for the large one running; a small one behind it may go
                            continue
                        del lane[i]
                        if job.future.set_running_or_notify_cancel():
                            job.started = True
                            job.started_at = time.monotonic()
                            self._waiting -= 1
                            self._running += 1
                            self._large_running += job.large
                            self._active.add(job)
                            self._update_gauges()
                            return job
                        # cancelled meanwhile: its callback does the accounting
                if self._closed:
                    return None
                self._cond.wait()

    def _work(self, previews_only: bool = False) -> None:
        while (job := self._next_job(previews_only)) is not None:
            try:
                result = job.fn()
            except BaseException as exc:  # handed to whoever waits on the future
                self._finish(job, done=False)
                if isinstance(exc, RenderCancelled):  # a stop that was asked for: its frames tell
                    exc.with_traceback(None)  # nothing, and asyncio's waits keep cycles of their own
                job.future.set_exception(exc)
            else:
                self._finish(job, done=True)
                job.future.set_result(result)
            finally:
                # An exception holds in its traceback every frame it passed; where such a frame
                # holds the future that holds the exception, the two form a cycle that only the
                # garbage collector frees, with every tensor of the render's frames. A server
                # collects that rarely and never trims what it frees late: cancelled 1440x1440
                # renders left hundreds of megabytes behind. So the frames that hand on or wait
                # for a job's outcome drop the job and its futures before they end.
                job = result = None  # noqa: F841

    def _finish(self, job: _Job, done: bool) -> None:
        """Account for a job that ended (``done``: it returned; a large one's time then updates the
        estimate of seconds per unit of cost)."""
        with self._cond:
            if done and job.large and job.cost > 0.0:
                rate = (time.monotonic() - job.started_at) / job.cost
                old = self._large_rate
                self._large_rate = rate if old is None else LARGE_RATE_WEIGHT * rate + (1 - LARGE_RATE_WEIGHT) * old
            self._active.discard(job)
            self._running -= 1
            self._large_running -= job.large
            self._update_gauges()
            if job.large:
                self._cond.notify_all()  # a large job waiting may start now

    def _stopped(self, future: concurrent.futures.Future, cancel: threading.Event) -> bool:
        """Stop a job its caller gave up on: drop it if queued, else tell it to stop. True when
        it had started."""
        cancel.set()
        started = not future.cancel()
        if started and not future.done():
            self._metrics.cancelled.inc()
        return started

    def run(
        self,
        fn: Callable[[], T],
        timeout: float,
        lane: Lane = Lane.FULL,
        cancel: threading.Event | None = None,
        large: bool = False,
        cost: float = 0.0,
    ) -> T:
        """Run ``fn`` and wait for it at most ``timeout`` seconds (blocking; for sync callers).
        Past the limit the job is dropped or stopped and RenderTimeoutError raised. A ``large``
        job of ``cost`` that would wait past the limit is refused at once (WouldOutwaitError)."""
        cancel = cancel if cancel is not None else threading.Event()
        future = self.submit(fn, lane, cancel, large=large, cost=cost, limit_s=timeout)
        try:
            return future.result(timeout=timeout)
        except _TIMEOUT_ERRORS:
            raise RenderTimeoutError(started=self._stopped(future, cancel)) from None
        except RenderCancelled:
            if self._closed:
                raise QueueFullError("server is shutting down") from None
            raise
        finally:
            del future  # no cycle through the future (``_work``)

    async def run_async(
        self,
        fn: Callable[[], T],
        timeout: float,
        lane: Lane = Lane.FULL,
        cancel: threading.Event | None = None,
        large: bool = False,
        cost: float = 0.0,
    ) -> T:
        """``run`` for coroutines: waits without blocking the event loop. When the waiting task is
        cancelled (its client left), the job is dropped or stopped too."""
        cancel = cancel if cancel is not None else threading.Event()
        future = self.submit(fn, lane, cancel, large=large, cost=cost, limit_s=timeout)
        waiter = asyncio.wrap_future(future)
        waiter.add_done_callback(lambda f: f.cancelled() or f.exception())  # never "unretrieved"
        try:
            return await asyncio.wait_for(asyncio.shield(waiter), timeout)
        except _TIMEOUT_ERRORS:
            waiter.cancel()  # nobody waits for the result any more (nor after this loop has closed)
            raise RenderTimeoutError(started=self._stopped(future, cancel)) from None
        except asyncio.CancelledError:
            waiter.cancel()
            self._stopped(future, cancel)
            raise
        except RenderCancelled:
            if self._closed:
                raise QueueFullError("server is shutting down") from None
            raise
        finally:
            del future, waiter  # no cycle through the futures (``_work``)

    def close(self) -> None:
        """Refuse new work, fail the queued jobs with QueueFullError (the server answers 503) and
        tell the running ones to stop (a render stops within a chunk of rays); returns at once."""
        with self._cond:
            self._closed = True
            queued = [job for lane in self._lanes.values() for job in lane]
            for lane in self._lanes.values():
                lane.clear()
            running = list(self._active)
            self._cond.notify_all()
        for job in queued:
            if not job.future.set_running_or_notify_cancel():
                continue  # its caller cancelled it meanwhile; its callback gave the slot back
            with self._cond:
                self._waiting -= 1
                self._update_gauges()
            job.future.set_exception(QueueFullError("server is shutting down"))
        for job in running:
            job.cancel.set()

    def shutdown(self) -> None:
        """``close``, then wait for the workers to end (each finishes the job it is running,
        told to stop)."""
        self.close()
        for thread in [*self._threads, *self._preview_threads]:
            thread.join()
