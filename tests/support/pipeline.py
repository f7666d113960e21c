"""Driving a `MonitorPipeline` in tests: its transitions and the frames it publishes, kept
in lists."""

from __future__ import annotations

from collections.abc import Iterable

import can

from monitor.bus.codec import MotorDatabase
from monitor.pipeline import Counters, DiagnosisEvent, MonitorConfig, MonitorPipeline
from monitor.sinks.base import FanOut, Sink
from monitor.sinks.publisher import BusPublisher


class Transitions(Sink):
    """Keeps every transition."""

    def __init__(self, events: list[DiagnosisEvent] | None = None) -> None:
        self.events: list[DiagnosisEvent] = [] if events is None else events

    def on_transition(self, event: DiagnosisEvent) -> None:
        self.events.append(event)


def pipeline(db: MotorDatabase, cfg: MonitorConfig | None = None, *,
             events: list[DiagnosisEvent] | None = None, sent: list[can.Message] | None = None,
             sink: Sink | None = None) -> MonitorPipeline:
    """A pipeline whose transitions go to `events` and whose MonitorDiagnosis frames go to
    `sent` (each if given), besides `sink`."""
    counters = Counters()
    sinks: list[Sink] = [] if sink is None else [sink]
    if sent is not None:
        sinks.append(BusPublisher(db, sent.append, counters))
    if events is not None:
        sinks.append(Transitions(events))
    return MonitorPipeline(db, cfg, sink=FanOut(sinks), counters=counters)


def feed_all(pipe: MonitorPipeline, frames: Iterable[can.Message]) -> None:
    for msg in frames:
        pipe.feed(msg)


def stalled(frames: list[can.Message], t0: float, t1: float) -> list[can.Message]:
    """`frames` as a sender held up from `t0` to `t1` sends them: what was due meanwhile goes
    out back to back at `t1`, in order."""
    out = []
    j = 0
    for m in frames:
        t = m.timestamp
        if t0 <= t < t1:
            t = t1 + 1e-5 * j
            j += 1
        out.append(can.Message(arbitration_id=m.arbitration_id, data=m.data,
                               is_extended_id=False, timestamp=t))
    return out


def without_currents(frames: list[can.Message], first: int, n: int,
                     current_id: int = 0x110) -> list[can.Message]:
    """`frames` without current frames number first .. first + n - 1."""
    currents = [i for i, m in enumerate(frames) if m.arbitration_id == current_id]
    gone = set(currents[first:first + n])
    return [m for i, m in enumerate(frames) if i not in gone]
