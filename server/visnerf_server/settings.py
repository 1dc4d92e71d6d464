"""Server settings: environment variables prefixed ``VISNERF_`` (e.g. ``VISNERF_TOKEN``), or CLI flags.

``get_settings`` is the lru_cached dependency (FastAPI's settings pattern); ``create_app(settings)``
overrides it with the settings the app was built with.
"""

import dataclasses
import ipaddress
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from visnerf.config import FramesConfig
from visnerf.token_file import default_state_dir
from visnerf_server.origins import normalize_origin

MIN_FRAME_PIXELS = 64
"""The smallest frame (8x8) any pixel budget must allow."""

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
    state_dir: Path = Field(default_factory=default_state_dir)
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

    render_workers: int | None = Field(default=None, ge=1, le=64)
    """Renders running at once (threads), of any quality; None: one per render thread
    (``threads``). A frame alone marches its rays on every render thread, frames at once share
    them (``visnerf.rendering.parallel``, which gives the figures)."""
    preview_workers: int = Field(default=1, ge=0, le=8)
    """More render threads that take previews only, so that a drag is answered while full frames
    occupy the other workers."""
    render_queue_size: int = Field(default=8, ge=0, le=1024)
    """Renders allowed to wait for a worker; beyond that the server answers 503."""
    render_timeout_s: float = Field(default=30.0, gt=0)
    """Per-request limit, waiting included: 503 if still queued, 504 if still rendering."""
    retry_after_s: int = Field(default=1, ge=1)
    """``Retry-After`` sent with 503 answers."""
    # How a frame is cut into work, and the per-setting grids kept (``FramesConfig``: its defaults)
    chunk_rays: int = FramesConfig.chunk_rays
    """Rays per chunk of a frame; on the CPU the chunks go one per render thread."""
    segment_samples: int = FramesConfig.segment_samples
    """Samples marched per segment of a chunk before its finished rays are dropped."""
    first_segment_samples: int = FramesConfig.first_segment_samples
    """Samples in a ray's first segment (each later one doubles, up to ``segment_samples``)."""
    setting_grids: int = FramesConfig.setting_grids
    """Per-setting occupancy grids kept per scene (0: none, every frame marches the union grid)."""
    setting_grid_after: int = FramesConfig.setting_grid_after
    """Full-quality frames at one parameter setting before its grid is built (in the background lane)."""
    setting_grid_samples: int = FramesConfig.setting_grid_samples
    """Density samples per cell and axis of a per-setting grid."""
    refine_spacing: int = FramesConfig.refine_spacing
    """Largest spacing of the pixel lattice a large full-quality frame is marched on first (1: every pixel)."""
    refine_spread: float = FramesConfig.refine_spread
    """Colour difference over a lattice cell's corners above which its pixels are marched, not blended."""

    # Costs per request and per client, from the slowest bundled scenes' cost per megapixel
    # (docs/decisions.md#server.frame_costs)
    threads: int | None = Field(default=None, ge=1, le=1024)
    """Torch threads for rendering (``VISNERF_THREADS``, ``--threads``); None: the CPU quota of
    the server's cgroup where there is one, else the cores it may run on."""
    max_preview_pixels: int = Field(default=512 * 512, ge=MIN_FRAME_PIXELS)
    """Largest width x height of a preview frame: 512x512 renders in about 0.43 s (0.57 s at
    the p95 rate). Previews go ahead of queued full frames, so they must stay cheap."""
    max_full_pixels: int = Field(default=1920 * 1080, ge=MIN_FRAME_PIXELS)
    """Largest width x height of a full-quality frame: 1920x1080 renders in about 9.3 s (10.2 s at
    the p95 rate), a third of ``render_timeout_s``."""
    preview_pixel_cost: float = Field(default=0.3, gt=0.0, le=1.0)
    """What a preview pixel costs against a full-quality one (rate limit): 0.19 to 0.37 measured
    at 256x256, 0.34 on the slowest scene."""
    rate_limit_pixels_per_s: float = Field(default=100_000.0, ge=0.0)
    """Full-quality pixels each client may have rendered per second, sustained (cache hits are
    free): about 0.45 s of rendering per second on the slowest scene. 0 turns the limit off."""
    rate_limit_burst_pixels: int = Field(default=1920 * 1080, ge=1)
    """Pixels a client may spend at once from a full bucket (one largest full frame); a frame that
    costs more waits for a full bucket."""
    rate_limit_clients: int = Field(default=10_000, ge=1)
    """Clients the rate limiter remembers; an idle client's bucket (refilled) is forgotten first."""

    frame_cache_bytes: int = Field(default=64 * 1024 * 1024, ge=0)
    """Memory for the LRU cache of encoded frames."""
    bake_cache_bytes: int = Field(default=256 * 1024 * 1024, ge=0)
    """Memory for the bakes built (``GET /api/scenes/{id}/bake``), least recently used dropped
    first (bench/results/bake_fidelity.md has the sizes)."""
    bake_cost_pixels: int = Field(default=512 * 512, ge=1)
    """What a bake's build costs against a client's rate limit, in full-quality pixels: a bake of a
    bundled scene takes about as long as a 512x512 full frame (bench/results/bake_fidelity.md)."""
    jpeg_quality: int = Field(default=88, ge=1, le=100)
    """JPEG and WebP quality."""

    warmup: bool = True
    """Render one tiny frame per scene before reporting ready."""
    background_load: bool = True
    """Load scenes after the server starts listening (``/api/ready`` answers 503 meanwhile)."""
    log_format: Literal["json", "text"] = "json"
    """Access log: one JSON line per request, or plain text."""

    # WebSocket, errors and documentation
    ws_max_message_bytes: int = Field(default=64 * 1024, ge=1024, le=16 * 1024 * 1024)
    """Largest stream message. ``visnerf serve`` gives it to uvicorn (``ws_max_size``), whose
    protocol closes the connection with code 1009 on a bigger frame before buffering it; the stream
    also refuses longer text itself (an error message), for servers started another way."""
    ws_max_sessions: int = Field(default=32, ge=1, le=100_000)
    """Stream sessions open at once; one more gets an error (status 503, ``retry_after``) and
    close code 1013 (try again later)."""
    ws_messages_per_s: float = Field(default=30.0, gt=0, le=10_000)
    """Sustained messages a second one stream session may send (a token bucket refilled at this
    rate); a message over it is not rendered and gets an error with status 429 and ``retry_after``,
    the session stays open."""
    ws_message_burst: int = Field(default=60, ge=1, le=100_000)
    """Messages a stream session may send at once before ``ws_messages_per_s`` applies."""
    allowed_origins: Annotated[tuple[str, ...], NoDecode] = ()
    """Browser origins allowed to open a stream besides the server's own (the ``Host`` header):
    ``VISNERF_ALLOWED_ORIGINS=https://a.example,http://b.example:8080``. A handshake without
    ``Origin`` (not a browser) is allowed; one from any other origin is refused with 403."""
    docs_assets_dir: Path | None = None
    """Folder with Swagger UI's ``swagger-ui-bundle.js`` and ``swagger-ui.css`` (npm package
    ``swagger-ui-dist``) and ReDoc's ``redoc.standalone.js``: ``/docs`` and ``/redoc`` are served,
    with those files and nothing from a CDN, only when it is set (off by default; ``/openapi.json``
    is always served)."""
    frame_cache_entries: int = Field(default=4096, ge=0)
    """Most frames the frame cache holds, whatever their size (``frame_cache_bytes`` counts each
    entry's overhead too)."""

    # Movie jobs (``POST /api/scenes/{id}/movies``): rendered frame by frame in the render queue's
    # background lane, below every interactive render. Rates as above (slowest scene, 2-core CPU).
    movie_max_frames: int = Field(default=1800, ge=1, le=100_000)
    """Most frames one movie job may have: one minute at 30 fps."""
    movie_max_pixels: int = Field(default=600 * 512 * 512, ge=MIN_FRAME_PIXELS)
    """Largest frames x width x height of one job (157 MP: 600 frames of 512x512, 20 s at 30 fps):
    about 12 min of rendering at full quality (4.6 s/MP), 4 min as previews, on an idle server. Each
    frame is also held to ``max_image_size`` and its quality's pixel budget, like a single render."""
    movie_jobs_running: int = Field(default=1, ge=1, le=16)
    """Movie jobs rendering at once. Their frames share the render workers with interactive
    renders at the lowest priority, so a second job would only slow the first."""
    movie_jobs_queued: int = Field(default=3, ge=0, le=1000)
    """Movie jobs allowed to wait for a running one to finish; beyond that a new job gets 429."""
    movie_jobs_per_client: int = Field(default=2, ge=1, le=1000)
    """Movie jobs one client (``rate_limit.client_key``) may have queued or running at once."""
    movie_keep_s: float = Field(default=1800.0, gt=0)
    """How long a finished job (its file and its status) is kept: 30 minutes."""
    movie_max_disk_bytes: int = Field(default=1024 * 1024 * 1024, ge=1)
    """Disk the finished movie files may take together (1 GiB); the oldest are deleted first to
    make room for a new one. They live in a temporary folder removed at shutdown."""
    movie_dir: Path | None = None
    """Folder in which that temporary folder is made; None: the system's temporary folder."""

    # Replicas: several servers over one checkpoints folder, behind a proxy (docker/README.md)
    store_poll_s: float = Field(default=2.0, ge=0.0, le=3600.0)
    """How often the checkpoints folder is compared with the scenes served (``store_watch``), so
    that an upload or deletion through another server sharing the folder reaches this one: a new
    file is served within two polls and its load. 0 turns the watcher off."""
    trusted_proxies: Annotated[tuple[str, ...], NoDecode] = ()
    """Proxies whose ``X-Forwarded-For`` and ``X-Forwarded-Proto`` are believed, as addresses or
    networks: ``VISNERF_TRUSTED_PROXIES=127.0.0.1,10.0.0.0/8`` (``*``: any peer). Behind nginx every
    request comes from the proxy; from a trusted one the client's address (the rate limit's key) is
    the last one in ``X-Forwarded-For`` that is not a trusted proxy. Empty: nobody is believed."""

    @model_validator(mode="after")
    def _frames_fit(self) -> "Settings":
        self.frames()  # ValueError names the setting
        return self

    def frames(self) -> FramesConfig:
        """How this server cuts frames into work and keeps per-setting grids."""
        return FramesConfig(**{f.name: getattr(self, f.name) for f in dataclasses.fields(FramesConfig)})

    @field_validator("allowed_origins", mode="before")
    @classmethod
    def _split_origins(cls, value: object) -> object:
        """A comma-separated string (the environment variable) or a list; each origin normalised."""
        items = value.split(",") if isinstance(value, str) else value
        if not isinstance(items, list | tuple):
            return value
        return tuple(normalize_origin(str(item)) for item in items if str(item).strip())

    @field_validator("trusted_proxies", mode="before")
    @classmethod
    def _split_proxies(cls, value: object) -> object:
        """A comma-separated string (the environment variable) or a list; each an IP address or
        network, or ``*``."""
        items = value.split(",") if isinstance(value, str) else value
        if not isinstance(items, list | tuple):
            return value
        proxies = tuple(str(item).strip() for item in items if str(item).strip())
        for proxy in proxies:
            if proxy != "*":
                ipaddress.ip_network(proxy, strict=False)  # ValueError names the bad one
        return proxies


@lru_cache
def get_settings() -> Settings:
    """Settings from the environment, read once."""
    return Settings()
