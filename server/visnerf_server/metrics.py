"""Prometheus metrics on a per-app registry (never the global default one, so many apps can coexist)."""

from dataclasses import dataclass, field

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest

from visnerf_server.frame_cache import FrameCache

_LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)


@dataclass
class Metrics:
    """The server's metrics; ``render()`` gives the exposition text for ``/metrics``."""

    registry: CollectorRegistry = field(default_factory=lambda: CollectorRegistry(auto_describe=True))

    def __post_init__(self) -> None:
        r = self.registry
        self.render_seconds = Histogram(
            "visnerf_render_seconds",
            "Time to render and encode one frame",
            ["quality"],
            buckets=_LATENCY_BUCKETS,
            registry=r,
        )
        self.queue_depth = Gauge("visnerf_render_queue_depth", "Renders waiting for a worker", registry=r)
        self.in_flight = Gauge("visnerf_renders_in_flight", "Renders running now", registry=r)
        self.rejected = Counter(
            "visnerf_render_rejected", "Renders refused because the queue was full", registry=r
        )
        self.cancelled = Counter(
            "visnerf_renders_cancelled", "Running renders stopped early (deadline passed, client left)", registry=r
        )
        self.rate_limited = Counter(
            "visnerf_rate_limited", "Render requests refused by the per-client rate limit", registry=r
        )
        self.stream_rate_waits = Counter(
            "visnerf_stream_rate_waits", "Stream frames that waited for the client's pixel budget instead of a 429",
            registry=r,
        )
        self.dropped_frames = Counter(
            "visnerf_stream_dropped_frames", "Stale stream requests replaced before rendering", registry=r
        )
        self.cache_hits = Counter("visnerf_frame_cache_hits", "Frames served from the cache", registry=r)
        self.cache_misses = Counter(
            "visnerf_frame_cache_misses", "Frames that had to be rendered", registry=r
        )
        self.responses = Counter(
            "visnerf_http_responses", "HTTP responses by status code", ["status"], registry=r
        )
        self.scenes = Gauge("visnerf_scenes_loaded", "Scenes available", registry=r)
        self.cache_entries = Gauge("visnerf_frame_cache_entries", "Frames in the frame cache", registry=r)
        self.cache_bytes = Gauge(
            "visnerf_frame_cache_bytes", "Memory of the frame cache: frames, keys and overhead", registry=r
        )
        self.stream_sessions = Gauge("visnerf_stream_sessions", "Stream sessions open", registry=r)
        self.stream_refused = Counter(
            "visnerf_stream_refused",
            "Stream handshakes and messages refused: origin, sessions (over the cap), rate",
            ["reason"],
            registry=r,
        )
        self.movie_jobs_started = Counter(
            "visnerf_movie_jobs_started", "Movie jobs that began rendering", registry=r
        )
        self.movie_jobs_finished = Counter(
            "visnerf_movie_jobs_finished",
            "Movie jobs ended, by state: done, failed, cancelled (queued or running)",
            ["state"],
            registry=r,
        )
        self.movie_frames = Counter("visnerf_movie_frames", "Frames rendered for movie jobs", registry=r)
        self.movie_jobs_active = Gauge("visnerf_movie_jobs_active", "Movie jobs queued or running", registry=r)
        self._add_bake_metrics(r)

    def _add_bake_metrics(self, r: CollectorRegistry) -> None:
        """The bake store's (``bakes.BakeStore``)."""
        self.bakes_built = Counter("visnerf_bakes_built", "Bakes of a parameter setting built", registry=r)
        self.bake_seconds = Histogram(
            "visnerf_bake_seconds", "Seconds a bake took to build", buckets=(0.25, 0.5, 1, 2, 4, 8, 16, 32, 64),
            registry=r,
        )
        self.bake_hits = Counter("visnerf_bake_hits", "Bakes answered from the server's store", registry=r)
        self.bake_cache_bytes = Gauge("visnerf_bake_cache_bytes", "Bytes of the bakes the server keeps", registry=r)

    def watch_cache(self, cache: FrameCache) -> None:
        """Report ``cache``'s entries and bytes at each scrape."""
        self.cache_entries.set_function(lambda: len(cache))
        self.cache_bytes.set_function(lambda: cache.n_bytes)

    def render(self) -> bytes:
        return generate_latest(self.registry)
