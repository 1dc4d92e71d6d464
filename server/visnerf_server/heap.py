"""Giving the memory of a large frame back to the system once it is rendered.

A large full-quality frame allocates hundreds of megabytes in many blocks (rays, samples, the
image, its encoding), on the render thread and the chunk threads, each of which glibc serves from
an arena of its own. Freed, most of those blocks stay in the arenas: the process keeps them
resident, and after a few large frames the server's memory had grown by 170 MB and stayed there
(bench/results/server_load.md, heavy clients). ``malloc_trim(0)`` hands the free pages of every
arena back; it takes milliseconds, so it runs only after frames of at least ``TRIM_AFTER_PIXELS``.
Elsewhere than glibc (musl, macOS) it does nothing.
"""

import logging

from visnerf.runtime import release_free_memory

log = logging.getLogger(__name__)

TRIM_AFTER_PIXELS = 512 * 512
"""Frames of at least this many pixels give their memory back when done: a 512x512 full frame
allocates about 100 MB; smaller frames reuse the same blocks frame after frame."""


def after_frame(pixels: int) -> None:
    """Called once a frame of ``pixels`` is rendered and encoded."""
    if pixels >= TRIM_AFTER_PIXELS and not release_free_memory():
        log.debug("malloc_trim is not available: the heap keeps the frame's free blocks")
