"""Upload a checkpoint to a running ``visnerf serve`` (``PUT /api/scenes/{id}`` with a bearer token).

Used by ``visnerf submit`` and ``visnerf train --submit``. The client side of the API lives in the
model package so that training never imports the server.
"""

import os
from dataclasses import dataclass
from pathlib import Path

import httpx

from visnerf.token_file import configured_token, default_state_dir


class UploadError(Exception):
    """The upload did not happen: no token, the server unreachable, or its refusal (the message says which)."""


@dataclass(frozen=True)
class Uploaded:
    scene_id: str
    url: str
    size: int
    created: bool
    """True when the scene is new on the server, False when it replaced one."""


def find_token(explicit: str | None = None) -> str | None:
    """The upload token: ``explicit``, else as the server looks for it (``token_file.configured_token``:
    ``$VISNERF_TOKEN``, the file ``$VISNERF_TOKEN_FILE``, ``token`` in the state folder).
    UploadError for a named or found token file that cannot be read or is empty."""
    if explicit:
        return explicit
    named = os.environ.get("VISNERF_TOKEN_FILE")
    try:
        return configured_token(os.environ.get("VISNERF_TOKEN"), Path(named) if named else None, default_state_dir())
    except ValueError as exc:
        raise UploadError(str(exc)) from None


def upload_checkpoint(path: Path, server: str, scene_id: str, token: str | None, timeout: float = 300.0) -> Uploaded:
    """Stream ``path`` to ``server`` as scene ``scene_id``; raises ``UploadError`` naming the cause."""
    if not path.is_file():
        raise UploadError(f"{path} is not a file")
    token = find_token(token)
    if not token:
        raise UploadError("no token: pass --token or set VISNERF_TOKEN")
    url = f"{server.rstrip('/')}/api/scenes/{scene_id}"
    size = path.stat().st_size

    def chunks():
        with path.open("rb") as f:
            while chunk := f.read(1 << 20):
                yield chunk

    headers = {"Authorization": f"Bearer {token}", "Content-Type": "application/octet-stream",
               "Content-Length": str(size)}
    try:
        response = httpx.put(url, content=chunks(), headers=headers, timeout=timeout)
    except httpx.HTTPError as exc:
        raise UploadError(f"upload to {url} failed: {exc}") from None
    if response.status_code in (200, 201):
        return Uploaded(scene_id, url, size, response.status_code == 201)
    try:
        detail = response.json().get("detail")
    except ValueError:
        detail = response.text[:500]
    raise UploadError(f"server answered {response.status_code}: {detail}")
