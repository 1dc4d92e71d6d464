"""SIGTERM and Ctrl-C as a request to stop training cleanly.

Schedulers preempt with SIGTERM and a grace period (Slurm and Kubernetes give 30 s by default);
people press Ctrl-C. Inside ``StopSignals`` the first of either only sets a flag: the training loop
looks at it before each step, writes its run state and returns, within one step and one state
write. A second signal, or any signal after the loop has ended (the run state on disk is then
complete: ``loop_ended``), interrupts at once with ``StopRequested``.
"""

import signal
import threading
from types import FrameType, TracebackType
from typing import Protocol, runtime_checkable

HANDLED = (signal.SIGINT, signal.SIGTERM)


@runtime_checkable
class StopRequest(Protocol):
    """What the training loop asks of a stop source (``StopSignals``; tests stop at an iteration)."""

    def requested(self) -> bool:
        """Whether the loop should stop before its next step."""
        ...

    def loop_ended(self) -> None:
        """Called once the loop has ended and written its last state."""
        ...


class StopRequested(KeyboardInterrupt):
    """Raised for a signal that cannot wait for the loop: ``signum`` names it."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class StopSignals:
    """Context manager: SIGINT / SIGTERM ask the loop to stop (handlers restored on exit)."""

    def __init__(self) -> None:
        self.signum: int | None = None
        """The first signal received, if any."""
        self._immediate = False
        self._previous: dict[int, object] = {}

    def __enter__(self) -> "StopSignals":
        if threading.current_thread() is threading.main_thread():  # handlers live in the main thread only
            for signum in HANDLED:
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)  # type: ignore[arg-type]
        self._previous.clear()

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self._immediate or self.signum is not None:
            self.signum = self.signum or signum
            raise StopRequested(signum)
        self.signum = signum

    def requested(self) -> bool:
        """Whether a stop was asked for."""
        return self.signum is not None

    def loop_ended(self) -> None:
        """From now on a signal interrupts at once (the loop has written its last state)."""
        self._immediate = True
        if self.signum is not None:
            raise StopRequested(self.signum)

    @property
    def exit_status(self) -> int:
        """The shell's convention for a process ended by the signal: 128 + its number."""
        return 128 + (self.signum or signal.SIGINT)

    @property
    def name(self) -> str:
        return signal.Signals(self.signum or signal.SIGINT).name
