"""Diagnosis events as JSON lines (`--events FILE`, or `replay`'s standard output): each
health transition and model-mismatch change of a node, and what a CANopen drive says about
itself (`DriveEvent`, kind ``drive``)."""

from __future__ import annotations

import dataclasses
from typing import IO

from monitor.pipeline.events import BusEvent, DiagnosisEvent, DriveEvent
from monitor.sinks.base import Sink

__all__ = ["JsonLinesSink"]


class JsonLinesSink(Sink):
    """One JSON object per health transition and per drive report, flushed at once. Closes
    the stream only if `owned` (a file it was given to write, not standard output).
    `fault_unit` is the unit of the events' `fault_input` (`PlantSignals.fault_unit`),
    written as ``fault_input_unit`` where an event has none."""

    def __init__(self, stream: IO[str], *, owned: bool = False,
                 fault_unit: str | None = None) -> None:
        self.stream = stream
        self.owned = owned
        self.fault_unit = fault_unit

    def on_transition(self, event: DiagnosisEvent) -> None:
        if event.fault_input_unit is None and self.fault_unit is not None:
            event = dataclasses.replace(event, fault_input_unit=self.fault_unit)
        self.stream.write(event.to_json() + "\n")
        self.stream.flush()

    def on_bus_event(self, event: BusEvent) -> None:
        if isinstance(event, DriveEvent):
            self.stream.write(event.to_json() + "\n")
            self.stream.flush()

    def close(self) -> None:
        if self.owned and not self.stream.closed:
            self.stream.close()
