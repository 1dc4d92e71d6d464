"""The interactive stream: ``WS /api/scenes/{id}/stream``.

Protocol (the browser client is written against exactly this):

- client -> server, text JSON: ``{"seq": int, "camera": {"azimuth", "elevation", "distance"} or
  {"c2w": 4x4}, "projection", "fov_deg" or "view_height", "width", "height", "params": {name: value},
  "quality", "format"}`` (``RenderRequest`` documents each field).
- server -> client, per rendered frame: text JSON ``{"type": "frame", "seq", "render_ms", "width",
  "height", "format", "dropped"}`` then one binary message with the encoded image.
- an invalid message gets ``{"type": "error", "seq": n or null, "status": 422 or 404, "detail"}``
  and the connection stays open. When the server is overloaded the status is 503 (with
  ``"retry_after"`` in seconds) or 504 (the render ran past the time limit).
- unknown scene at connect: the error with status 404, then close code 4404. A scene whose file is
  there but not loaded yet (server start-up): status 503 with ``"retry_after"``, then close code 1013
  (try again later).

Limits (``Settings``, block "WebSocket, errors and documentation"):

- a browser page of another origin than the server's own (the ``Host`` header) or
  ``allowed_origins`` is refused at the handshake (HTTP 403); no ``Origin`` header (a client that
  is not a browser) is accepted.
- a message over ``ws_max_message_bytes`` is refused by the protocol under ``visnerf serve`` (close
  code 1009 before it is buffered); text over it that still arrives gets an error with status 422.
- past ``ws_max_sessions`` open sessions, a new one gets an error with status 503 and
  ``"retry_after"``, then close code 1013.
- each session may send ``ws_message_burst`` messages at once, then ``ws_messages_per_s`` a
  second (a token bucket): a message over the rate is not rendered and gets an error with status
  429, its ``seq`` and ``"retry_after"`` (seconds until one more is taken); the session stays open.
- each frame rendered (not served from the cache) is paid from the client's pixel budget, shared
  with its HTTP requests (``rate_limit``): a frame over it waits up to ``RATE_WAIT_MAX_S`` for the
  budget (or is dropped for a newer request), else gets an error with status 429, its ``seq`` and
  ``"retry_after"``. Frames over the size limits (``costs``) get status 422.

A receive task keeps only the newest valid message; the render loop takes it, so stale requests
are dropped (``dropped`` counts them) and a slow renderer never builds a backlog.
"""

import asyncio
import contextlib
import json
import logging
import math
import time
from dataclasses import dataclass
from typing import Any

from fastapi import APIRouter, WebSocket
from pydantic import ValidationError
from starlette.websockets import WebSocketDisconnect, WebSocketState

from visnerf_server.costs import FrameLimits
from visnerf_server.dependencies import (
    ClientKeyDep,
    FrameRendererDep,
    MetricsDep,
    RegistryDep,
    ServerDep,
    SettingsDep,
)
from visnerf_server.frames import Frame, FrameJob, FrameRenderer, prepare_frame
from visnerf_server.metrics import Metrics
from visnerf_server.origins import origin_allowed
from visnerf_server.rate_limit import RateLimited, TokenBucket
from visnerf_server.registry import SceneRegistry
from visnerf_server.render_queue import QueueFullError, RenderTimeoutError, WouldOutwaitError
from visnerf_server.routers.scenes import LOADING_RETRY_S
from visnerf_server.schemas import StreamRequest
from visnerf_server.settings import Settings

logger = logging.getLogger(__name__)

router = APIRouter(tags=["stream"])

CLOSE_UNKNOWN_SCENE = 4404
CLOSE_TRY_AGAIN_LATER = 1013
CLOSE_POLICY_VIOLATION = 1008
"""Sent before the handshake is accepted, which the server answers with HTTP 403."""
RATE_LIMITED = 429
QUEUE_RETRY_S = 0.02
RATE_WAIT_MAX_S = 1.0


class _Closed:
    """What ``_render`` returns where the session closed while it waited."""


_CLOSED = _Closed()
"""A frame over the client's pixel budget waits this long at most for it to refill (the stream
slows down); longer, and it gets an error with status 429."""


@dataclass(frozen=True)
class StreamLimits:
    """What one session may send (``Settings.ws_*``)."""

    max_message_chars: int
    messages_per_s: float
    message_burst: int

    @classmethod
    def from_settings(cls, settings: Settings) -> "StreamLimits":
        return cls(settings.ws_max_message_bytes, settings.ws_messages_per_s, settings.ws_message_burst)


def format_validation_error(exc: ValidationError) -> str:
    parts = []
    for error in exc.errors():
        where = ".".join(str(p) for p in error["loc"])
        parts.append(f"{where}: {error['msg']}" if where else error["msg"])
    return "; ".join(parts)


def _parse_json(text: str) -> tuple[Any, str | None]:
    """(the parsed message, None) or (None, why it is not JSON)."""
    try:
        return json.loads(text), None
    except ValueError as exc:
        return None, str(exc)


