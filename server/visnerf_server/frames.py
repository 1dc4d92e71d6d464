"""Turning a render request into an encoded frame: validation against the scene, the frame cache,
the bounded render queue and image encoding. Shared by the HTTP render routes and the stream."""

import asyncio
import contextlib
import hashlib
import io
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from PIL import Image

from visnerf import inference
from visnerf.data.cameras import orbit_c2w
from visnerf.inference import CancelCheck, FrameView, Quality, RenderCancelled, SceneRenderer, choose_lens
from visnerf.runtime import release_free_memory
from visnerf_server.costs import FrameLimits
from visnerf_server.frame_cache import CachedFrame, FrameCache
from visnerf_server.metrics import Metrics
from visnerf_server.rate_limit import ClientRateLimiter
from visnerf_server.registry import Scene, default_view
from visnerf_server.render_queue import Lane, QueueFullError, RenderQueue
from visnerf_server.schemas import MEDIA_TYPES, MatrixCamera, RenderRequest

LARGE_FRAME_PIXELS = inference.TRIM_AFTER_PIXELS
"""Full frames of at least this many pixels (512x512) run one at a time (``render_queue``): a
1440x1440 frame holds a few hundred megabytes while it renders (docs/decisions.md#frames.blocks)."""


def is_large_frame(width: int, height: int, quality: str) -> bool:
    """A full frame of ``LARGE_FRAME_PIXELS`` or more: the render queue runs one such at a time."""
    return quality == "full" and width * height >= LARGE_FRAME_PIXELS


@dataclass(frozen=True)
class FrameJob:
    """A render request checked once (``prepare_frame``), handed on resolved."""

    scene: Scene
    view: FrameView
    """The frame as the scene's renderer checked it (``SceneRenderer.view``)."""
    format: str
    cost: float = 0.0
    """Rate-limit price: the frame's pixels, a preview pixel at ``FrameLimits.preview_pixel_cost``."""

    @property
    def width(self) -> int:
        return self.view.width

    @property
    def height(self) -> int:
        return self.view.height

    @property
    def quality(self) -> Quality:
        return self.view.quality

    @property
    def large(self) -> bool:
        """``is_large_frame`` of this frame."""
        return is_large_frame(self.width, self.height, self.quality)

    def key(self) -> tuple:
        """Identical requests (same scene version) give identical keys; starts with the scene id."""
        view = self.view
        return (
            self.scene.id,
            self.scene.version,
            tuple(round(float(x), 9) for x in view.c2w.reshape(-1)),
            None if view.fov_deg is None else round(view.fov_deg, 9),
            None if view.view_height is None else round(view.view_height, 9),
            view.width,
            view.height,
            view.values,
            view.quality,
            self.format,
        )

    def etag(self) -> str:
        return '"' + hashlib.sha256(repr(self.key()).encode()).hexdigest()[:32] + '"'


@dataclass(frozen=True)
class Frame:
    data: bytes
    media_type: str
    width: int
    height: int
    render_ms: float
    """Render time of this request (0 for cache hits)."""
    encode_ms: float
    queue_ms: float
    cache_hit: bool

    def timing_headers(self) -> dict[str, str]:
        if self.cache_hit:
            timing = "cache;desc=hit;dur=0"
        else:
            phases = (("queue", self.queue_ms), ("render", self.render_ms), ("encode", self.encode_ms))
            timing = ", ".join(f"{name};dur={ms:.1f}" for name, ms in phases)
        return {
            "X-Render-Time-Ms": f"{self.render_ms:.1f}",
            "Server-Timing": timing,
            "X-Cache": "hit" if self.cache_hit else "miss",
        }


def prepare_frame(scene: Scene, request: RenderRequest, limits: FrameLimits) -> FrameJob:
    """Check a request against the server's limits and the scene (``SceneRenderer.view``), once;
    ValueError names the problem (``costs.FrameTooLarge`` for a size over the limits). A size not
    given is the scene's trained size, scaled down to fit the limits."""
    default_w, default_h = limits.default_size(*scene.renderer.info.image_size, request.quality)
    width = request.width if request.width is not None else default_w
    height = request.height if request.height is not None else default_h
    limits.check(width, height, request.quality)
    camera = request.camera
    if camera is None:
        c2w = default_view(scene.renderer)
    elif isinstance(camera, MatrixCamera):
        c2w = np.asarray(camera.c2w, dtype=np.float64)
    else:
        c2w = orbit_c2w(camera.azimuth, camera.elevation, camera.distance)
    fov_deg, view_height = choose_lens(scene.renderer.info.camera, request.fov_deg, request.view_height,
                                       request.projection)
    view = scene.renderer.view(c2w, fov_deg, width, height, request.params, request.quality, view_height)
    return FrameJob(scene, view, request.format, limits.cost(width, height, request.quality))


def draw_in_lanes(queue: RenderQueue, renderer: SceneRenderer, view: FrameView, cancel: CancelCheck) -> np.ndarray:
    """``renderer.draw(view)``, a setting grid that falls due built in the queue's background lane:
    it counts against the queue's capacity like any render instead of taking CPU beside it, and a
    queue that takes no work now leaves it for a later frame."""
    own, build = renderer.setting_grid(view)
    if build is not None:
        try:
            future = queue.submit(build.run, Lane.BACKGROUND)
        except QueueFullError:
            build.drop()
        else:
            future.add_done_callback(lambda done: build.drop() if done.cancelled() else None)
    return renderer.draw(view, own, cancel)


