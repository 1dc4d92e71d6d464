"""ASGI middleware: structured access logs, responses-by-status metrics, and a request-body limit.

Pure ASGI (not ``BaseHTTPMiddleware``) so streamed uploads and WebSockets pass through untouched.
"""

import json
import logging
import time

from starlette.exceptions import HTTPException
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from visnerf_server.metrics import Metrics

access_logger = logging.getLogger("visnerf_server.access")


def _is_upload(scope: Scope) -> bool:
    """``PUT /api/scenes/{id}`` enforces its own (larger) limit while streaming to disk."""
    return scope["method"] == "PUT" and scope["path"].startswith("/api/scenes/")


class AccessLogMiddleware:
    """One log record per request or WebSocket session: method, path, status, ms (JSON or text)."""

    def __init__(
        self, app: ASGIApp, metrics: Metrics, max_request_bytes: int, log_format: str = "json"
    ) -> None:
        self.app = app
        self.metrics = metrics
        self.max_request_bytes = max_request_bytes
        self.log_format = log_format

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status_code: int | None = None

        async def send_wrapper(message: Message) -> None:
            nonlocal status_code
            kind = message["type"]
            if kind == "http.response.start":
                status_code = int(message["status"])
            elif kind == "websocket.accept":
                status_code = 101
            elif kind == "websocket.close" and status_code is None:
                status_code = 403  # handshake refused
            await send(message)

        if scope["type"] == "http" and not _is_upload(scope):
            receive = self._limited(scope, receive)
            declared = dict(scope["headers"]).get(b"content-length")
            if declared is not None and declared.isdigit() and int(declared) > self.max_request_bytes:
                response = JSONResponse(
                    {"detail": f"request body over the limit of {self.max_request_bytes} bytes"},
                    status_code=413,
                )
                await response(scope, receive, send_wrapper)
                self._log(scope, status_code, start)
                return
        try:
            await self.app(scope, receive, send_wrapper)
        except Exception:
            if status_code is None:
                status_code = 500
            raise
        finally:
            self._log(scope, status_code, start)

    def _limited(self, scope: Scope, receive: Receive) -> Receive:
        received = 0
        limit = self.max_request_bytes

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    raise HTTPException(413, f"request body over the limit of {limit} bytes")
            return message

        return limited_receive

    def _log(self, scope: Scope, status_code: int | None, start: float) -> None:
        ms = (time.perf_counter() - start) * 1e3
        method = scope.get("method", "WS") if scope["type"] == "http" else "WS"
        status = status_code if status_code is not None else 0
        if scope["type"] == "http":
            self.metrics.responses.labels(str(status)).inc()
        if not access_logger.isEnabledFor(logging.INFO):
            return
        if self.log_format == "json":
            line = json.dumps({"method": method, "path": scope["path"], "status": status, "ms": round(ms, 2)})
        else:
            line = f"{method} {scope['path']} {status} {ms:.1f}ms"
        access_logger.info(line)
