"""The monitor's data path on frames: every frame gets one counted outcome, diagnosis out."""

from __future__ import annotations

import itertools

import can
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from monitor.bus.codec import Decoded, MotorDatabase, load_database
from monitor.diagnosis import HealthState
from monitor.pipeline import DiagnosisEvent, MonitorConfig, MonitorPipeline
from sim_ecu.ecu import VirtualECU
from sim_ecu.scenario import load_scenario
from tests.support.pipeline import decode_all, feed_all, pipeline, stalled, without_currents

T0 = 1_700_000_000.0


@pytest.fixture(scope="module")
def db() -> MotorDatabase:
    return load_database()


@pytest.fixture(scope="module")
def frames(db: MotorDatabase) -> list[can.Message]:
    ecu = VirtualECU(None, db, 0, load_scenario("fault-outage-recovery"), seed=3)
    return list(ecu.frames(start_time=T0))


def _pipe(db: MotorDatabase, **kw: object) -> tuple[MonitorPipeline, list[DiagnosisEvent],
                                                     list[can.Message]]:
    events: list[DiagnosisEvent] = []
    sent: list[can.Message] = []
    cfg = MonitorConfig(**kw)  # type: ignore[arg-type]
    return pipeline(db, cfg, events=events, sent=sent), events, sent


def _diagnoses(db: MotorDatabase, sent: list[can.Message]) -> list[Decoded]:
    """The published frames decoded; each must be a valid MonitorDiagnosis frame."""
    decoded = decode_all(db, sent)
    assert all(d.kind == "diagnosis" for d in decoded), decoded
    return decoded


def test_fault_outage_recovery_is_diagnosed_and_published(db: MotorDatabase,
                                                          frames: list[can.Message]) -> None:
    pipe, events, sent = _pipe(db)
    feed_all(pipe, frames)
    states = [(round(e.t - T0, 2), e.state) for e in events]
    assert [s for _, s in states] == ["fault_free", "fault", "outage", "fault", "fault_free"] or \
        [s for _, s in states] == ["fault_free", "fault", "outage", "fault_free"]
    onset = next(t for t, s in states if s == "fault")
    assert 4.0 < onset <= 4.15  # the detection target: within 0.15 s at 100 Hz
    outage = next(t for t, s in states if s == "outage")
    assert 8.0 < outage <= 8.2
    # published frames decode as MonitorDiagnosis with the states in order
    decoded = _diagnoses(db, sent)
    hs = [int(d.raw["HealthState"]) for d in decoded]
    assert HealthState.OUTAGE in hs and hs[-1] == HealthState.FAULT_FREE
    # steady publication at ~10 Hz over 16 s plus the transitions
    assert 150 <= len(sent) <= 175
    counters = [d.counter for d in decoded if d.counter is not None]
    assert len(counters) == len(decoded)  # every diagnosis frame carries its alive counter
    assert all((b - a) % 16 == 1 for a, b in itertools.pairwise(counters))
    c = pipe.counters
    assert c["samples/estimated"] == 1599 and not any(k.startswith("rejected/") for k in c)


def _msg(arb: int, data: bytes, t: float) -> can.Message:
    return can.Message(arbitration_id=arb, data=data, timestamp=t, is_extended_id=False)


def test_bad_frames_are_counted_and_never_reach_the_estimator(
        db: MotorDatabase, frames: list[can.Message]) -> None:
    pipe, _, _ = _pipe(db)
    good = frames[:400]
    feed_all(pipe, good)
    est_before = pipe.counters["samples/estimated"]
    gamma_before = pipe.nodes[0].estimator.out.gamma.copy()
    cur = next(m for m in good if m.arbitration_id == 0x110)
    t = good[-1].timestamp
    bad = [
        _msg(0x555, b"\x00" * 8, t),  # unknown id
        _msg(0x110, bytes(cur.data[:5]), t),  # wrong length
        _msg(0x110, bytes([cur.data[0] ^ 0xFF]) + bytes(cur.data[1:]), t),  # bad CRC
        can.Message(arbitration_id=0x110, data=bytes(cur.data), is_extended_id=True,
                    timestamp=t),  # extended id
        can.Message(arbitration_id=0x110, is_remote_frame=True, is_extended_id=False,
                    timestamp=t),  # remote frame
    ]
    feed_all(pipe, bad)
    c = pipe.counters
    for reason in ("unknown_id", "wrong_length", "bad_crc", "extended_id", "remote_frame"):
        assert c[f"rejected/{reason}"] == 1, reason
    assert c["samples/estimated"] == est_before
    assert np.array_equal(pipe.nodes[0].estimator.out.gamma, gamma_before)