def encode_image(image: np.ndarray, fmt: str, quality: int) -> bytes:
    buffer = io.BytesIO()
    pil = Image.fromarray(np.ascontiguousarray(image))
    if fmt == "png":
        pil.save(buffer, format="PNG", compress_level=1)
    elif fmt == "jpeg":
        pil.save(buffer, format="JPEG", quality=quality)
    elif fmt == "webp":
        pil.save(buffer, format="WEBP", quality=quality, method=2)
    else:
        raise ValueError(f"unknown image format {fmt!r}; use png, jpeg or webp")
    return buffer.getvalue()


@dataclass
class FrameRenderer:
    """Renders ``FrameJob``s through the cache, the client's rate limit and the bounded queue
    (previews in the queue's preview lane). A render stops early, between chunks of rays, when
    its deadline passes or its caller goes away (``render_queue``)."""

    queue: RenderQueue
    cache: FrameCache
    metrics: Metrics
    timeout_s: float
    jpeg_quality: int
    limiter: ClientRateLimiter | None = None
    """Per-client token buckets; None: no rate limit."""

    def _lookup(self, job: FrameJob) -> Frame | None:
        cached = self.cache.get(job.key())
        if cached is None:
            self.metrics.cache_misses.inc()
            return None
        self.metrics.cache_hits.inc()
        return Frame(cached.data, cached.media_type, cached.width, cached.height, 0.0, 0.0, 0.0, True)

    def _charge(self, job: FrameJob, client: str | None) -> None:
        """Take the frame's cost from the client's bucket (a cache hit costs nothing); RateLimited
        when it holds too little (the caller refuses the frame or waits, and counts which)."""
        if self.limiter is not None and client is not None:
            self.limiter.take(client, job.cost)

    def _refund(self, job: FrameJob, client: str | None) -> None:
        """The queue refused the frame: nothing was rendered, so nothing is owed."""
        if self.limiter is not None and client is not None:
            self.limiter.give_back(client, job.cost)

    def _work(self, job: FrameJob, submitted: float, cancel: threading.Event):
        def run() -> Frame:
            try:
                return render_and_encode()
            finally:
                # The scene's render trims once the frame is drawn (``inference.TRIM_AFTER_PIXELS``);
                # the frame's 8-bit copy and its encoding come after that, so a large frame
                # trims again here (docs/decisions.md#runtime.trim).
                if job.width * job.height >= inference.TRIM_AFTER_PIXELS:
                    release_free_memory()

        def render_and_encode() -> Frame:
            started = time.perf_counter()
            image = draw_in_lanes(self.queue, job.scene.renderer, job.view, cancel.is_set)
            rendered = time.perf_counter()
            data = encode_image(image, job.format, self.jpeg_quality)
            done = time.perf_counter()
            self.metrics.render_seconds.labels(job.quality).observe(done - started)
            frame = Frame(
                data,
                MEDIA_TYPES[job.format],
                image.shape[1],
                image.shape[0],
                (rendered - started) * 1e3,
                (done - rendered) * 1e3,
                (started - submitted) * 1e3,
                False,
            )
            self.cache.put(
                job.key(), CachedFrame(data, frame.media_type, frame.width, frame.height, frame.render_ms)
            )
            return frame

        return run

    def render(self, job: FrameJob, client: str | None = None) -> Frame:
        """Blocking; raises RateLimited, QueueFullError, RenderTimeoutError or ValueError.
        ``client`` is the rate-limit key (``rate_limit.client_key``; None: not limited)."""
        hit = self._lookup(job)
        if hit is not None:
            return hit
        self._charge(job, client)
        cancel = threading.Event()
        try:
            return self.queue.run(
                self._work(job, time.perf_counter(), cancel), self.timeout_s, Lane.of_quality(job.quality), cancel,
                job.large, job.cost,
            )
        except QueueFullError:
            self._refund(job, client)
            raise

    async def render_unless_superseded(self, job: FrameJob, client: str | None, wakeup: asyncio.Event,
                                       superseded: Callable[[], bool]) -> Frame | None:
        """``render_async``; a large frame (``FrameJob.large``) is stopped, and None returned, once
        ``wakeup`` is set while ``superseded()`` holds (a stream's newer request): it takes seconds
        the newer one would wait behind, e.g. a client's frame at its screen's size, given up when
        the user moves again. ``wakeup`` is cleared when it was set for nothing newer."""
        if not job.large:
            return await self.render_async(job, client)
        task = asyncio.ensure_future(self.render_async(job, client))
        while not task.done():
            waiter = asyncio.ensure_future(wakeup.wait())
            await asyncio.wait({task, waiter}, return_when=asyncio.FIRST_COMPLETED)
            waiter.cancel()
            if not task.done() and superseded():
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError, RenderCancelled):
                    await task
                return None
            if not task.done():
                wakeup.clear()
        return task.result()

    async def render_async(self, job: FrameJob, client: str | None = None) -> Frame:
        """``render`` for coroutines; cancelling the awaiting task stops the render."""
        hit = self._lookup(job)
        if hit is not None:
            return hit
        self._charge(job, client)
        cancel = threading.Event()
        work = self._work(job, time.perf_counter(), cancel)
        try:
            return await self.queue.run_async(work, self.timeout_s, Lane.of_quality(job.quality), cancel, job.large,
                                              job.cost)
        except QueueFullError:
            self._refund(job, client)
            raise
