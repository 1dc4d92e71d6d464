"""Checkpoint uploads: stream to a hidden temporary file in the checkpoints folder (size checked
while streaming), validate fully (every checkpoint check, then a tiny test render), build the
answer, then ``os.replace`` into place and swap the scene in the registry. Nothing is left behind
on failure, and nothing fails after the swap. Uploads and deletions of one id run one at a time."""

import hashlib
import logging
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from fastapi import HTTPException, Request, Response
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect

from visnerf.inference import SceneRenderer
from visnerf_server.dependencies import ServerState
from visnerf_server.registry import Scene, SceneRegistry, load_and_check

logger = logging.getLogger(__name__)

UPLOAD_PREFIX = ".upload-"
UPLOAD_SUFFIX = ".tmp"
MAX_CONCURRENT_UPLOADS = 2
STALE_UPLOAD_SECONDS = 3600.0
CLIENT_CLOSED_REQUEST = 499
"""Status logged for an upload the client abandoned (nginx's code; nobody receives the answer)."""

UploadAnswer = Callable[[Scene, bool], Response]
"""Builds the PUT's response from the validated scene and whether it is new (``created``)."""


def remove_stale_uploads(checkpoints_dir: Path, older_than_s: float = STALE_UPLOAD_SECONDS) -> int:
    """Delete temporaries left by a crashed server (old enough not to belong to a live upload)."""
    if not checkpoints_dir.is_dir():
        return 0
    removed = 0
    now = time.time()
    for path in checkpoints_dir.glob(f"{UPLOAD_PREFIX}*{UPLOAD_SUFFIX}"):
        try:
            if now - path.stat().st_mtime > older_than_s:
                path.unlink()
                removed += 1
        except OSError:
            continue
    return removed


def _declared_length(request: Request) -> int | None:
    value = request.headers.get("content-length")
    if value is None:
        return None
    if not value.strip().isdigit():
        raise HTTPException(400, "Content-Length is not a number")
    return int(value)


async def _stream_to(request: Request, path: Path, limit: int) -> tuple[int, str]:
    """Write the body to ``path``; 413 as soon as it passes ``limit`` bytes, 499 when the client
    goes away before the end. Returns (size, sha256)."""
    size = 0
    digest = hashlib.sha256()
    with path.open("wb") as f:
        try:
            async for chunk in request.stream():
                size += len(chunk)
                if size > limit:
                    raise HTTPException(413, f"checkpoint is over the upload limit of {limit} bytes")
                digest.update(chunk)
                f.write(chunk)
        except ClientDisconnect:  # not a server error: the access log's one line says 499
            raise HTTPException(CLIENT_CLOSED_REQUEST, "client closed the request during the upload") from None
        f.flush()
        await run_in_threadpool(os.fsync, f.fileno())
    return size, digest.hexdigest()


async def receive_checkpoint(
    request: Request, server: ServerState, scene_id: str, answer: UploadAnswer
) -> Response:
    """Upload, validate and install one scene; returns ``answer(scene, created)``.

    Uploads (and deletions) of one id run one at a time: a second PUT of the id waits for the
    first, then replaces its scene (200), so two PUTs never both answer 201."""
    limit = server.settings.max_upload_bytes
    declared = _declared_length(request)
    if declared is not None and declared > limit:
        raise HTTPException(
            413,
            f"checkpoint of {declared} bytes is over the upload limit of {limit} bytes",
        )
    if server.uploads_in_progress >= MAX_CONCURRENT_UPLOADS:
        raise HTTPException(503, "too many uploads at once", {"Retry-After": "5"})
    server.uploads_in_progress += 1
    try:
        async with server.scene_locks.hold(scene_id):
            return await _receive_alone(request, server, scene_id, answer)
    finally:
        server.uploads_in_progress -= 1


async def _receive_alone(request: Request, server: ServerState, scene_id: str, answer: UploadAnswer) -> Response:
    """``receive_checkpoint`` once no other upload or deletion of ``scene_id`` runs. The answer
    (status and body) is built before the swap: nothing can fail once the scene is committed."""
    registry = server.registry
    final_path = registry.path_for(scene_id)
    tmp_path: Path | None = None
    try:
        registry.checkpoints_dir.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix=UPLOAD_PREFIX, suffix=UPLOAD_SUFFIX, dir=registry.checkpoints_dir)
        os.close(fd)
        tmp_path = Path(name)
        size, version = await _stream_to(request, tmp_path, server.settings.max_upload_bytes)
        if size == 0:
            raise HTTPException(422, "empty body: send the checkpoint file")
        scene = Scene(scene_id, await _validated(tmp_path, registry, scene_id), final_path, version)
        created = registry.get(scene_id) is None and not final_path.exists()
        response = answer(scene, created)
        await run_in_threadpool(_commit, registry, tmp_path, scene)
        tmp_path = None
        server.cache.drop_scene(scene_id)
        if server.bakes is not None:
            server.bakes.drop_scene(scene_id)
        server.metrics.scenes.set(len(registry))
        logger.info("scene %r %s (%d bytes)", scene_id, "added" if created else "replaced", size)
        return response
    finally:
        if tmp_path is not None:
            tmp_path.unlink(missing_ok=True)


async def _validated(path: Path, registry: SceneRegistry, scene_id: str) -> SceneRenderer:
    """Every checkpoint check and a test render, in a worker thread; 422 naming the problem."""
    try:
        return await run_in_threadpool(load_and_check, path, registry.device, registry.frames)
    except Exception as exc:  # whatever the file does to the loader, it is the file's fault: 422
        logger.info("rejected upload for scene %r: %s", scene_id, exc)
        raise HTTPException(422, f"invalid checkpoint: {exc}") from None


def _commit(registry: SceneRegistry, tmp_path: Path, scene: Scene) -> None:
    """Move the validated file into place and swap the scene in, together."""
    os.chmod(tmp_path, 0o644)
    with registry.mutation_lock:
        os.replace(tmp_path, scene.path)
        registry.install(scene)


def delete_scene(server: ServerState, scene_id: str) -> None:
    """Remove a scene's file and registry entry; 404 when neither exists."""
    registry = server.registry
    path = registry.path_for(scene_id)
    with registry.mutation_lock:
        if registry.get(scene_id) is None and not path.exists():
            raise HTTPException(404, f"unknown scene {scene_id!r}")
        path.unlink(missing_ok=True)
        registry.remove(scene_id)
    server.cache.drop_scene(scene_id)
    if server.bakes is not None:
        server.bakes.drop_scene(scene_id)
    server.metrics.scenes.set(len(registry))
    logger.info("scene %r deleted", scene_id)


async def delete_scene_alone(server: ServerState, scene_id: str) -> None:
    """``delete_scene`` once no upload of ``scene_id`` runs (they share the id's lock). It runs in
    the event loop: an unlink needs no thread from a pool that renders may fill."""
    async with server.scene_locks.hold(scene_id):
        delete_scene(server, scene_id)
