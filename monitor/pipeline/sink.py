"""One small interface for every outlet of the pipeline, the way python-can's `Listener`
takes messages from a `Notifier`.

The pipeline calls the `on_*` methods, in data order, from one thread; the application
that wired the sinks calls `maybe_flush` periodically and `close` once at exit. Every
method of `Sink` does nothing, so an outlet overrides only what it consumes. `FanOut`
hands each event to several sinks in order.

It lives beside the events it receives (`monitor.pipeline.events`): the pipeline hands its
events to a `Sink` without importing any outlet (`monitor.sinks`, which re-exports both).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from types import TracebackType
from typing import Self

from monitor.pipeline.events import BusEvent, Diagnosis, DiagnosisEvent, InputSample, Sample

__all__ = ["FanOut", "Sink"]


class Sink:
    """An outlet of the pipeline; this base drops everything."""

    def on_sample(self, sample: Sample) -> None:
        """One estimator step of a node."""

    def on_input(self, sample: InputSample) -> None:
        """An input of a node, as a frame carried it."""

    def on_transition(self, event: DiagnosisEvent) -> None:
        """A node's health state changed."""

    def on_diagnosis(self, diagnosis: Diagnosis) -> None:
        """A node's diagnosis is due for publication (on change and at a steady rate)."""

    def on_bus_event(self, event: BusEvent) -> None:
        """An error frame, an interface outage or its end."""

    def on_counters(self, t: float, counters: Mapping[str, int]) -> None:
        """The pipeline's counters at bus time `t` (about once a second, and at exit)."""

    def maybe_flush(self, now_monotonic: float) -> None:
        """Housekeeping the application calls often: flush what is due."""

    def flush(self) -> None:
        """Write out everything buffered."""

    def close(self) -> None:
        """Flush and release; later events are dropped."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


class FanOut(Sink):
    """Several sinks behind one: every call goes to each, in the order given."""

    def __init__(self, sinks: Iterable[Sink]) -> None:
        self.sinks: tuple[Sink, ...] = tuple(sinks)

    def on_sample(self, sample: Sample) -> None:
        for s in self.sinks:
            s.on_sample(sample)

    def on_input(self, sample: InputSample) -> None:
        for s in self.sinks:
            s.on_input(sample)

    def on_transition(self, event: DiagnosisEvent) -> None:
        for s in self.sinks:
            s.on_transition(event)

    def on_diagnosis(self, diagnosis: Diagnosis) -> None:
        for s in self.sinks:
            s.on_diagnosis(diagnosis)

    def on_bus_event(self, event: BusEvent) -> None:
        for s in self.sinks:
            s.on_bus_event(event)

    def on_counters(self, t: float, counters: Mapping[str, int]) -> None:
        for s in self.sinks:
            s.on_counters(t, counters)

    def maybe_flush(self, now_monotonic: float) -> None:
        for s in self.sinks:
            s.maybe_flush(now_monotonic)

    def flush(self) -> None:
        for s in self.sinks:
            s.flush()

    def close(self) -> None:
        """Close every sink, even if one fails; the first failure is raised afterwards."""
        first: BaseException | None = None
        for s in self.sinks:
            try:
                s.close()
            except BaseException as exc:  # the others must still close
                first = first or exc
        if first is not None:
            raise first
