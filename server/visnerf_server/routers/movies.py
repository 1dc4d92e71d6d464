"""Movie jobs: ``POST /api/scenes/{id}/movies`` starts one, ``/api/movies/{job_id}`` follows,
downloads and cancels it (``movies`` does the work).

Creating a job is open like a render and paid like one: the job's pixels (every frame's, previews at
their discount) come out of the client's rate-limit bucket, at most a full bucket (``rate_limit``),
on top of the per-job limits (413) and the jobs-at-once limits (429). The job id is an unguessable
capability: whoever has it may follow, download or cancel the job.
"""

import asyncio
import os
from collections.abc import Iterator
from typing import IO, Annotated, Any

from fastapi import APIRouter, HTTPException, Path, Response
from fastapi.responses import StreamingResponse

from visnerf_server.costs import FrameLimits
from visnerf_server.dependencies import ClientKeyDep, MovieJobsDep, RegistryDep, ServerDep, SettingsDep
from visnerf_server.movie_plans import MovieLimits, MovieTooLarge, prepare_movie
from visnerf_server.movies import MovieJob, MovieJobs, TooManyJobs
from visnerf_server.rate_limit import RateLimited
from visnerf_server.render_queue import QueueFullError
from visnerf_server.routers.scenes import ERRORS, SceneIdPath, find_scene
from visnerf_server.schemas import MOVIE_MEDIA_TYPES, ErrorDetail, MovieJobCreated, MovieJobStatus, MovieRequest

router = APIRouter(tags=["movies"])

JOB_ID_PATTERN = r"^[A-Za-z0-9_-]{1,64}$"
JobIdPath = Annotated[str, Path(pattern=JOB_ID_PATTERN, description="The id `POST .../movies` answered")]
NOT_FOUND: dict[int | str, dict[str, Any]] = {404: {"model": ErrorDetail, "description": "Unknown job"}}
CANCEL_WAIT_S = 5.0
"""How long ``DELETE`` waits for a running job's frame to stop (it stops within a chunk of rays)."""
CHUNK_BYTES = 1 << 20


def unknown_job(job_id: str, keep_s: float) -> HTTPException:
    return HTTPException(
        404,
        f"unknown movie job {job_id!r}: jobs live in this server's memory only, so they do not survive a "
        f"server restart, and a finished job is forgotten {keep_s / 60:g} minutes after it ended or once deleted",
    )


def find_job(movies: MovieJobs, job_id: str) -> MovieJob:
    job = movies.get(job_id)
    if job is None:
        raise unknown_job(job_id, movies.limits.keep_s)
    return job


@router.post(
    "/api/scenes/{scene_id}/movies",
    status_code=202,
    response_model=MovieJobCreated,
    responses={**ERRORS, 429: {"model": ErrorDetail, "description": "Rate limit spent or too many jobs"}},
)
def create_movie(
    scene_id: SceneIdPath,
    body: MovieRequest,
    registry: RegistryDep,
    movies: MovieJobsDep,
    settings: SettingsDep,
    server: ServerDep,
    client: ClientKeyDep,
) -> MovieJobCreated:
    """Queue a movie of a camera and parameter ``path`` (or ``orbit`` frames around the scene);
    poll ``status_url``, then download ``file_url``."""
    scene = find_scene(registry, scene_id)
    try:
        plan = prepare_movie(scene, body, FrameLimits.from_settings(settings), MovieLimits.from_settings(settings))
    except MovieTooLarge as exc:
        raise HTTPException(413, str(exc)) from None
    except ValueError as exc:  # the path (PathError names the field), a frame size, the movie settings
        raise HTTPException(422, str(exc)) from None
    limiter = server.limiter
    if limiter is not None:
        try:
            limiter.take(client, plan.cost)
        except RateLimited as exc:
            server.metrics.rate_limited.inc()
            raise HTTPException(429, str(exc), {"Retry-After": exc.retry_after_header}) from None
    try:
        job = movies.submit(plan, client)
    except (TooManyJobs, QueueFullError) as exc:
        if limiter is not None:
            limiter.give_back(client, plan.cost)
        if isinstance(exc, QueueFullError):
            raise HTTPException(503, f"{exc}; retry shortly", {"Retry-After": str(settings.retry_after_s)}) from None
        raise HTTPException(429, str(exc), {"Retry-After": str(exc.retry_after_s)}) from None
    return MovieJobCreated(
        job_id=job.id,
        frames=plan.n_frames,
        status_url=f"/api/movies/{job.id}",
        file_url=f"/api/movies/{job.id}/file",
    )


@router.get("/api/movies/{job_id}", response_model=MovieJobStatus, responses=NOT_FOUND)
async def movie_status(job_id: JobIdPath, movies: MovieJobsDep) -> MovieJobStatus:
    """The job's state and progress."""
    return find_job(movies, job_id).status(movies.now())


FILE_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {"content": {media: {} for media in MOVIE_MEDIA_TYPES.values()}, "description": "The movie file"},
    **NOT_FOUND,
    409: {"model": ErrorDetail, "description": "The job is not done (yet)"},
}


def _chunks(f: IO[bytes]) -> Iterator[bytes]:
    with f:
        while chunk := f.read(CHUNK_BYTES):
            yield chunk


@router.get("/api/movies/{job_id}/file", response_class=Response, responses=FILE_RESPONSES)
async def movie_file(job_id: JobIdPath, movies: MovieJobsDep) -> Response:
    """The finished movie, as an attachment."""
    job = find_job(movies, job_id)
    if job.state != "done":
        raise HTTPException(409, f"movie job {job_id!r} is {job.state}, not done: it has no file to download")
    try:  # opened here: a file deleted while it is sent (expired) stays readable to the end
        f = job.file.open("rb")
    except FileNotFoundError:
        raise unknown_job(job_id, movies.limits.keep_s) from None
    headers = {
        "Content-Disposition": f'attachment; filename="{job.download_name}"',
        "Content-Length": str(os.fstat(f.fileno()).st_size),
    }
    return StreamingResponse(_chunks(f), media_type=job.media_type, headers=headers)


@router.delete("/api/movies/{job_id}", status_code=204, responses=NOT_FOUND)
async def delete_movie(job_id: JobIdPath, movies: MovieJobsDep) -> Response:
    """Cancel a queued or running job (its state becomes ``cancelled``) and delete its file; a
    finished job is forgotten."""
    job = movies.delete(job_id)
    if job is None:
        raise unknown_job(job_id, movies.limits.keep_s)
    loop = asyncio.get_running_loop()
    deadline = loop.time() + CANCEL_WAIT_S
    while not job.ended.is_set() and loop.time() < deadline:
        await asyncio.sleep(0.01)
    return Response(status_code=204)
