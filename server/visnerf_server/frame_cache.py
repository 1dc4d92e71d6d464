"""A small LRU cache of encoded frames, bounded by bytes."""

import threading
from collections import OrderedDict
from collections.abc import Hashable
from dataclasses import dataclass


@dataclass(frozen=True)
class CachedFrame:
    data: bytes
    media_type: str
    width: int
    height: int
    render_ms: float
    """How long the original render took."""


class FrameCache:
    """Thread-safe LRU mapping request keys to encoded frames; holds at most ``max_bytes`` of data."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self._frames: OrderedDict[Hashable, CachedFrame] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, key: Hashable) -> CachedFrame | None:
        with self._lock:
            frame = self._frames.get(key)
            if frame is not None:
                self._frames.move_to_end(key)
            return frame

    def put(self, key: Hashable, frame: CachedFrame) -> None:
        size = len(frame.data)
        if size > self.max_bytes:
            return
        with self._lock:
            old = self._frames.pop(key, None)
            if old is not None:
                self._bytes -= len(old.data)
            self._frames[key] = frame
            self._bytes += size
            while self._bytes > self.max_bytes:
                _, evicted = self._frames.popitem(last=False)
                self._bytes -= len(evicted.data)

    def drop_scene(self, scene_id: str) -> None:
        """Forget every frame of one scene (keys start with the scene id)."""
        with self._lock:
            for key in [k for k in self._frames if isinstance(k, tuple) and k and k[0] == scene_id]:
                self._bytes -= len(self._frames.pop(key).data)

    @property
    def n_bytes(self) -> int:
        return self._bytes

    def __len__(self) -> int:
        return len(self._frames)
