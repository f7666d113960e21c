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
