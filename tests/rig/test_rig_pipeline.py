"""Rigs through the whole monitor offline (virtual twin -> frames -> pipeline): a plant with
two actuators and two outputs, the foreign layouts, lost samples without counters."""

from __future__ import annotations

import argparse

import can
import pytest

from monitor.app.options import monitor_config
from monitor.bus.rigcodec import RigCodec
from monitor.pipeline import DiagnosisEvent, MonitorPipeline
from monitor.pipeline.feed import feed_log
from monitor.rig import Rig, build_decoder, load_rig
from sim_ecu.rig_ecu import RigECU
from sim_ecu.scenario import load_scenario
from tests.support.paths import TEST_RIGS
from tests.support.pipeline import pipeline

NO_OVERRIDES = argparse.Namespace(nodes=None, rate=None, thresholds=None)


def _codec(rig: Rig) -> RigCodec:
    codec = build_decoder(rig)
    assert isinstance(codec, RigCodec)  # the test rigs are foreign layouts
    return codec


def _run(rig_name: str, scenario: str, node: int, *, drop: int = 0
         ) -> tuple[MonitorPipeline, list[DiagnosisEvent]]:
    rig = load_rig(TEST_RIGS / rig_name)
    codec = _codec(rig)
    ecu = RigECU(None, _codec(rig), rig, node, load_scenario(TEST_RIGS / scenario), seed=5)
    events: list[DiagnosisEvent] = []
    pipe = pipeline(codec, monitor_config(NO_OVERRIDES, rig), events=events)
    frames = ecu.frames(start_time=1000.0)
    # a lossy bus drops every `drop`-th frame
    feed_log(pipe, (m for i, m in enumerate(frames) if not (drop and i % drop == 7)))
    return pipe, events


def test_two_actuators_two_outputs_find_the_faulty_actuator() -> None:
    pipe, events = _run("twin.toml", "twin_fault.toml", 1)
    states = [(e.state, round(e.t - 1000.0, 2)) for e in events]
    assert [s for s, _ in states] == ["fault_free", "fault"], states
    assert 3.0 < states[1][1] <= 3.15, states
    gamma = pipe.nodes[1].estimator.out.gamma
    assert gamma[1] == pytest.approx(0.4, abs=0.05) and gamma[0] < 0.05
    assert pipe.counters.rejected_total() == 0


@pytest.mark.parametrize(("rig", "scenario", "node"), [
    ("press.toml", "press_excite.toml", 1),  # E2E: the alive counter says how many
    ("twin.toml", "twin_fault.toml", 1),  # no counter: the timestamps and the period say
])
def test_lost_samples_are_found_and_predicted_through(rig: str, scenario: str,
                                                      node: int) -> None:
    clean, _ = _run(rig, scenario, node)
    lossy, events = _run(rig, scenario, node, drop=50)
    lost = clean.counters["samples/estimated"] - lossy.counters["samples/estimated"]
    assert lost > 10
    assert lossy.counters["samples/predicted_through"] == lost
    assert lossy.counters.get("time/jitter", 0) == 0
    assert events[0].state == "fault_free"


def test_a_frame_of_the_wrong_length_or_crc_is_rejected() -> None:
    codec = _codec(load_rig(TEST_RIGS / "press.toml"))
    fid, ext, data = codec.encode_sample("Fb", 1, [220.0], [60.0], counter=3)
    bad_crc = bytes([data[0] ^ 0xFF]) + data[1:]
    for payload, reason in ((data[:4], "wrong_length"), (bad_crc, "bad_crc")):
        r = codec.decode_can(can.Message(arbitration_id=fid, is_extended_id=ext,
                                         data=payload, timestamp=1.0))
        assert getattr(r, "reason", None) == reason
    r = codec.decode_can(can.Message(arbitration_id=fid, is_extended_id=not ext, data=data))
    assert getattr(r, "reason", None) == "extended_id"
