"""SIGINT/SIGTERM as a stop request, for the daemon's loop and the virtual ECU alike."""

from __future__ import annotations

import signal
import threading
from types import FrameType
from typing import Any

__all__ = ["StopOnSignals"]


class StopOnSignals:
    """Within the block, SIGINT and SIGTERM set `event` (the previous handlers come back
    afterwards). Only the main thread can install handlers; elsewhere this does nothing."""

    def __init__(self, event: threading.Event | None = None) -> None:
        self.event = event if event is not None else threading.Event()
        self.signum: int | None = None
        self._old: dict[int, Any] = {}

    @property
    def received(self) -> str | None:
        """The name of the signal that stopped the run (e.g. "SIGTERM"), None if none."""
        return None if self.signum is None else signal.Signals(self.signum).name

    def _handler(self, signum: int, frame: FrameType | None) -> None:
        self.signum = signum
        self.event.set()

    def __enter__(self) -> StopOnSignals:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._old[sig] = signal.signal(sig, self._handler)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old.clear()
