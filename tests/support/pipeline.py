"""Driving a `MonitorPipeline` in tests: its transitions and the frames it publishes, kept
in lists; a sink that keeps everything a pipeline gives it (`Recorder`)."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import can

from monitor.bus.codec import Decoded, MotorDatabase
from monitor.estimation.fuzzy_ukf import FuzzyUKFConfig
from monitor.pipeline import Counters, DiagnosisEvent, MonitorConfig, MonitorPipeline
from monitor.pipeline.core import FrameDecoder
from monitor.pipeline.events import BusEvent, Diagnosis, InputSample, Sample
from monitor.pipeline.feed import feed_log
from monitor.sinks.base import FanOut, Sink
from monitor.sinks.publisher import BusPublisher


class Transitions(Sink):
    """Keeps every transition."""

    def __init__(self, events: list[DiagnosisEvent] | None = None) -> None:
        self.events: list[DiagnosisEvent] = [] if events is None else events

    def on_transition(self, event: DiagnosisEvent) -> None:
        self.events.append(event)


@dataclass
class Recorder(Sink):
    """Keeps every transition, diagnosis, bus event, sample and input sample, in order."""

    transitions: list[DiagnosisEvent] = field(default_factory=list)
    diagnoses: list[Diagnosis] = field(default_factory=list)
    bus: list[BusEvent] = field(default_factory=list)
    samples: list[Sample] = field(default_factory=list)
    inputs: list[InputSample] = field(default_factory=list)

    def on_transition(self, event: DiagnosisEvent) -> None:
        self.transitions.append(event)

    def on_diagnosis(self, diagnosis: Diagnosis) -> None:
        self.diagnoses.append(diagnosis)

    def on_bus_event(self, event: BusEvent) -> None:
        self.bus.append(event)

    def on_sample(self, sample: Sample) -> None:
        self.samples.append(sample)

    def on_input(self, sample: InputSample) -> None:
        self.inputs.append(sample)


def pipeline(db: FrameDecoder, cfg: MonitorConfig | None = None, *,
             events: list[DiagnosisEvent] | None = None, sent: list[can.Message] | None = None,
             sink: Sink | None = None) -> MonitorPipeline:
    """A pipeline whose transitions go to `events` and whose MonitorDiagnosis frames go to
    `sent` (each if given), besides `sink`."""
    counters = Counters()
    sinks: list[Sink] = [] if sink is None else [sink]
    if sent is not None:
        # MonitorDiagnosis frames exist on our own bus only, as in `monitor.app.daemon`
        assert isinstance(db, MotorDatabase), "frames to `sent` need our own bus's database"
        sinks.append(BusPublisher(db, sent.append, counters))
    if events is not None:
        sinks.append(Transitions(events))
    return MonitorPipeline(db, cfg, sink=FanOut(sinks), counters=counters)


def decode_all(db: FrameDecoder, frames: Iterable[can.Message]) -> list[Decoded]:
    """`frames` decoded, after asserting that the decoder rejects none of them."""
    decoded = [db.decode_can(m) for m in frames]
    rejected = [d for d in decoded if not isinstance(d, Decoded)]
    assert not rejected, rejected[:3]
    return [d for d in decoded if isinstance(d, Decoded)]


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


def changed_currents(db: MotorDatabase, frames: Iterable[can.Message],
                     change: Callable[[float, float], float]) -> list[can.Message]:
    """`frames` with every current frame re-encoded to read ``change(value, timestamp)``
    (its counter kept, so the frame stays valid): a sensor's offset or noise."""
    out = []
    for m in frames:
        d = db.decode_can(m)
        if isinstance(d, Decoded) and d.kind == "current":
            value = change(d.value, m.timestamp)
            if value != d.value:
                data = db.encode_current(d.node, value, int(d.counter or 0))
                m = can.Message(arbitration_id=m.arbitration_id, data=data,
                                timestamp=m.timestamp, is_extended_id=False)
        out.append(m)
    return out


def with_offset(db: MotorDatabase, frames: list[can.Message], amps: float, after: float
                ) -> list[can.Message]:
    """The current frames from time stamp `after` on read `amps` more than the motor draws
    (a 10 A offset on 67.7 A: the windowed NIS settles near 2.5, twice its band)."""
    return changed_currents(db, frames, lambda v, t: v + amps if t >= after else v)


def diagnose(db: MotorDatabase, frames: list[can.Message], bias: str = "auto") -> tuple[
        list[DiagnosisEvent], list[can.Message]]:
    """Node 0's transitions and the MonitorDiagnosis frames sent, over `frames` replayed
    with the estimator's bias states `bias`."""
    events: list[DiagnosisEvent] = []
    sent: list[can.Message] = []
    cfg = MonitorConfig(nodes=(0,), estimator=FuzzyUKFConfig(bias=bias))
    feed_log(pipeline(db, cfg, events=events, sent=sent), frames)
    return events, sent
