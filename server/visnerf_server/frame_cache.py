"""A small LRU cache of encoded frames, bounded by the memory its entries take and by their number.

An entry costs its frame's bytes, its key (the request: a tuple of some 30 numbers and strings,
``frames.FrameJob.key``) and a fixed overhead (``ENTRY_OVERHEAD_BYTES``). Counting the frame's
bytes alone let a cache of tiny frames hold several times its budget.
"""

import sys
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


ENTRY_OVERHEAD_BYTES = 352
"""Memory an entry takes besides its frame's data bytes and its key (``key_bytes``), measured with
tracemalloc on CPython 3.11 for 1-byte frames: the ``bytes`` header, the ``CachedFrame`` and its
render time 135 bytes; the OrderedDict's slot and link, the (frame, size) pair and the size 145
to 201 bytes an entry with the table's fill (100 to 43000 entries). ``key_bytes`` counts a key
like the server's (``FrameJob.key``) as 1197 bytes where it holds 929 (strings and small numbers
are shared). ``test_frame_cache_memory_is_bounded`` checks the sum against tracemalloc."""


def key_bytes(key: object) -> int:
    """``sys.getsizeof`` of the key and of everything inside its tuples (strings and numbers
    shared between keys are counted for each: an upper bound)."""
    size = sys.getsizeof(key)
    if isinstance(key, tuple | frozenset):
        size += sum(key_bytes(item) for item in key)
    return size


class FrameCache:
    """Thread-safe LRU mapping request keys to encoded frames: at most ``max_bytes`` of memory
    (frames, keys and overhead) and at most ``max_entries`` frames."""

    def __init__(self, max_bytes: int, max_entries: int = 4096) -> None:
        self.max_bytes = max_bytes
        self.max_entries = max_entries
        self._frames: OrderedDict[Hashable, tuple[CachedFrame, int]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    @staticmethod
    def entry_bytes(key: Hashable, frame: CachedFrame) -> int:
        """What an entry is counted as: data, key and ``ENTRY_OVERHEAD_BYTES``."""
        return len(frame.data) + key_bytes(key) + ENTRY_OVERHEAD_BYTES

    def get(self, key: Hashable) -> CachedFrame | None:
        with self._lock:
            entry = self._frames.get(key)
            if entry is None:
                return None
            self._frames.move_to_end(key)
            return entry[0]

    def put(self, key: Hashable, frame: CachedFrame) -> None:
        size = self.entry_bytes(key, frame)
        if size > self.max_bytes or self.max_entries < 1:
            return
        with self._lock:
            old = self._frames.pop(key, None)
            if old is not None:
                self._bytes -= old[1]
            self._frames[key] = (frame, size)
            self._bytes += size
            while self._bytes > self.max_bytes or len(self._frames) > self.max_entries:
                _, (_, evicted) = self._frames.popitem(last=False)
                self._bytes -= evicted

    def drop_scene(self, scene_id: str) -> None:
        """Forget every frame of one scene (keys start with the scene id)."""
        with self._lock:
            for key in [k for k in self._frames if isinstance(k, tuple) and k and k[0] == scene_id]:
                self._bytes -= self._frames.pop(key)[1]

    @property
    def n_bytes(self) -> int:
        """Memory the entries are counted as (``entry_bytes``)."""
        return self._bytes

    def __len__(self) -> int:
        return len(self._frames)
