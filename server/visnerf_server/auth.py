"""The upload/delete token: configured (``VISNERF_TOKEN``, ``VISNERF_TOKEN_FILE``) or generated once.

A generated token lives in ``<state_dir>/token`` with 0600 permissions; only its path is logged.
"""

import logging
import os
import secrets
import stat
from pathlib import Path

from fastapi import HTTPException, status

from visnerf.token_file import TOKEN_FILE_NAME, configured_token, read_token_file
from visnerf_server.settings import Settings

logger = logging.getLogger(__name__)


def _read_token_file(path: Path) -> str:
    try:
        return read_token_file(path)
    except ValueError as exc:  # the server does not start without its token
        raise RuntimeError(str(exc)) from None


def _create_token_file(path: Path) -> str:
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    token = secrets.token_urlsafe(32)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:  # another process created it first
        return _read_token_file(path)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(token + "\n")
    logger.warning("created a new upload token in %s (read it from there; it is not logged)", path)
    return token


def resolve_token(settings: Settings) -> str:
    """The token uploads and deletes need: configured (``token_file.configured_token``, the order
    the clients look in too), else a generated one, written to the state folder."""
    path = settings.state_dir / TOKEN_FILE_NAME
    secret = settings.token.get_secret_value() if settings.token is not None else None
    try:
        token = configured_token(secret, settings.token_file, settings.state_dir)
    except ValueError as exc:  # the server does not start without its token
        raise RuntimeError(str(exc)) from None
    if token is None:
        return _create_token_file(path)
    if not (secret or "").strip() and settings.token_file is None:
        mode = stat.S_IMODE(path.stat().st_mode)
        if mode & 0o077:
            logger.warning("upload token file %s is readable by others (mode %o); use chmod 600", path, mode)
    return token


def check_bearer(authorization: str | None, expected: str) -> None:
    """401 for a missing or malformed ``Authorization`` header, 403 for a wrong token."""
    challenge = {"WWW-Authenticate": "Bearer"}
    if not authorization:
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "missing Authorization: Bearer <token>", challenge)
    scheme, _, presented = authorization.strip().partition(" ")
    if scheme.lower() != "bearer" or not presented.strip():
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "Authorization must be 'Bearer <token>'", challenge)
    if not secrets.compare_digest(presented.strip().encode("utf-8"), expected.encode("utf-8")):
        raise HTTPException(status.HTTP_403_FORBIDDEN, "wrong token")
