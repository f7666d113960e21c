"""Health transitions into the systemd journal with structured fields (through cysystemd,
journald's native protocol), so that an operator finds them with

    journalctl MESSAGE_ID=7f2c5b0e4a1d4c8e9b3f6a2d1e0c5b47 NODE=3

Fields: MESSAGE (the one human line), PRIORITY (info for a return to fault_free, warning
otherwise), MESSAGE_ID, NODE, STATE, PREVIOUS, GAMMA, FAULT, RULES, CAUSE, and
SYSLOG_IDENTIFIER=motor-monitor. Bus events (error frames, outages) get MESSAGE_ID
`BUS_EVENT_ID`.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Any

from monitor.pipeline.events import BusEvent, DiagnosisEvent
from monitor.sinks.base import Sink

__all__ = ["BUS_EVENT_ID", "JOURNAL_SOCKET", "TRANSITION_ID", "JournalSink", "journal_available"]

TRANSITION_ID = "7f2c5b0e4a1d4c8e9b3f6a2d1e0c5b47"
BUS_EVENT_ID = "c1e94a7d35b24f0e8a6d9b2f4c7e1a03"
JOURNAL_SOCKET = Path("/run/systemd/journal/socket")


def journal_available() -> bool:
    """journald is there to take native messages (a systemd service, or a systemd host)."""
    return "JOURNAL_STREAM" in os.environ or JOURNAL_SOCKET.exists()


class JournalSink(Sink):
    """Sends each transition and bus event to journald as one structured entry."""

    def __init__(self) -> None:
        from cysystemd import journal  # libsystemd's sd_journal_send, bundled in the wheel

        self._journal = journal

    def _send(self, **fields: Any) -> None:
        # journald gone (a stopping system): the other outlets carry the event
        with contextlib.suppress(OSError):
            self._journal.send(syslog_identifier="motor-monitor", **fields)

    def on_transition(self, event: DiagnosisEvent) -> None:
        p = self._journal.Priority
        self._send(message=f"node {event.node}: {event.text}", message_id=TRANSITION_ID,
                   priority=int(p.INFO if event.level == "INFO" else p.WARNING),
                   node=str(event.node), state=event.state, previous=event.previous,
                   gamma=f"{event.gamma:.4f}", fault=f"{event.fault_input:.3f}",
                   rules=str(event.rules), cause=event.cause, kind=event.kind,
                   model_mismatch="1" if event.model_mismatch else "0")

    def on_bus_event(self, event: BusEvent) -> None:
        p = self._journal.Priority
        level = {"ERROR": p.ERROR, "WARN": p.WARNING}.get(event.level, p.INFO)
        self._send(message=event.text, message_id=BUS_EVENT_ID, priority=int(level))