def test_replayed_frame_is_dropped_and_lost_frames_are_predicted_through(
        db: MotorDatabase, frames: list[can.Message]) -> None:
    pipe, _, _ = _pipe(db)
    currents = [m for m in frames if m.arbitration_id == 0x110]
    volt = next(m for m in frames if m.arbitration_id == 0x120)
    pipe.feed(volt)
    feed_all(pipe, currents[:50])
    pipe.feed(currents[49])  # the same frame again: a replay
    assert pipe.counters["e2e/repeated"] == 1
    assert pipe.counters["samples/estimated"] == 50
    feed_all(pipe, currents[53:60])  # three lost
    assert pipe.counters["e2e/lost_frames"] == 3
    assert pipe.counters["samples/predicted_through"] == 3
    assert pipe.counters["samples/estimated"] == 57


def test_time_going_backwards_and_missing_voltage(db: MotorDatabase,
                                                  frames: list[can.Message]) -> None:
    pipe, _, _ = _pipe(db)
    currents = [m for m in frames if m.arbitration_id == 0x110]
    pipe.feed(currents[0])
    assert pipe.counters["samples/no_input"] == 1
    pipe.feed(next(m for m in frames if m.arbitration_id == 0x120))
    pipe.feed(currents[1])
    late = currents[2]
    pipe.feed(_msg(late.arbitration_id, bytes(late.data), currents[0].timestamp))
    assert pipe.counters["time/non_monotonic"] == 1


def test_silent_ecu_turns_no_data_and_says_so_on_the_bus(db: MotorDatabase,
                                                         frames: list[can.Message]) -> None:
    pipe, events, sent = _pipe(db, nodes=(0, 5))
    feed_all(pipe, frames[:300])
    t = frames[299].timestamp
    pipe.tick(t + 0.1)
    assert pipe.nodes[0].state == HealthState.FAULT_FREE
    pipe.tick(t + 0.6)
    assert pipe.nodes[0].state == HealthState.NO_DATA
    assert events[-1].state == "no_data" and events[-1].cause == "silence"
    n = len(sent)
    pipe.tick(t + 0.8)
    new = _diagnoses(db, sent[n:])
    assert {d.node for d in new} == {0, 5}
    assert all(d.raw["HealthState"] == 3 for d in new)
    # the ECU comes back: classification resumes
    feed_all(pipe, frames[300:600])
    assert pipe.nodes[0].state == HealthState.FAULT_FREE


def test_other_nodes_and_foreign_diagnosis_are_ignored(db: MotorDatabase) -> None:
    pipe, _, _ = _pipe(db, nodes=(1,))
    pipe.feed(_msg(0x112, db.encode_current(2, 10.0, 0), T0))
    pipe.feed(_msg(0x181, db.encode_diagnosis(1, 0, 0.0, 0.0, 2, 0), T0))
    assert pipe.counters["ignored/node"] == 1
    assert pipe.counters["ignored/diagnosis"] == 1


@settings(max_examples=300, deadline=None)
@given(
    arb=st.one_of(st.integers(0, 0x7FF), st.sampled_from([0x110, 0x120, 0x7E0, 0x180, 0x113])),
    data=st.binary(min_size=0, max_size=8),
    dt=st.floats(-1.0, 1.0, allow_nan=False),
    flags=st.sampled_from(["", "ext", "rtr", "err"]),
)
def test_random_frames_never_crash_and_are_counted(arb: int, data: bytes, dt: float,
                                                   flags: str) -> None:
    db = load_database()
    pipe = _PIPE.setdefault("p", MonitorPipeline(db, MonitorConfig()))
    before = pipe.counters.get("frames/received", 0)
    msg = can.Message(arbitration_id=arb if flags != "ext" else arb | 0x10000000,
                      data=data if flags != "rtr" else b"", is_extended_id=flags == "ext",
                      is_remote_frame=flags == "rtr", is_error_frame=flags == "err",
                      timestamp=T0 + dt, dlc=len(data))
    pipe.feed(msg)
    pipe.tick(T0 + dt + 1.0)
    assert pipe.counters["frames/received"] == before + 1
    for nm in pipe.nodes.values():
        assert np.all(np.isfinite(nm.estimator.out.gamma))


_PIPE: dict[str, MonitorPipeline] = {}


