"""Server settings: environment variables prefixed ``VISNERF_`` (e.g. ``VISNERF_TOKEN``), or CLI flags.

``get_settings`` is the lru_cached dependency (FastAPI's settings pattern); ``create_app(settings)``
overrides it with the settings the app was built with.
"""

from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict

_PROJECT_ROOT = Path(__file__).resolve().parents[2]
"""The checkout (or install prefix) holding ``server/``, ``checkpoints/`` and ``client/``."""


def default_checkpoints_dir() -> Path:
    """The project's bundled ``checkpoints/`` folder, or ``./checkpoints`` outside a checkout."""
    bundled = _PROJECT_ROOT / "checkpoints"
    return bundled if bundled.is_dir() else Path.cwd() / "checkpoints"


def default_client_dir() -> Path | None:
    """The web client's static files, when this install has them."""
    client = _PROJECT_ROOT / "client"
    return client if client.is_dir() else None


class Settings(BaseSettings):
    """Everything the render server can be told; all sizes in bytes, all times in seconds."""

    model_config = SettingsConfigDict(env_prefix="VISNERF_", frozen=True, extra="ignore")

    checkpoints_dir: Path = Field(default_factory=default_checkpoints_dir)
    """Folder of ``<scene id>.safetensors`` files; uploads land here."""
    client_dir: Path | None = Field(default_factory=default_client_dir)
    """Static web client served at ``/``; ``None`` serves the API only."""
    state_dir: Path = Field(default_factory=lambda: Path.home() / ".config" / "visnerf")
    """Where the generated upload token is kept when none is configured."""
    token: SecretStr | None = None
    """Upload/delete token (``VISNERF_TOKEN``)."""
    token_file: Path | None = None
    """File holding the upload/delete token (``VISNERF_TOKEN_FILE``)."""
    device: str = "cpu"
    """Torch device the scenes are loaded on, chosen once here."""

    max_image_size: int = Field(default=2048, ge=8, le=8192)
    """Largest width or height a client may ask for."""
    max_upload_bytes: int = Field(default=64 * 1024 * 1024, ge=1)
    """Largest checkpoint accepted by ``PUT /api/scenes/{id}``."""
    max_request_bytes: int = Field(default=1024 * 1024, ge=1024)
    """Largest body of any other request."""

    render_workers: int = Field(default=1, ge=1, le=64)
    """Renders running at once (threads)."""
    render_queue_size: int = Field(default=8, ge=0, le=1024)
    """Renders allowed to wait for a worker; beyond that the server answers 503."""
    render_timeout_s: float = Field(default=30.0, gt=0)
    """Per-request limit, waiting included: 503 if still queued, 504 if still rendering."""
    retry_after_s: int = Field(default=1, ge=1)
    """``Retry-After`` sent with 503 answers."""
    frame_cache_bytes: int = Field(default=64 * 1024 * 1024, ge=0)
    """Memory for the LRU cache of encoded frames."""
    jpeg_quality: int = Field(default=88, ge=1, le=100)
    """JPEG and WebP quality."""

    warmup: bool = True
    """Render one tiny frame per scene before reporting ready."""
    background_load: bool = True
    """Load scenes after the server starts listening (``/api/ready`` answers 503 meanwhile)."""
    log_format: Literal["json", "text"] = "json"
    """Access log: one JSON line per request, or plain text."""


@lru_cache
def get_settings() -> Settings:
    """Settings from the environment, read once."""
    return Settings()
