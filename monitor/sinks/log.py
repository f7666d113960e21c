"""The log outlet: health transitions as log lines (the service's journal)."""

from __future__ import annotations

import logging

from monitor.pipeline.events import DiagnosisEvent
from monitor.sinks.base import Sink

__all__ = ["LogSink"]


class LogSink(Sink):
    """Logs every health transition at INFO on the `motor_monitor` logger."""

    def __init__(self, logger: logging.Logger | None = None) -> None:
        self.log = logger or logging.getLogger("motor_monitor")

    def on_transition(self, event: DiagnosisEvent) -> None:
        self.log.info("node %d: %s", event.node, event.text)
