"""Stopping work whose HTTP client has gone away.

``until_disconnected`` awaits a coroutine while it polls ``Request.is_disconnected()``; when the
client closes the connection first, the coroutine is cancelled (a render waiting in the queue is
dropped, a running one stops at its next chunk of rays, ``render_queue``) and ``ClientDisconnected``
is raised. WebSocket sessions need no polling: their render task is cancelled when the socket closes.
"""

import asyncio
import contextlib
from collections.abc import Coroutine
from typing import Any, TypeVar

from starlette.requests import Request

T = TypeVar("T")

DISCONNECT_POLL_S = 0.1
"""How often a waiting request checks its connection."""


class ClientDisconnected(Exception):
    """The client closed the connection before the answer was ready."""


async def until_disconnected(
    request: Request, work: Coroutine[Any, Any, T], poll_s: float = DISCONNECT_POLL_S
) -> T:
    """The result of ``work``, or ClientDisconnected (``work`` cancelled) once the client has gone."""
    task = asyncio.ensure_future(work)
    try:
        while True:
            done, _ = await asyncio.wait({task}, timeout=poll_s)
            if done:
                return task.result()
            if await request.is_disconnected():
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
                raise ClientDisconnected("client closed the connection")
    finally:
        if not task.done():  # this request itself was cancelled (server shutting down)
            task.cancel()
