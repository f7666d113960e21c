"""The model-mismatch flag stands beside the diagnosis (it never replaces it).

A plant whose current sensor is noisier than the model's R for a while (2 to 16 s: 1.4
times the model's sigma on top of it) and that loses half its actuator effectiveness at 10 s: the
windowed NIS leaves its band, the flag goes up, and the loss is still reported as a fault
within the usual delay, by both engines alike. A rig that sets
``withhold_alarms_on_mismatch`` holds that alarm while the flag is up and reports it when
the flag falls. The JSON events, the bus frames, the metrics file and the Rerun recording
carry the flag."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import can
import numpy as np
from prometheus_client.parser import text_string_to_metric_families

from monitor.bus.codec import Decoded, load_database
from monitor.diagnosis import HealthState, reported_state
from monitor.estimation.fuzzy_ukf import FuzzyUKFConfig
from monitor.pipeline import DiagnosisEvent, MonitorConfig, MonitorPipeline
from monitor.pipeline.events import HEALTH, MODEL_MISMATCH
from monitor.rig import load_rig
from monitor.sinks.base import FanOut
from monitor.sinks.jsonl import JsonLinesSink
from monitor.sinks.metrics import MetricsSink
from monitor.sinks.publisher import BusPublisher
from monitor.sinks.rerun import RerunSink
from sim_ecu.ecu import VirtualECU
from sim_ecu.scenario import scenario_from_dict
from tests.support.dbc import REPO_DBC
from tests.support.engines import compare_engines
from tests.support.log_readers import write_log
from tests.support.paths import ROOT
from tests.support.rrd import chunk_series, entity_chunks

T0 = 1_700_000_000.0
LOSS_AT = 10.0
NOISY = (2.0, 16.0)
DELAY_S = 0.4  # the accuracy bench's worst detection delay


@functools.cache
def _frames() -> tuple[can.Message, ...]:
    """Node 0: a 0.5 loss at `LOSS_AT`; its current frames within `NOISY` carry extra
    Gaussian noise of 0.7 A (the model's sigma is 0.5 A)."""
    db = load_database()
    sc = scenario_from_dict({"name": "noisy-loss", "duration": 25.0,
                             "fault": [{"kind": "step", "start": LOSS_AT, "gamma": 0.5}]})
    rng = np.random.default_rng(7)
    out = []
    for m in VirtualECU(None, db, 0, sc, seed=5).frames(start_time=T0):
        d = db.decode_can(m)
        if (isinstance(d, Decoded) and d.kind == "current"
                and NOISY[0] <= m.timestamp - T0 < NOISY[1]):
            data = db.encode_current(d.node, d.value + float(rng.normal(0.0, 0.7)),
                                     int(d.counter or 0))
            m = can.Message(arbitration_id=m.arbitration_id, data=data, timestamp=m.timestamp,
                            is_extended_id=False)
        out.append(m)
    return tuple(out)


def _cfg(withhold: bool) -> MonitorConfig:
    # The estimator's noise learning off (a rig's `adaptive_noise = false`): the extra noise
    # then stays a mismatch the flag must show (with it on, the noise is learned:
    # tests/estimation/test_adaptive_noise.py).
    return MonitorConfig(nodes=(0,), withhold_alarms_on_mismatch=withhold,
                         estimator=FuzzyUKFConfig(adaptive_noise=False))


def _both(tmp_path: Path, withhold: bool) -> list[DiagnosisEvent]:
    """The events of both engines (asserted identical, with samples, diagnoses and
    counters, by `tests.support.engines.compare_engines`)."""
    path = write_log(tmp_path / f"noisy-{withhold}.log", list(_frames()))
    db = load_database()
    res, pipe, rec = compare_engines(path, db, load_database(), _cfg(withhold))
    # the samples carry the flag as the events say it
    flags = [e for e in rec.transitions if e.kind == MODEL_MISMATCH]
    for s in rec.samples:
        before = [e.model_mismatch for e in flags if e.t <= s.t]
        assert s.model_mismatch == (before[-1] if before else False)
    assert res.nodes[0]["model_mismatch"] == pipe.nodes[0].model_mismatch
    events: list[DiagnosisEvent] = res.events
    return events


def _flag_times(events: list[DiagnosisEvent]) -> list[tuple[bool, float]]:
    return [(e.model_mismatch, e.t - T0) for e in events if e.kind == MODEL_MISMATCH]


def test_the_loss_is_reported_while_the_flag_is_up(tmp_path: Path) -> None:
    events = _both(tmp_path, withhold=False)
    flags = _flag_times(events)
    assert [f for f, _ in flags] == [True, False], flags
    up, down = flags[0][1], flags[1][1]
    assert NOISY[0] < up < LOSS_AT and down > NOISY[1], flags
    faults = [e for e in events if e.kind == HEALTH and e.state == "fault"]
    assert faults, events
    f = faults[0]
    assert LOSS_AT <= f.t - T0 <= LOSS_AT + DELAY_S, f
    assert f.model_mismatch and f.cause == "estimate" and f.previous == "fault_free"
    # no false alarm before the loss, noise or not
    assert [e.state for e in events if e.kind == HEALTH and e.t - T0 < LOSS_AT] == [
        "fault_free"]
    # a flag event keeps the state: it stands beside it
    assert all(e.state == e.previous for e in events if e.kind == MODEL_MISMATCH)


def test_withheld_alarm_is_reported_when_the_flag_falls(tmp_path: Path) -> None:
    events = _both(tmp_path, withhold=True)
    flags = _flag_times(events)
    assert [f for f, _ in flags] == [True, False], flags
    down = flags[1][1]
    health = [(e.previous, e.state, e.cause, e.t - T0) for e in events if e.kind == HEALTH]
    # nothing but the first diagnosis until the flag falls; then the held fault, at once,
    # after the flag's own event
    assert health[0][:2] == ("no_data", "fault_free"), health
    assert health[1][:3] == ("fault_free", "fault", "model"), health
    assert health[1][3] == down, (health, flags)
    i_flag = next(i for i, e in enumerate(events) if e.kind == MODEL_MISMATCH
                  and not e.model_mismatch)
    assert events[i_flag + 1].state == "fault" and not events[i_flag + 1].model_mismatch


def test_reported_state_rule() -> None:
    ff, fault, outage, nd = (int(s) for s in HealthState)
    # off, or the flag down: the classifier's state
    assert reported_state(fault, ff, True, False) == fault
    assert reported_state(outage, ff, False, True) == outage
    # on and flagged: a change to fault or outage is held, every other change goes through
    assert reported_state(fault, ff, True, True) == ff
    assert reported_state(outage, fault, True, True) == fault
    assert reported_state(ff, fault, True, True) == ff
    assert reported_state(nd, fault, True, True) == nd
    assert reported_state(fault, fault, True, True) == fault


def test_rig_file_sets_withholding(tmp_path: Path) -> None:
    text = (ROOT / "rigs" / "motor.toml").read_text(encoding="utf-8").replace(
        '"../dbc/motor.dbc"', f'"{REPO_DBC}"')
    assert load_rig(_rig(tmp_path, text)).diagnosis.withhold_alarms_on_mismatch is False
    text += "\n" if "[diagnosis]" in text else "\n[diagnosis]\n"
    on = text.replace("[diagnosis]\n", "[diagnosis]\nwithhold_alarms_on_mismatch = true\n", 1)
    assert load_rig(_rig(tmp_path, on)).diagnosis.withhold_alarms_on_mismatch is True


def _rig(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "rig.toml"
    path.write_text(text, encoding="utf-8")
    return path


def test_outlets_carry_the_flag(tmp_path: Path) -> None:
    """JSON lines, bus frames, the metrics file and the .rrd, read back."""
    db = load_database()
    jpath, prom, rrd = tmp_path / "ev.jsonl", tmp_path / "m.prom", tmp_path / "run.rrd"
    sent: list[can.Message] = []
    pipe = MonitorPipeline(db, _cfg(False))
    metrics = MetricsSink(prom, live=False)
    proms: list[dict[str, float]] = []
    with jpath.open("w", encoding="utf-8") as stream:
        sink = FanOut([JsonLinesSink(stream), BusPublisher(db, sent.append, pipe.counters),
                       metrics, RerunSink(rrd_path=rrd, nodes=(0,), recording_id="mm")])
        pipe.sink = sink
        for m in _frames():
            pipe.feed(m)
            if round((m.timestamp - T0) * 100) % 200 == 0:  # every 2 s
                metrics.flush()
                proms.append(_gauges(prom))
        sink.close()
    lines = [json.loads(x) for x in jpath.read_text(encoding="utf-8").splitlines()]
    kinds = [(x["kind"], x["model_mismatch"]) for x in lines if x["kind"] == "model_mismatch"]
    assert kinds == [("model_mismatch", True), ("model_mismatch", False)], lines
    assert {"t", "node", "state", "previous", "cause", "model_mismatch", "kind"} <= set(lines[0])
    # the bus: ModelMismatch 1 in frames while up, with the diagnosis beside it
    raw = [db.decode_can(m).raw for m in sent]  # type: ignore[union-attr]
    assert {int(r["HealthState"]) for r in raw if r["ModelMismatch"]} >= {0, 1}
    # the metrics file: the gauge was 1 in some writes and 0 in others, health beside it
    key = 'motor_monitor_node_model_mismatch{node="0"}'
    flags = [p[key] for p in proms if key in p]
    assert flags[0] == 0.0 and 1.0 in flags and flags[-1] == 0.0, proms
    # the recording: /node/0/model_mismatch steps 0 -> 1 -> 0 at the events' times
    t, v = chunk_series(entity_chunks(rrd)["/node/0/model_mismatch"])
    ups = [x["t"] for x in lines if x["kind"] == "model_mismatch"]
    assert set(v.tolist()) == {0.0, 1.0}
    changes = t[1:][np.diff(v) != 0]
    assert np.allclose(changes, ups, atol=1e-6), (changes, ups)


def _gauges(prom: Path) -> dict[str, float]:
    out = {}
    for fam in text_string_to_metric_families(prom.read_text(encoding="utf-8")):
        for s in fam.samples:
            labels = ",".join(f'{k}="{v}"' for k, v in sorted(s.labels.items()))
            out[f"{s.name}{{{labels}}}" if labels else s.name] = s.value
    return out
