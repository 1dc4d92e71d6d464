"""Checking a movie request before anything is queued: the path (``visnerf.animation``), each
frame against the single-frame limits (``costs``: 422), and the whole job against ``MovieLimits``
(frames, and frames x width x height: 413, naming the limit).

The frames themselves (``sample_frames``) are worked out by the job's thread when it starts, not
while the request waits: a winding path of many keyframes takes seconds to sample, and the job
threads are few and bounded. Their number is known before (``frame_times``)."""

import math
from dataclasses import dataclass

from visnerf.animation.movie import MovieSettings
from visnerf.animation.path import AnimationPath, frame_times, orbit_path, parse_path
from visnerf.lens import choose_lens
from visnerf_server.costs import FrameLimits
from visnerf_server.registry import Scene
from visnerf_server.schemas import MovieRequest
from visnerf_server.settings import Settings


class MovieTooLarge(ValueError):
    """A job over the per-job limits (413; the message names the limit)."""


@dataclass(frozen=True)
class MovieLimits:
    max_frames: int
    max_pixels: int
    """frames x width x height."""
    running: int
    queued: int
    per_client: int
    keep_s: float
    max_disk_bytes: int

    @classmethod
    def from_settings(cls, settings: Settings) -> "MovieLimits":
        return cls(
            settings.movie_max_frames,
            settings.movie_max_pixels,
            settings.movie_jobs_running,
            settings.movie_jobs_queued,
            settings.movie_jobs_per_client,
            settings.movie_keep_s,
            settings.movie_max_disk_bytes,
        )

    def check(self, n_frames: int, width: int, height: int) -> None:
        """Raise MovieTooLarge when the job is over a per-job limit."""
        if n_frames > self.max_frames:
            raise MovieTooLarge(
                f"a movie of {n_frames} frames exceeds this server's limit of {self.max_frames} frames "
                "per job (movie_max_frames)"
            )
        pixels = n_frames * width * height
        if pixels > self.max_pixels:
            raise MovieTooLarge(
                f"a movie of {n_frames} frames of {width}x{height} = {pixels} pixels exceeds this server's "
                f"limit of {self.max_pixels} pixels per job (movie_max_pixels)"
            )


@dataclass(frozen=True)
class MoviePlan:
    """A fully validated movie request."""

    scene: Scene
    path: AnimationPath
    n_frames: int
    """Frames ``sample_frames(path, settings.fps, ...)`` gives."""
    settings: MovieSettings
    cost: float
    """Rate-limit price: every frame's pixels, a preview pixel at ``FrameLimits.preview_pixel_cost``."""


def prepare_movie(scene: Scene, request: MovieRequest, frame_limits: FrameLimits, limits: MovieLimits) -> MoviePlan:
    """Check a request against the scene and the server's limits; ValueError names the problem
    (``PathError`` for the path, ``MovieTooLarge`` for a job over a per-job limit)."""
    frame_limits.check(request.width, request.height, request.quality)
    fps = float(request.fps)
    settings = MovieSettings(
        fps=fps, width=request.width, height=request.height, format=request.format, quality=request.quality
    )
    info = scene.renderer.info
    if request.orbit is not None:
        limits.check(request.orbit, request.width, request.height)  # before anything is sampled
        camera = info.camera
        defaults = {axis.name: axis.default for axis in info.params}
        fov_deg, view_height = choose_lens(camera)
        path = orbit_path(
            request.orbit,
            fps,
            float(camera.get("elevation", 0.0)),
            float(camera.get("distance", 4.0)),
            fov_deg,
            defaults,
            start_azimuth=float(camera.get("azimuth", 0.0)),
            view_height=view_height,
        )
    else:
        path = parse_path(request.path, info.params, info.camera)
        limits.check(_fewest_frames(path, fps), request.width, request.height)  # before listing times
    n_frames = len(frame_times(path, fps))
    limits.check(n_frames, request.width, request.height)
    cost = n_frames * frame_limits.cost(request.width, request.height, request.quality)
    return MoviePlan(scene, path, n_frames, settings, cost)


def _fewest_frames(path: AnimationPath, fps: float) -> int:
    """A lower bound of the frames ``path`` gives at ``fps``, known before sampling them: a path of
    a million seconds is refused without building its frames."""
    return math.floor(path.duration * fps)