def test_error_frames_are_decoded_and_counted(db: MotorDatabase) -> None:
    pipe, _, _ = _pipe(db)
    t = T0
    # controller: rx overflow + rx error passive; bus-off; restarted (linux/can/error.h)
    pipe.feed(can.Message(is_error_frame=True, arbitration_id=0x004,
                          data=bytes([0, 0x11, 0, 0, 0, 0, 0, 0]), timestamp=t))
    pipe.feed(can.Message(is_error_frame=True, arbitration_id=0x040, data=bytes(8), timestamp=t))
    pipe.feed(can.Message(is_error_frame=True, arbitration_id=0x100, data=bytes(8), timestamp=t))
    c = pipe.counters
    assert c["bus/error_frames"] == 3
    assert c["bus/errors/controller/rx_overflow"] == 1
    assert c["bus/errors/controller/rx_error_passive"] == 1
    assert c["bus/errors/bus_off"] == 1
    assert c["bus/errors/restarted"] == 1
    assert not any(k.startswith("rejected/") for k in c)


def test_late_frames_are_not_mistaken_for_lost_ones(db: MotorDatabase,
                                                    frames: list[can.Message]) -> None:
    # Every other current frame arrives 6 ms late (jitter) and a few 25 ms late: the alive
    # counters show nothing was lost, so nothing is predicted through and no state flickers.
    # Frames of one ECU keep their order (one sender, FIFO queues): a late frame holds back
    # the ones behind it.
    pipe, events, _ = _pipe(db)
    jittered = []
    prev = 0.0
    for i, m in enumerate(frames):
        late = 0.025 if i % 97 == 0 else (0.006 if i % 2 else 0.0)
        prev = max(m.timestamp + late, prev + 1e-6)
        jittered.append(can.Message(arbitration_id=m.arbitration_id, data=m.data,
                                    is_extended_id=False, timestamp=prev))
    feed_all(pipe, jittered)
    assert pipe.counters.get("samples/predicted_through", 0) == 0
    assert [e.state for e in events][:4] == ["fault_free", "fault", "outage", "fault"] or \
        [e.state for e in events][:4] == ["fault_free", "fault", "outage", "fault_free"]


@pytest.mark.parametrize("periods", [9, 15])
def test_a_held_up_senders_backlog_is_late_not_lost(db: MotorDatabase,
                                                    frames: list[can.Message],
                                                    periods: int) -> None:
    # The first frame of the backlog is `periods` late, more than half a counter wrap:
    # rounded to the nearest wrap it would be 16 lost; as the whole wraps that fit, late.
    pipe, _, _ = _pipe(db)
    t0 = T0 + 3.0005
    feed_all(pipe, stalled(frames, t0, t0 + periods / 100.0))
    assert pipe.counters.get("samples/predicted_through", 0) == 0
    assert pipe.counters.get("e2e/lost_frames", 0) == 0


@pytest.mark.parametrize("n", [15, 31])
def test_a_counter_wrap_of_lost_frames_is_not_a_repeat(db: MotorDatabase,
                                                       frames: list[can.Message], n: int) -> None:
    # 15 or 31 lost frames give the next one its predecessor's counter: due 16 or 32 periods
    # on, within the silence timeout, it is n lost samples, not a replay.
    pipe, _, _ = _pipe(db)
    feed_all(pipe, without_currents(frames, 300, n))
    c = pipe.counters
    assert c.get("e2e/repeated", 0) == 0
    assert c["samples/predicted_through"] == n
    assert (c.get("e2e/counter_jumps"), c.get("e2e/lost_frames")) == (1, 15)


def test_same_counter_soon_or_after_silence_is_a_repeat(db: MotorDatabase,
                                                        frames: list[can.Message]) -> None:
    # A duplicate a millisecond later, and the last frame replayed after the node went silent.
    last = [m for m in frames if m.arbitration_id == 0x110][200]
    head = frames[:frames.index(last) + 1]

    def again(m: can.Message, dt: float) -> can.Message:
        return can.Message(arbitration_id=m.arbitration_id, data=m.data,
                           is_extended_id=False, timestamp=m.timestamp + dt)

    pipe, _, _ = _pipe(db)
    feed_all(pipe, [*head, again(last, 0.001), again(last, 0.6)])
    assert pipe.counters["e2e/repeated"] == 2
    assert pipe.counters.get("e2e/counter_jumps", 0) == 0


def test_long_gap_counts_whole_counter_wraps(db: MotorDatabase,
                                             frames: list[can.Message]) -> None:
    pipe, _, _ = _pipe(db)
    currents = [m for m in frames if m.arbitration_id == 0x110]
    pipe.feed(next(m for m in frames if m.arbitration_id == 0x120))
    feed_all(pipe, currents[:10])
    feed_all(pipe, currents[10 + 37:60])  # 37 lost: 2 wraps of the 4-bit counter + 5
    assert pipe.counters["samples/predicted_through"] == 37
