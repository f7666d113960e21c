"""The monitor says when its model stops fitting: an unmodelled sensor offset (which no loss
of effectiveness can explain: gamma would have to be negative) raises the node's
model-mismatch flag, on the bus and in the events, beside its diagnosis (which stays
fault_free: no fault alarm); a fitting model over healthy and faulty runs never does."""

from __future__ import annotations

from monitor.bus.codec import load_database
from monitor.diagnosis import HealthState
from monitor.pipeline.events import HEALTH, MODEL_MISMATCH
from sim_ecu.ecu import VirtualECU
from sim_ecu.scenario import load_scenario, scenario_from_dict
from tests.support.pipeline import diagnose, with_offset

T0 = 1_700_000_000.0


def test_unmodelled_offset_raises_the_flag_not_a_fault() -> None:
    db = load_database()
    healthy = scenario_from_dict({"name": "h", "duration": 20.0})
    frames = list(VirtualECU(None, db, 0, healthy, seed=4).frames(start_time=T0))
    # without the estimator's bias states, which would learn the offset (tests/estimation/
    # test_bias.py): the flag is what tells of a model that does not fit
    events, sent = diagnose(db, with_offset(db, frames, 10.0, after=T0 + 5.0), bias="none")
    health = [e.state for e in events if e.kind == HEALTH]
    assert health == ["fault_free"], events  # the diagnosis stays: no fault alarm
    flags = [(e.model_mismatch, e.cause, e.state, round(e.t - T0, 1)) for e in events
             if e.kind == MODEL_MISMATCH]
    # it rises beside fault_free; the adaptive noise (the estimator's steps 5b and 5c) may
    # later learn what the state's pull towards the offset leaves in the innovations as
    # noise and let it fall, seconds on: the bias states, the default, take the offset
    assert flags and flags[0][:3] == (True, "nis", "fault_free"), flags
    assert 5.0 < flags[0][3] < 12.0, flags
    assert len(flags) == 1 or flags[1][3] - flags[0][3] > 5.0, flags
    # ... and the bus hears it: ModelMismatch 1 beside HealthState fault_free (0)
    raw = [db.decode_can(m).raw for m in sent]  # type: ignore[union-attr]
    pairs = {(int(r["HealthState"]), int(r["ModelMismatch"])) for r in raw}
    assert (HealthState.FAULT_FREE, 1) in pairs, pairs  # (no_data, 0) before the first sample
    assert pairs <= {(HealthState.FAULT_FREE, 0), (HealthState.FAULT_FREE, 1),
                     (HealthState.NO_DATA, 0)}, pairs


def test_a_fitting_model_is_never_flagged() -> None:
    db = load_database()
    for name, seed in (("fault-outage-recovery", 1), ("incipient", 2), ("intermittent", 3)):
        frames = list(VirtualECU(None, db, 0, load_scenario(name), seed=seed)
                      .frames(start_time=T0))
        events, _ = diagnose(db, frames)
        assert not any(e.model_mismatch or e.kind == MODEL_MISMATCH for e in events), (
            name, events)
    long_run = scenario_from_dict({"name": "long", "duration": 300.0})
    events, _ = diagnose(db, list(VirtualECU(None, db, 0, long_run, seed=9)
                                   .frames(start_time=T0)))
    assert [e.state for e in events] == ["fault_free"]
