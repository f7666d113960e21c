"""The monitor says when its model stops fitting: an unmodelled sensor offset (which no loss
of effectiveness can explain: gamma would have to be negative) turns the node to
model_mismatch, on the bus and in the events, instead of a fault alarm; a fitting model over
healthy and faulty runs never does."""

from __future__ import annotations

import can

from monitor.app.replay import feed_log
from monitor.bus.codec import Decoded, MotorDatabase, load_database
from monitor.diagnosis import HealthState
from monitor.pipeline import DiagnosisEvent, MonitorConfig
from sim_ecu.ecu import VirtualECU
from sim_ecu.scenario import load_scenario, scenario_from_dict
from tests.support.pipeline import pipeline

T0 = 1_700_000_000.0


def _offset(db: MotorDatabase, frames: list[can.Message], amps: float, after: float
            ) -> list[can.Message]:
    """The current frames after `after` seconds read `amps` more than the motor draws (a
    10 A offset on 67.7 A: the windowed NIS settles near 2.5, twice its band)."""
    out = []
    for m in frames:
        d = db.decode_can(m)
        if isinstance(d, Decoded) and d.kind == "current" and m.timestamp - T0 >= after:
            data = db.encode_current(d.node, d.value + amps, int(d.counter or 0))
            m = can.Message(arbitration_id=m.arbitration_id, data=data, timestamp=m.timestamp,
                            is_extended_id=False)
        out.append(m)
    return out


def _diagnose(db: MotorDatabase, frames: list[can.Message]) -> tuple[
        list[DiagnosisEvent], list[can.Message]]:
    events: list[DiagnosisEvent] = []
    sent: list[can.Message] = []
    feed_log(pipeline(db, MonitorConfig(nodes=(0,)), events=events, sent=sent), frames)
    return events, sent


def test_unmodelled_offset_is_a_model_mismatch_not_a_fault() -> None:
    db = load_database()
    healthy = scenario_from_dict({"name": "h", "duration": 20.0})
    frames = list(VirtualECU(None, db, 0, healthy, seed=4).frames(start_time=T0))
    events, sent = _diagnose(db, _offset(db, frames, 10.0, after=5.0))
    states = [(e.state, e.cause, round(e.t - T0, 1)) for e in events]
    assert "fault" not in [s for s, _, _ in states] and "outage" not in [s for s, _, _ in
                                                                         states], states
    mism = [t for s, c, t in states if s == "model_mismatch"]
    assert mism and 5.0 < mism[0] < 12.0, states
    assert [c for s, c, _ in states if s == "model_mismatch"] == ["model"]
    # ... and the bus hears it: MonitorDiagnosis frames with HealthState 4
    assert any(int(db.decode_can(m).raw["HealthState"]) == HealthState.MODEL_MISMATCH  # type: ignore[union-attr]
               for m in sent)


def test_a_fitting_model_is_never_flagged() -> None:
    db = load_database()
    for name, seed in (("fault-outage-recovery", 1), ("incipient", 2), ("intermittent", 3)):
        frames = list(VirtualECU(None, db, 0, load_scenario(name), seed=seed)
                      .frames(start_time=T0))
        events, _ = _diagnose(db, frames)
        assert "model_mismatch" not in [e.state for e in events], (name, events)
    long_run = scenario_from_dict({"name": "long", "duration": 300.0})
    events, _ = _diagnose(db, list(VirtualECU(None, db, 0, long_run, seed=9)
                                   .frames(start_time=T0)))
    assert [e.state for e in events] == ["fault_free"]