class StreamSession:
    """One WebSocket connection: a receive loop and a render loop sharing the newest request."""

    def __init__(
        self,
        websocket: WebSocket,
        scene_id: str,
        registry: SceneRegistry,
        frames: FrameRenderer,
        metrics: Metrics,
        frame_limits: FrameLimits,
        retry_after_s: int,
        limits: StreamLimits,
        client: str | None = None,
    ) -> None:
        self.websocket = websocket
        self.scene_id = scene_id
        self.registry = registry
        self.frames = frames
        self.metrics = metrics
        self.frame_limits = frame_limits
        self.client = client
        """Whose rate limit pays for the frames (``rate_limit.client_key``); None: no limit."""
        self.retry_after_s = retry_after_s
        self.pending: tuple[int, FrameJob] | None = None
        self.wakeup = asyncio.Event()
        self.closed = False
        self.dropped = 0
        self.send_lock = asyncio.Lock()
        self.limits = limits
        self.bucket = TokenBucket.full(float(limits.message_burst), limits.messages_per_s, time.monotonic())

    async def send_json(self, message: dict[str, Any]) -> None:
        async with self.send_lock:
            await self.websocket.send_text(json.dumps(message))

    async def send_error(
        self, seq: int | None, status: int, detail: str, retry_after: float | None = None
    ) -> None:
        message: dict[str, Any] = {"type": "error", "seq": seq, "status": status, "detail": detail}
        if status == 503 and retry_after is None:
            retry_after = self.retry_after_s  # seconds, as in the HTTP Retry-After header
        if retry_after is not None:
            message["retry_after"] = retry_after
        await self.send_json(message)

    async def accept_message(self, text: str) -> None:
        """Validate one client message; keep it as the newest pending request or answer an error."""
        limit = self.limits.max_message_chars
        if len(text) > limit:
            await self.send_error(None, 422, f"message over {limit} characters")
            return
        data, not_json = _parse_json(text)
        seq = data.get("seq") if isinstance(data, dict) else None
        seq = seq if isinstance(seq, int) and not isinstance(seq, bool) else None
        if not self.bucket.try_take(1.0, time.monotonic()):  # every message counts, valid or not
            await self._refuse_over_rate(seq)
            return
        if not_json is not None:
            await self.send_error(None, 422, f"message is not valid JSON: {not_json}")
            return
        try:
            request = StreamRequest.model_validate(data)
        except ValidationError as exc:
            await self.send_error(seq, 422, format_validation_error(exc))
            return
        scene = self.registry.get(self.scene_id)
        if scene is None:
            await self.send_error(request.seq, 404, f"unknown scene {self.scene_id!r}")
            return
        try:
            job = prepare_frame(scene, request, self.frame_limits)
        except ValueError as exc:
            await self.send_error(request.seq, 422, str(exc))
            return
        if self.pending is not None:
            self._drop()
        self.pending = (request.seq, job)
        self.wakeup.set()

    async def _refuse_over_rate(self, seq: int | None) -> None:
        self.metrics.stream_refused.labels("rate").inc()
        wait = math.ceil(self.bucket.wait_s() * 1000) / 1000
        detail = f"over {self.limits.messages_per_s:g} messages a second: not rendered, send it again later"
        await self.send_error(seq, RATE_LIMITED, detail, retry_after=wait)

    def _drop(self) -> None:
        self.dropped += 1
        self.metrics.dropped_frames.inc()

    async def receive_loop(self) -> None:
        try:
            while True:
                message = await self.websocket.receive()
                if message["type"] == "websocket.disconnect":
                    return
                text = message.get("text")
                if text is None:
                    if self.bucket.try_take(1.0, time.monotonic()):
                        await self.send_error(None, 422, "messages must be text JSON")
                    else:
                        await self._refuse_over_rate(None)
                    continue
                await self.accept_message(text)
        finally:
            self.closed = True
            self.wakeup.set()

    async def render_loop(self) -> None:
        while True:
            await self.wakeup.wait()
            self.wakeup.clear()
            if self.closed:
                return
            if self.pending is None:
                continue
            seq, job = self.pending
            self.pending = None
            frame = await self._render(seq, job)
            if isinstance(frame, _Closed):
                return
            if frame is not None:
                await self._send_frame(seq, job, frame)

    async def _render(self, seq: int, job: FrameJob) -> Frame | None | _Closed:
        """The frame of ``job``; None where it was superseded or refused (the error sent); ``_CLOSED``
        where the session closed meanwhile. Short rate-limit waits and full queues are waited out
        until the frame timeout, unless a newer request replaces this one."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.frames.timeout_s
        while True:
            try:
                frame = await self.frames.render_unless_superseded(
                    job, self.client, self.wakeup, lambda: self.pending is not None or self.closed)
                if frame is None:  # a newer request came while a large frame rendered
                    self._drop()
                return frame
            except RateLimited as exc:  # the client's pixel budget (``rate_limit``)
                if exc.retry_after_s > RATE_WAIT_MAX_S or loop.time() + exc.retry_after_s >= deadline:
                    self.metrics.rate_limited.inc()
                    await self.send_error(seq, RATE_LIMITED, str(exc), retry_after=round(exc.retry_after_s, 3))
                    return None
                self.metrics.stream_rate_waits.inc()
                await asyncio.sleep(exc.retry_after_s)  # a short wait: the stream slows down
            except WouldOutwaitError as exc:  # a large frame behind large ones: sooner is no use
                await self.send_error(seq, 503, str(exc), retry_after=round(exc.retry_after_s, 3))
                return None
            except QueueFullError:  # back off; a newer request may replace this one meanwhile
                if not self.closed and self.pending is None:
                    if loop.time() > deadline:
                        await self.send_error(seq, 503, "render queue is full; try again")
                        return None
                    await asyncio.sleep(QUEUE_RETRY_S)
            except RenderTimeoutError as exc:
                await self.send_error(seq, 504 if exc.started else 503, f"render {exc}")
                return None
            # A ValueError here is a bug (``prepare_frame`` checked the request): it ends the
            # session with close code 1011 and a logged traceback (``run``), not a 422.
            if self.closed:
                return _CLOSED
            if self.pending is not None:  # a newer request replaces this one
                self._drop()
                return None

    async def _send_frame(self, seq: int, job: FrameJob, frame: Frame) -> None:
        header = {
            "type": "frame",
            "seq": seq,
            "render_ms": round(frame.render_ms, 2),
            "width": frame.width,
            "height": frame.height,
            "format": job.format,
            "dropped": self.dropped,
        }
        async with self.send_lock:
            await self.websocket.send_text(json.dumps(header))
            await self.websocket.send_bytes(frame.data)

    async def run(self) -> None:
        receiver = asyncio.create_task(self.receive_loop())
        renderer = asyncio.create_task(self.render_loop())
        try:
            done, _ = await asyncio.wait({receiver, renderer}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in (receiver, renderer):
                task.cancel()
            await asyncio.gather(receiver, renderer, return_exceptions=True)
        for task in done:
            exc = None if task.cancelled() else task.exception()
            if exc is not None and not isinstance(exc, WebSocketDisconnect | RuntimeError):
                logger.error("stream for scene %r failed", self.scene_id, exc_info=exc)
                await _close(self.websocket, 1011)


async def _close(websocket: WebSocket, code: int) -> None:
    if websocket.application_state == WebSocketState.CONNECTED:
        with contextlib.suppress(RuntimeError, WebSocketDisconnect):
            await websocket.close(code)


@router.websocket("/api/scenes/{scene_id}/stream")
async def stream(
    websocket: WebSocket,
    scene_id: str,
    registry: RegistryDep,
    frames: FrameRendererDep,
    metrics: MetricsDep,
    settings: SettingsDep,
    server: ServerDep,
    client: ClientKeyDep,
) -> None:
    origin = websocket.headers.get("origin")
    if not origin_allowed(origin, websocket.headers.get("host"), settings.allowed_origins):
        metrics.stream_refused.labels("origin").inc()
        await websocket.close(CLOSE_POLICY_VIOLATION)  # before accept: the handshake gets 403
        return
    await websocket.accept()
    if registry.get(scene_id) is None:
        await _refuse_scene(websocket, registry, scene_id)
        return
    if server.stream_sessions >= settings.ws_max_sessions:
        metrics.stream_refused.labels("sessions").inc()
        detail = f"the server has its maximum of {settings.ws_max_sessions} stream sessions open"
        await _refuse(websocket, 503, detail, CLOSE_TRY_AGAIN_LATER, settings.retry_after_s)
        return
    session = StreamSession(
        websocket, scene_id, registry, frames, metrics, FrameLimits.from_settings(settings), settings.retry_after_s,
        StreamLimits.from_settings(settings), client,
    )
    server.stream_sessions += 1  # no await between the check and here: the count cannot race
    metrics.stream_sessions.inc()
    try:
        await session.run()
    finally:
        server.stream_sessions -= 1
        metrics.stream_sessions.dec()


async def _refuse_scene(websocket: WebSocket, registry: SceneRegistry, scene_id: str) -> None:
    """An unknown scene (close 4404), or one still loading at start-up (close 1013)."""
    if registry.pending(scene_id):
        detail = f"scene {scene_id!r} is still loading"
        await _refuse(websocket, 503, detail, CLOSE_TRY_AGAIN_LATER, LOADING_RETRY_S)
    else:
        await _refuse(websocket, 404, f"unknown scene {scene_id!r}", CLOSE_UNKNOWN_SCENE)


async def _refuse(
    websocket: WebSocket, status: int, detail: str, code: int, retry_after: float | None = None
) -> None:
    """One error message, then close with ``code``."""
    error: dict[str, Any] = {"type": "error", "seq": None, "status": status}
    if retry_after is not None:
        error["retry_after"] = retry_after
    error["detail"] = detail
    with contextlib.suppress(RuntimeError, WebSocketDisconnect):
        await websocket.send_text(json.dumps(error))
    await _close(websocket, code)
