"""Running the app under uvicorn (``visnerf serve``), with renders stopped as soon as a stop is asked.

uvicorn answers SIGTERM (and Ctrl-C) by waiting up to its graceful-shutdown time for the requests
in progress, then cancels them (a 500 each) and runs the app's shutdown. A large frame would keep
the process for all that time. Here the signal also closes the render queue at once: queued frames
and the running ones, stopped within a chunk of rays, answer 503 with Retry-After, and the process
exits in about a second.
"""

import asyncio
import contextlib
from types import FrameType
from typing import Any

import uvicorn
from fastapi import FastAPI


def stop_renders(app: FastAPI) -> None:
    """Close the app's render queue (``RenderQueue.close``), if the app has started."""
    server = getattr(app.state, "server", None)
    if server is not None:
        server.queue.close()


class RenderStoppingServer(uvicorn.Server):
    """``uvicorn.Server`` whose stop signal also stops the app's renders."""

    def __init__(self, config: uvicorn.Config, app: FastAPI) -> None:
        super().__init__(config)
        self.app = app

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        super().handle_exit(sig, frame)
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # not serving yet (or any more)
            return
        # Not from the signal handler itself: the interrupted code may hold the queue's lock.
        loop.call_soon_threadsafe(stop_renders, self.app)


def serve(app: FastAPI, **options: Any) -> bool:
    """``uvicorn.run(app, **options)`` on a ``RenderStoppingServer``; False when it did not start."""
    server = RenderStoppingServer(uvicorn.Config(app, **options), app)
    with contextlib.suppress(KeyboardInterrupt):
        server.run()
    return server.started
