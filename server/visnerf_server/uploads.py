"""Checkpoint uploads: stream to a hidden temporary file in the checkpoints folder (size checked
while streaming), validate fully (every checkpoint check, then a tiny test render), then
``os.replace`` into place and swap the scene in the registry. Nothing is left behind on failure."""

import hashlib
import logging
import os
import tempfile
import time
from pathlib import Path

from fastapi import HTTPException, Request
from starlette.concurrency import run_in_threadpool

from visnerf_server.dependencies import ServerState
from visnerf_server.registry import Scene, load_and_check

logger = logging.getLogger(__name__)

UPLOAD_PREFIX = ".upload-"
UPLOAD_SUFFIX = ".tmp"
MAX_CONCURRENT_UPLOADS = 2
STALE_UPLOAD_SECONDS = 3600.0


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
    """Write the body to ``path``; 413 as soon as it passes ``limit`` bytes. Returns (size, sha256)."""
    size = 0
    digest = hashlib.sha256()
    with path.open("wb") as f:
        async for chunk in request.stream():
            size += len(chunk)
            if size > limit:
                raise HTTPException(413, f"checkpoint is over the upload limit of {limit} bytes")
            digest.update(chunk)
            f.write(chunk)
        f.flush()
        await run_in_threadpool(os.fsync, f.fileno())
    return size, digest.hexdigest()


async def receive_checkpoint(request: Request, server: ServerState, scene_id: str) -> tuple[Scene, bool]:
    """Upload, validate and install one scene; returns (scene, replaced an existing one)."""
    registry = server.registry
    limit = server.settings.max_upload_bytes
    final_path = registry.path_for(scene_id)
    declared = _declared_length(request)
    if declared is not None and declared > limit:
        raise HTTPException(
            413,
            f"checkpoint of {declared} bytes is over the upload limit of {limit} bytes",
        )
    if server.uploads_in_progress >= MAX_CONCURRENT_UPLOADS:
        raise HTTPException(503, "too many uploads at once", {"Retry-After": "5"})
    server.uploads_in_progress += 1
    tmp_path: Path | None = None
    try:
        registry.checkpoints_dir.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix=UPLOAD_PREFIX, suffix=UPLOAD_SUFFIX, dir=registry.checkpoints_dir)
        os.close(fd)
        tmp_path = Path(name)
        size, version = await _stream_to(request, tmp_path, limit)
        if size == 0:
            raise HTTPException(422, "empty body: send the checkpoint file")
        try:
            renderer = await run_in_threadpool(load_and_check, tmp_path, registry.device)
        except Exception as exc:  # whatever the file does to the loader, it is the file's fault: 422
            logger.info("rejected upload for scene %r: %s", scene_id, exc)
            raise HTTPException(422, f"invalid checkpoint: {exc}") from None
        scene = Scene(scene_id, renderer, final_path, version)

        def commit() -> bool:
            os.chmod(tmp_path, 0o644)
            with registry.mutation_lock:
                os.replace(tmp_path, final_path)
                return registry.install(scene)

        replaced = await run_in_threadpool(commit)
        tmp_path = None
        server.cache.drop_scene(scene_id)
        server.metrics.scenes.set(len(registry))
        logger.info("scene %r %s (%d bytes)", scene_id, "replaced" if replaced else "added", size)
        return scene, replaced
    finally:
        server.uploads_in_progress -= 1
        if tmp_path is not None:
            tmp_path.unlink(missing_ok=True)


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
    server.metrics.scenes.set(len(registry))
    logger.info("scene %r deleted", scene_id)
