"""The frames of a running movie job: rendered one at a time, each a task of the render queue's
background lane, so an interactive render waits at most for the one movie frame being rendered.
A full-quality movie frame of 512x512 or more is large (``frames.is_large_frame``): it never
runs beside a large interactive frame, nor one beside it.

Before each frame the job's cancel event is asked, and whether its scene is still the one it started
with (deleted or replaced by an upload: ``SceneChanged``); inside a frame the renderer asks the same
event between chunks of rays (``RenderCancelled``).
"""

import concurrent.futures
import time
from collections.abc import Callable, Iterator
from threading import Event

import numpy as np

from visnerf.animation.path import FrameSpec
from visnerf.inference import RenderCancelled
from visnerf_server.frames import draw_in_lanes, is_large_frame
from visnerf_server.movie_plans import MoviePlan
from visnerf_server.registry import SceneRegistry
from visnerf_server.render_queue import Lane, QueueFullError, RenderQueue

QUEUE_RETRY_S = 0.05
"""Wait before offering a frame again to a render queue that is full of interactive work."""
CANCEL_POLL_S = 0.05
"""How often a job waiting for its frame looks at its cancel event."""
STOPPED = (RenderCancelled, QueueFullError)
"""What ends a job's frames early besides ``SceneChanged``: cancelled, or the server stopping."""


class SceneChanged(RuntimeError):
    """The job's scene was deleted or replaced while the job rendered."""


def check_scene(registry: SceneRegistry, plan: MoviePlan, index: int) -> None:
    """Raise SceneChanged unless the registry still holds the scene the job was planned on."""
    scene = registry.get(plan.scene.id)
    if scene is None or scene.version != plan.scene.version:
        what = "deleted" if scene is None else "replaced by an upload"
        raise SceneChanged(
            f"scene {plan.scene.id!r} was {what} while the movie was rendering "
            f"(at frame {index + 1} of {plan.n_frames})"
        )


def render_frame(queue: RenderQueue, plan: MoviePlan, spec: FrameSpec, cancel: Event) -> np.ndarray:
    """One frame as a background-lane task: offered again while the queue is full of interactive
    work, dropped (queued) or stopped (running) once ``cancel`` is set."""
    renderer = plan.scene.renderer
    settings = plan.settings
    large = is_large_frame(settings.width, settings.height, settings.quality)
    view = renderer.view(spec.c2w, spec.fov_deg, settings.width, settings.height, spec.params,
                         settings.quality, spec.view_height)  # type: ignore[arg-type]

    def run() -> np.ndarray:
        return draw_in_lanes(queue, renderer, view, cancel.is_set)

    while True:
        if cancel.is_set():
            raise RenderCancelled("movie job cancelled")
        try:
            future = queue.submit(run, Lane.BACKGROUND, cancel, large=large)
            break
        except QueueFullError:
            if queue.closed:
                raise
            time.sleep(QUEUE_RETRY_S)
    while True:
        try:
            return future.result(timeout=CANCEL_POLL_S)
        except TimeoutError:
            if cancel.is_set() and future.cancel():
                raise RenderCancelled("movie job cancelled") from None
        except concurrent.futures.CancelledError:
            raise RenderCancelled("movie job cancelled") from None


def movie_frames(
    plan: MoviePlan,
    specs: list[FrameSpec],
    registry: SceneRegistry,
    queue: RenderQueue,
    cancel: Event,
    failure: list[str],
    on_frame: Callable[[], None],
) -> Iterator[np.ndarray]:
    """The job's frames in order. Why it stopped early (unless cancelled) is appended to
    ``failure`` before the exception goes on to the movie writer, which may keep it to itself
    while it closes its file."""
    for index, spec in enumerate(specs):
        try:
            if cancel.is_set():
                raise RenderCancelled("movie job cancelled")
            check_scene(registry, plan, index)
            image = render_frame(queue, plan, spec, cancel)
        except (*STOPPED, SceneChanged) as exc:
            if not cancel.is_set():
                failure.append(str(exc))
            raise
        on_frame()
        yield image
