"""Bakes the server answers (``GET /api/scenes/{id}/bake``): one parameter setting of a scene,
built in the render queue's background lane, one at a time, and kept per setting in an LRU
bounded by bytes, shared by every client.

A request for a bake not built yet starts its build (when none is running) and is answered 503
with Retry-After: no worker waits on a bake, and a preview or a full frame never waits behind
one (the background lane is served last). The key is the scene's id, its checkpoint's content
hash and the exact parameter values, so a replaced checkpoint never serves an old bake. A bake is
kept gzip-compressed at level 1, the form it goes out in to every browser
(docs/decisions.md#bake.wire).
"""

import gzip
import hashlib
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

from visnerf.bake.bake_file import bake_bytes
from visnerf.bake.scene_bake import bake_scene
from visnerf.config.bake import BakeConfig
from visnerf_server.metrics import Metrics
from visnerf_server.registry import Scene
from visnerf_server.render_queue import Lane, RenderQueue

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BakeKey:
    scene_id: str
    version: str
    values: tuple[float, ...]

    def etag(self) -> str:
        """A weak validator: the same bake goes out compressed or not (``Vary: Accept-Encoding``)."""
        return 'W/"' + hashlib.sha256(repr((self.scene_id, self.version, self.values)).encode()).hexdigest()[:32] + '"'


class BakeStore:
    """Thread-safe: ``lookup`` answers a built bake's bytes, or starts its build and answers None."""

    def __init__(self, queue: RenderQueue, metrics: Metrics, max_bytes: int, cfg: BakeConfig | None = None) -> None:
        self.queue = queue
        self.metrics = metrics
        self.max_bytes = max_bytes
        self.cfg = cfg or BakeConfig()
        self._bakes: OrderedDict[BakeKey, bytes] = OrderedDict()
        self._bytes = 0
        self._building: BakeKey | None = None
        self._failed: dict[BakeKey, str] = {}
        self._lock = threading.Lock()

    def key(self, scene: Scene, values: list[float]) -> BakeKey:
        return BakeKey(scene.id, scene.version, tuple(float(v) for v in values))

    def lookup(self, scene: Scene, key: BakeKey, before_build: Callable[[], None] | None = None) -> bytes | None:
        """The bake of ``key`` (gzip-compressed), or None while it is being built (its build started here when no
        other is running, after ``before_build``, which may refuse it by raising: the client's
        rate limit). QueueFullError when the queue takes no background work now; RuntimeError
        naming why when its build failed (it is not retried)."""
        with self._lock:
            data = self._bakes.get(key)
            if data is not None:
                self._bakes.move_to_end(key)
                self.metrics.bake_hits.inc()
                return data
            if key in self._failed:
                raise RuntimeError(self._failed[key])
            if self._building is not None:
                return None
            self._building = key
        try:
            if before_build is not None:
                before_build()
            self.queue.submit(lambda: self._build(scene, key), Lane.BACKGROUND)
        except Exception:
            with self._lock:
                self._building = None
            raise
        return None

    def _build(self, scene: Scene, key: BakeKey) -> None:
        started = time.perf_counter()
        try:
            names = [a.name for a in scene.renderer.info.params]
            bake = bake_scene(scene.renderer, dict(zip(names, key.values, strict=True)), self.cfg, key.version[:16])
            data = gzip.compress(bake_bytes(bake), compresslevel=1)
        except Exception as exc:  # a bake that cannot be built is refused, not retried in a loop
            log.exception("baking %s at %s failed", key.scene_id, key.values)
            with self._lock:
                self._failed[key] = f"the bake of this setting failed: {type(exc).__name__}: {exc}"
                self._building = None
            return
        self.metrics.bakes_built.inc()
        self.metrics.bake_seconds.observe(time.perf_counter() - started)
        with self._lock:
            self._building = None
            if len(data) <= self.max_bytes:
                self._bakes[key] = data
                self._bytes += len(data)
                while self._bytes > self.max_bytes:
                    _, dropped = self._bakes.popitem(last=False)
                    self._bytes -= len(dropped)
            self.metrics.bake_cache_bytes.set(self._bytes)

    def drop_scene(self, scene_id: str) -> None:
        """Forget every bake of one scene (it was replaced or deleted)."""
        with self._lock:
            for key in [k for k in self._bakes if k.scene_id == scene_id]:
                self._bytes -= len(self._bakes.pop(key))
            self._failed = {k: v for k, v in self._failed.items() if k.scene_id != scene_id}
            self.metrics.bake_cache_bytes.set(self._bytes)

    @property
    def n_bytes(self) -> int:
        return self._bytes

    def __len__(self) -> int:
        return len(self._bakes)
