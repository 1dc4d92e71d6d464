"""Where the upload token lives and how it is read: one rule for the server that writes it
(``visnerf_server.auth``) and the clients that send it (``visnerf.upload``)."""

import os
from pathlib import Path

TOKEN_FILE_NAME = "token"
"""The token's file in the state folder."""


def default_state_dir() -> Path:
    """``$VISNERF_STATE_DIR``, else ``~/.config/visnerf`` (``Settings.state_dir``'s default)."""
    state_dir = os.environ.get("VISNERF_STATE_DIR")
    return Path(state_dir) if state_dir else Path.home() / ".config" / "visnerf"


def read_token_file(path: Path) -> str:
    """The token in ``path``, stripped; ValueError naming the file when it cannot be read or is empty."""
    try:
        token = path.read_text(encoding="utf-8").strip()
    except OSError as exc:
        raise ValueError(f"cannot read the upload token file {path}: {exc.strerror or exc}") from None
    if not token:
        raise ValueError(f"the upload token file {path} is empty")
    return token


def configured_token(token: str | None, token_file: Path | None, state_dir: Path) -> str | None:
    """The upload token, looked up in one order by the server and its clients: ``token``
    (``VISNERF_TOKEN``), else the file ``token_file`` (``VISNERF_TOKEN_FILE``), else ``token`` in
    ``state_dir`` where that file exists; None where none is configured (the server then makes
    one). ValueError names a file that cannot be read or is empty."""
    if token is not None and token.strip():
        return token.strip()
    if token_file is not None:
        return read_token_file(token_file)
    path = state_dir / TOKEN_FILE_NAME
    return read_token_file(path) if path.is_file() else None

