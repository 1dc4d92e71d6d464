"""Movie jobs: a camera and parameter path rendered to an MP4 or GIF file in the background.

A checked request (``movie_plans.prepare_movie``) becomes a job here, bounded: at most ``running``
jobs render at once and ``queued`` more wait, ``per_client`` of them from one client. A running
job's thread drives the movie writer (``visnerf.animation.movie.write_movie``) with the generator of
``movie_frames``, which renders one frame at a time in the render queue's background lane.

Finished files live in a temporary folder, made by the first job and removed at shutdown; a
finished job is forgotten, and its file deleted, ``keep_s`` after it ended, or earlier when the
files together pass ``max_disk_bytes`` (oldest first). Jobs live in memory only: they do not
survive a restart.
"""

import logging
import math
import secrets
import shutil
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from visnerf.animation.movie import write_movie
from visnerf.animation.path import PathError, sample_frames
from visnerf_server.metrics import Metrics
from visnerf_server.movie_frames import movie_frames
from visnerf_server.movie_plans import MovieLimits, MoviePlan
from visnerf_server.registry import SceneRegistry
from visnerf_server.render_queue import QueueFullError, RenderQueue
from visnerf_server.schemas import MOVIE_MEDIA_TYPES, MovieJobStatus, MovieState

logger = logging.getLogger(__name__)

SWEEP_EVERY_S = 10.0
"""How often an idle job thread deletes expired files."""
MAX_JOBS_KEPT = 1000
"""Finished jobs remembered at most (the oldest forgotten first), whatever ``keep_s`` says."""
RETRY_UNKNOWN_S = 10
"""Retry-After for a full job queue while no running job can estimate its end yet."""


class TooManyJobs(RuntimeError):
    """Every job slot (or this client's share) is taken (429; ``retry_after_s`` estimated)."""

    def __init__(self, message: str, retry_after_s: int) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s


@dataclass(eq=False)
class MovieJob:
    id: str
    plan: MoviePlan
    client: str
    file: Path
    created: float
    state: MovieState = "queued"
    frames_done: int = 0
    error: str | None = None
    started: float | None = None
    finished: float | None = None
    cancel: threading.Event = field(default_factory=threading.Event)
    ended: threading.Event = field(default_factory=threading.Event)
    """Set once the job is finished and its thread has let go of it (file closed or removed)."""

    @property
    def scene_id(self) -> str:
        return self.plan.scene.id

    @property
    def format(self) -> str:
        return self.plan.settings.format

    @property
    def media_type(self) -> str:
        return MOVIE_MEDIA_TYPES[self.format]

    @property
    def download_name(self) -> str:
        return f"{self.scene_id}-{self.id[:8]}.{self.format}"

    @property
    def active(self) -> bool:
        return self.state in ("queued", "running")

    def status(self, now: float) -> MovieJobStatus:
        total = self.plan.n_frames
        speed = None
        if self.started is not None and self.frames_done > 0:
            speed = self.frames_done / max((self.finished or now) - self.started, 1e-6)
        left = None
        if self.state == "done":
            left = 0.0
        elif self.state == "running" and speed is not None:
            left = (total - self.frames_done) / speed
        return MovieJobStatus(
            job_id=self.id,
            scene_id=self.scene_id,
            state=self.state,
            frames_done=self.frames_done,
            frames_total=total,
            error=self.error,
            frames_per_second=None if speed is None else round(speed, 3),
            seconds_left=None if left is None else round(left, 2),
        )


