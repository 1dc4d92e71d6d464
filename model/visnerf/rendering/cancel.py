"""Stopping a render part-way: a frame is marched in chunks of rays, and a cancel check asked
between chunks ends it early with ``RenderCancelled``.

The check is any callable answering whether to stop (``threading.Event().is_set``, a deadline
test, ...); it is asked from the threads that march the chunks, so it must be thread safe and
cheap. A chunk already being marched finishes first: a render stops within one chunk's time
(tens of milliseconds for 4096 rays on a CPU).
"""

from collections.abc import Callable

CancelCheck = Callable[[], bool]
"""Answers True once the render should stop."""


class RenderCancelled(Exception):
    """The render was stopped between chunks of rays because its cancel check answered True
    (its client left, its deadline passed or the server is stopping)."""


def raise_if_cancelled(cancel: CancelCheck | None) -> None:
    """Raise ``RenderCancelled`` when ``cancel`` is given and answers True."""
    if cancel is not None and cancel():
        raise RenderCancelled("render cancelled")
