"""Diagnosis events as JSON lines (`--events FILE`, or `replay`'s standard output)."""

from __future__ import annotations

from typing import IO

from monitor.pipeline.events import DiagnosisEvent
from monitor.sinks.base import Sink

__all__ = ["JsonLinesSink"]


class JsonLinesSink(Sink):
    """One JSON object per health transition, flushed at once. Closes the stream only if
    `owned` (a file it was given to write, not standard output)."""

    def __init__(self, stream: IO[str], *, owned: bool = False) -> None:
        self.stream = stream
        self.owned = owned

    def on_transition(self, event: DiagnosisEvent) -> None:
        self.stream.write(event.to_json() + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.owned and not self.stream.closed:
            self.stream.close()
