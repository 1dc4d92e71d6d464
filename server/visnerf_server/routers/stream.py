"""The interactive stream: ``WS /api/scenes/{id}/stream``.

Protocol (the browser client is written against exactly this):

- client -> server, text JSON: ``{"seq": int, "camera": {"azimuth", "elevation", "distance"} or
  {"c2w": 4x4}, "fov_deg", "width", "height", "params": {name: value}, "quality", "format"}``.
- server -> client, per rendered frame: text JSON ``{"type": "frame", "seq", "render_ms", "width",
  "height", "format", "dropped"}`` then one binary message with the encoded image.
- an invalid message gets ``{"type": "error", "seq": n or null, "status": 422 or 404, "detail"}``
  and the connection stays open. When the server is overloaded the status is 503 (with
  ``"retry_after"`` in seconds) or 504 (the render ran past the time limit).
- unknown scene at connect: the error with status 404, then close code 4404. A scene whose file is
  there but not loaded yet (server start-up): status 503 with ``"retry_after"``, then close code 1013
  (try again later).

A receive task keeps only the newest valid message; the render loop takes it, so stale requests
are dropped (``dropped`` counts them) and a slow renderer never builds a backlog.
"""

import asyncio
import contextlib
import json
import logging
from typing import Any

from fastapi import APIRouter, WebSocket
from pydantic import ValidationError
from starlette.websockets import WebSocketDisconnect, WebSocketState

from visnerf_server.dependencies import FrameRendererDep, MetricsDep, RegistryDep, SettingsDep
from visnerf_server.frames import FrameJob, FrameRenderer, prepare_frame
from visnerf_server.metrics import Metrics
from visnerf_server.registry import SceneRegistry
from visnerf_server.render_queue import QueueFullError, RenderTimeoutError
from visnerf_server.routers.scenes import LOADING_RETRY_S
from visnerf_server.schemas import StreamRequest

logger = logging.getLogger(__name__)

router = APIRouter(tags=["stream"])

CLOSE_UNKNOWN_SCENE = 4404
CLOSE_TRY_AGAIN_LATER = 1013
MAX_MESSAGE_CHARS = 64 * 1024
QUEUE_RETRY_S = 0.02


def format_validation_error(exc: ValidationError) -> str:
    parts = []
    for error in exc.errors():
        where = ".".join(str(p) for p in error["loc"])
        parts.append(f"{where}: {error['msg']}" if where else error["msg"])
    return "; ".join(parts)


class StreamSession:
    """One WebSocket connection: a receive loop and a render loop sharing the newest request."""

    def __init__(
        self,
        websocket: WebSocket,
        scene_id: str,
        registry: SceneRegistry,
        frames: FrameRenderer,
        metrics: Metrics,
        max_image_size: int,
        retry_after_s: int = 1,
    ) -> None:
        self.websocket = websocket
        self.scene_id = scene_id
        self.registry = registry
        self.frames = frames
        self.metrics = metrics
        self.max_image_size = max_image_size
        self.retry_after_s = retry_after_s
        self.pending: tuple[int, FrameJob] | None = None
        self.wakeup = asyncio.Event()
        self.closed = False
        self.dropped = 0
        self.send_lock = asyncio.Lock()

    async def send_json(self, message: dict[str, Any]) -> None:
        async with self.send_lock:
            await self.websocket.send_text(json.dumps(message))

    async def send_error(self, seq: int | None, status: int, detail: str) -> None:
        message: dict[str, Any] = {"type": "error", "seq": seq, "status": status, "detail": detail}
        if status == 503:
            message["retry_after"] = self.retry_after_s  # seconds, as in the HTTP Retry-After header
        await self.send_json(message)

    async def accept_message(self, text: str) -> None:
        """Validate one client message; keep it as the newest pending request or answer an error."""
        if len(text) > MAX_MESSAGE_CHARS:
            await self.send_error(None, 422, f"message over {MAX_MESSAGE_CHARS} characters")
            return
        try:
            data = json.loads(text)
        except ValueError as exc:
            await self.send_error(None, 422, f"message is not valid JSON: {exc}")
            return
        seq = data.get("seq") if isinstance(data, dict) else None
        seq = seq if isinstance(seq, int) and not isinstance(seq, bool) else None
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
            job = prepare_frame(scene, request, self.max_image_size)
        except ValueError as exc:
            await self.send_error(request.seq, 422, str(exc))
            return
        if self.pending is not None:
            self._drop()
        self.pending = (request.seq, job)
        self.wakeup.set()

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
                    await self.send_error(None, 422, "messages must be text JSON")
                    continue
                await self.accept_message(text)
        finally:
            self.closed = True
            self.wakeup.set()

    async def render_loop(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            await self.wakeup.wait()
            self.wakeup.clear()
            if self.closed:
                return
            if self.pending is None:
                continue
            seq, job = self.pending
            self.pending = None
            deadline = loop.time() + self.frames.timeout_s
            while True:
                try:
                    frame = await self.frames.render_async(job)
                    break
                except QueueFullError:  # back off; a newer request may replace this one meanwhile
                    if self.closed:
                        return
                    if self.pending is not None:
                        self._drop()
                        frame = None
                        break
                    if loop.time() > deadline:
                        await self.send_error(seq, 503, "render queue is full; try again")
                        frame = None
                        break
                    await asyncio.sleep(QUEUE_RETRY_S)
                except RenderTimeoutError as exc:
                    await self.send_error(seq, 504 if exc.started else 503, f"render {exc}")
                    frame = None
                    break
                except ValueError as exc:
                    await self.send_error(seq, 422, str(exc))
                    frame = None
                    break
            if frame is None:
                continue
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
) -> None:
    await websocket.accept()
    if registry.get(scene_id) is None:
        if registry.pending(scene_id):
            error = {"type": "error", "seq": None, "status": 503, "retry_after": LOADING_RETRY_S,
                     "detail": f"scene {scene_id!r} is still loading"}
            code = CLOSE_TRY_AGAIN_LATER
        else:
            error = {"type": "error", "seq": None, "status": 404, "detail": f"unknown scene {scene_id!r}"}
            code = CLOSE_UNKNOWN_SCENE
        with contextlib.suppress(RuntimeError, WebSocketDisconnect):
            await websocket.send_text(json.dumps(error))
        await _close(websocket, code)
        return
    session = StreamSession(
        websocket, scene_id, registry, frames, metrics, settings.max_image_size, settings.retry_after_s
    )
    await session.run()