class MovieJobs:
    """The server's movie jobs, their threads and their files."""

    def __init__(
        self,
        limits: MovieLimits,
        queue: RenderQueue,
        registry: SceneRegistry,
        metrics: Metrics,
        parent_dir: Path | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.limits = limits
        self.queue = queue
        self.registry = registry
        self.metrics = metrics
        self.clock = clock
        self._parent_dir = parent_dir
        self._folder: Path | None = None  # made by the first job: a server that makes no movie leaves nothing
        self._jobs: dict[str, MovieJob] = {}
        self._queued: deque[MovieJob] = deque()
        self._cond = threading.Condition()
        self._threads: list[threading.Thread] = []
        self._closed = False

    @property
    def folder(self) -> Path:
        """The folder of this server's movie files, made on first use."""
        with self._cond:
            if self._folder is None:
                if self._parent_dir is not None:
                    self._parent_dir.mkdir(parents=True, exist_ok=True)
                self._folder = Path(tempfile.mkdtemp(prefix="visnerf-movies-", dir=self._parent_dir))
            return self._folder

    # --- requests ------------------------------------------------------------------------------

    def submit(self, plan: MoviePlan, client: str) -> MovieJob:
        """Queue a job; raises TooManyJobs when every slot (or the client's share) is taken,
        QueueFullError once the server is stopping."""
        with self._cond:
            self._sweep()
            if self._closed:
                raise QueueFullError("server is shutting down")
            active = [job for job in self._jobs.values() if job.active]
            capacity = self.limits.running + self.limits.queued
            if len(active) >= capacity:
                raise TooManyJobs(
                    f"the server has its limit of {capacity} movie jobs queued or running "
                    f"(movie_jobs_running {self.limits.running} + movie_jobs_queued {self.limits.queued})",
                    self._retry_after(active),
                )
            mine = [job for job in active if job.client == client]
            if len(mine) >= self.limits.per_client:
                raise TooManyJobs(
                    f"this client has its limit of {self.limits.per_client} movie jobs queued or running "
                    "(movie_jobs_per_client)",
                    self._retry_after(mine),
                )
            job_id = secrets.token_urlsafe(12)
            job = MovieJob(job_id, plan, client, self.folder / f"{job_id}.{plan.settings.format}", self.clock())
            self._jobs[job_id] = job
            self._queued.append(job)
            self._update_gauge()
            if len(self._threads) < min(self.limits.running, len(active) + 1):
                thread = threading.Thread(target=self._work, name=f"movie-{len(self._threads)}", daemon=True)
                self._threads.append(thread)
                thread.start()
            self._cond.notify()
        logger.info("movie job %s queued: scene %r, %d frames", job_id, plan.scene.id, plan.n_frames)
        return job

    def get(self, job_id: str) -> MovieJob | None:
        with self._cond:
            self._sweep()
            return self._jobs.get(job_id)

    def delete(self, job_id: str) -> MovieJob | None:
        """Cancel a queued or running job: its state becomes ``cancelled`` at once, its file goes
        once its frame has stopped (``ended``). Forget a finished job and delete its file."""
        with self._cond:
            job = self._jobs.get(job_id)
            if job is None:
                return None
            if job.state == "queued":
                self._queued.remove(job)
                self._end(job, "cancelled")
                job.ended.set()
            elif job.state == "running":
                job.cancel.set()  # its frame stops within a chunk of rays; its thread then lets go
                self._end(job, "cancelled")
            else:
                self._forget(job)
            return job

    def now(self) -> float:
        return self.clock()

    # --- shutting down -------------------------------------------------------------------------

    def close(self) -> None:
        """Refuse new jobs, cancel the queued ones and tell the running ones to stop."""
        with self._cond:
            self._closed = True
            for job in self._queued:
                self._end(job, "cancelled")
                job.ended.set()
            self._queued.clear()
            for job in self._jobs.values():
                job.cancel.set()
            self._cond.notify_all()

    def shutdown(self) -> None:
        """``close``, wait for the job threads (their frames stop within a chunk of rays once the
        render queue is closed too), then remove the folder of files."""
        self.close()
        for thread in list(self._threads):
            thread.join()
        if self._folder is not None:
            shutil.rmtree(self._folder, ignore_errors=True)

    # --- bookkeeping (callers hold ``_cond``) ---------------------------------------------------

    def _update_gauge(self) -> None:
        self.metrics.movie_jobs_active.set(sum(job.active for job in self._jobs.values()))

    def _retry_after(self, jobs: list[MovieJob]) -> int:
        now = self.clock()
        left = [s.seconds_left for s in (job.status(now) for job in jobs) if s.seconds_left is not None]
        return max(1, math.ceil(min(left))) if left else RETRY_UNKNOWN_S

    def _end(self, job: MovieJob, state: MovieState, error: str | None = None) -> None:
        job.state = state
        job.error = error
        job.finished = self.clock()
        if state != "done":
            job.file.unlink(missing_ok=True)
        self.metrics.movie_jobs_finished.labels(state).inc()
        self._update_gauge()

    def _forget(self, job: MovieJob) -> None:
        self._jobs.pop(job.id, None)
        job.file.unlink(missing_ok=True)

    def _sweep(self) -> None:
        """Forget the jobs finished more than ``keep_s`` ago, and the oldest beyond MAX_JOBS_KEPT."""
        now = self.clock()
        finished = sorted((job for job in self._jobs.values() if job.finished is not None),
                          key=lambda j: j.finished or 0.0)
        excess = len(finished) - MAX_JOBS_KEPT
        for i, job in enumerate(finished):
            if i < excess or now - job.finished > self.limits.keep_s:  # type: ignore[operator]
                self._forget(job)

    def _make_room(self, job: MovieJob) -> str | None:
        """Delete the oldest finished files until ``job``'s fits in ``max_disk_bytes``; the reason
        it cannot, if it alone is over the limit."""
        size = job.file.stat().st_size
        budget = self.limits.max_disk_bytes
        if size > budget:
            return (
                f"the movie file of {size} bytes exceeds this server's limit of {budget} bytes (movie_max_disk_bytes)"
            )
        done = sorted((j for j in self._jobs.values() if j.state == "done" and j is not job),
                      key=lambda j: j.finished or 0.0)
        total = size + sum(j.file.stat().st_size for j in done if j.file.exists())
        for old in done:
            if total <= budget:
                break
            total -= old.file.stat().st_size if old.file.exists() else 0
            self._forget(old)
        return None

    # --- the job threads -----------------------------------------------------------------------

    def _next_job(self) -> MovieJob | None:
        with self._cond:
            while not self._queued:
                if self._closed:
                    return None
                self._cond.wait(SWEEP_EVERY_S)
                self._sweep()
            job = self._queued.popleft()
            job.state = "running"
            job.started = self.clock()
            self.metrics.movie_jobs_started.inc()
            return job

    def _work(self) -> None:
        while (job := self._next_job()) is not None:
            try:
                self._run(job)
            except Exception as exc:  # a bug: fail this job, keep the thread for the next ones
                logger.exception("movie job %s failed", job.id)
                with self._cond:
                    if job.active:
                        self._end(job, "failed", f"internal error: {type(exc).__name__}")
            finally:
                job.ended.set()

    def _run(self, job: MovieJob) -> None:
        plan = job.plan
        failure: list[str] = []

        def progress(done: int, total: int) -> None:
            job.frames_done = done

        try:
            specs = sample_frames(plan.path, plan.settings.fps, plan.scene.renderer.info.params)
            frames = movie_frames(plan, specs, self.registry, self.queue, job.cancel, failure, self.on_frame)
            result = write_movie(frames, job.file, plan.settings, plan.n_frames, progress)
            if result.interrupted and not failure:
                failure.append(result.stopped_by or "the frames stopped early")
        except PathError as exc:  # parse_path checked the path: not expected, but the client's path
            failure.append(str(exc))
        with self._cond:
            if job.state != "running":  # cancelled (DELETE, shutdown) while its frame stopped
                job.file.unlink(missing_ok=True)
            elif job.cancel.is_set():
                self._end(job, "cancelled")
            elif failure:
                self._end(job, "failed", failure[0])
            elif (error := self._make_room(job)) is not None:
                self._end(job, "failed", error)
            else:
                self._end(job, "done")
        logger.info("movie job %s %s after %d frames", job.id, job.state, job.frames_done)

    def on_frame(self) -> None:
        self.metrics.movie_frames.inc()
