"""CAN FD: every FD frame is counted (`frames/fd`, `frames/fd_esi`) and ends in exactly one
outcome; a rig whose DBC defines FD messages (tests/rigs/fd_servo.toml: 16- and 64-byte
frames, the signals beyond byte 8) is decoded and diagnosed; FD frames on our classic bus
are ``rejected/fd_frame``; logs with FD frames (candump ``ID##<flags><data>``, BLF) replay
to the same counters and events through the per-frame and the columnar engine."""

from __future__ import annotations

import argparse
import copy
import json
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from monitor.app.options import monitor_config
from monitor.bus.codec import Decoded, Rejected, RejectReason, load_database
from monitor.bus.logfile import read_log
from monitor.bus.rigcodec import RigCodec
from monitor.columnar.decode import window_of
from monitor.columnar.reader import read_chunks
from monitor.columnar.replay import replay_file
from monitor.pipeline import Counters, DiagnosisEvent, MonitorConfig, MonitorPipeline
from monitor.pipeline import counters as C
from monitor.pipeline.feed import feed_log
from monitor.rig import build_decoder, load_rig
from monitor.runtime import canbus
from monitor.runtime.canbus import CAN_MTU, interface_mtu, open_bus
from sim_ecu.ecu import VirtualECU
from sim_ecu.rig_ecu import RigECU
from sim_ecu.scenario import load_scenario
from tests.support import motor_monitor
from tests.support.log_readers import write_log
from tests.support.paths import TEST_RIGS
from tests.support.pipeline import pipeline
from tests.support.rrd import outcome_total

FD_RIG = TEST_RIGS / "fd_servo.toml"
NO_OVERRIDES = argparse.Namespace(nodes=None, rate=None, thresholds=None)


def _fd_codec() -> RigCodec:
    codec = build_decoder(load_rig(FD_RIG))
    assert isinstance(codec, RigCodec)
    return codec


def _fd_frames(node: int = 1, scenario: str = "fault-outage-recovery") -> list[can.Message]:
    rig = load_rig(FD_RIG)
    ecu = RigECU(None, _fd_codec(), rig, node, load_scenario(scenario), seed=5)
    return list(ecu.frames(start_time=1000.0))


def _fd_pipe(events: list[DiagnosisEvent] | None = None) -> MonitorPipeline:
    rig = load_rig(FD_RIG)
    return pipeline(_fd_codec(), monitor_config(NO_OVERRIDES, rig), events=events)


def _balanced(c: Counters | dict[str, int]) -> None:
    """frames/received is the sum of the outcomes; frames/fd is none of them."""
    assert c.get(C.FRAMES_RECEIVED, 0) == outcome_total(c), c


# ------------------------------------------------------------------ the rig's DBC


def test_the_fd_rig_dbc_defines_fd_messages_longer_than_classic() -> None:
    codec = _fd_codec()
    status, command = codec.message("FdAxisStatus", 1), codec.message("FdAxisCommand", 1)
    assert (status.is_fd, status.length) == (True, 64)
    assert (command.is_fd, command.length) == (True, 16)
    assert codec.frame_id("FdAxisStatus", 2) == 2 << 5 | 2


def test_fd_rig_frames_are_decoded_through_the_pipeline() -> None:
    frames = _fd_frames()
    assert all(m.is_fd for m in frames)
    assert {len(m.data) for m in frames} == {8, 16, 64}
    events: list[DiagnosisEvent] = []
    pipe = _fd_pipe(events)
    feed_log(pipe, frames)
    c = pipe.counters
    assert c[C.FRAMES_FD] == c[C.FRAMES_RECEIVED] == len(frames)
    assert c.rejected_total() == 0
    assert c[C.SAMPLES_ESTIMATED] >= 1590 and c[C.SAMPLES_INPUT] > 0 and c[C.SAMPLES_TRUTH] > 0
    _balanced(c)
    states = [(e.state, round(e.t - 1000.0, 2)) for e in events]
    assert [s for s, _ in states] == ["fault_free", "fault", "outage", "fault", "fault_free"], \
        states
    assert 4.0 <= states[1][1] <= 4.3 and 8.0 <= states[2][1] <= 8.3, states


@pytest.mark.parametrize("length", [12, 16, 20, 24, 32, 48])
def test_fd_frame_of_another_length_is_wrong_length(length: int) -> None:
    codec = _fd_codec()
    fid = codec.frame_id("FdAxisStatus", 1)
    res = codec.decode_can(can.Message(arbitration_id=fid, is_extended_id=False, is_fd=True,
                                       data=bytes(length)))
    assert isinstance(res, Rejected) and res.reason == RejectReason.WRONG_LENGTH, res
    assert f"{length} bytes, expected 64" in res.detail


def test_the_frame_format_must_be_the_dbcs() -> None:
    codec = _fd_codec()
    fid, ext, data = codec.encode_sample("FdAxisStatus", 1, [12.0], [3.5])
    ok = codec.decode_can(can.Message(arbitration_id=fid, is_extended_id=ext, is_fd=True,
                                      bitrate_switch=True, data=data))
    assert isinstance(ok, Decoded) and ok.outputs == pytest.approx((3.5,))
    # the 8-byte truth message as a classic frame: same length, wrong format
    fid, ext, data = codec.encode_sample("FdSimTruth", 1, [0.0], [0.0], truth=0.25)
    assert len(data) == 8
    classic = codec.decode_can(can.Message(arbitration_id=fid, is_extended_id=ext, data=data))
    assert isinstance(classic, Rejected) and classic.reason == RejectReason.FD_FRAME
    assert "classic CAN frame" in classic.detail and "CAN FD message" in classic.detail
    fd = codec.decode_can(can.Message(arbitration_id=fid, is_extended_id=ext, is_fd=True,
                                      data=data))
    assert isinstance(fd, Decoded) and fd.truth == pytest.approx(0.25)


def test_fd_frames_on_our_classic_bus_are_counted_and_rejected() -> None:
    db = load_database()
    pipe = MonitorPipeline(db, MonitorConfig(nodes=(0,)))
    cur = db.frame_id("current", 0)
    good = db.encode_current(0, 1.0, 0)
    msgs = [
        # an 8-byte FD frame with a valid payload: still not the DBC's classic frame
        can.Message(timestamp=1.0, arbitration_id=cur, is_extended_id=False, is_fd=True,
                    data=good),
        can.Message(timestamp=1.1, arbitration_id=cur, is_extended_id=False, is_fd=True,
                    bitrate_switch=True, data=good + bytes(56)),  # 64 bytes
        can.Message(timestamp=1.2, arbitration_id=0x05F, is_extended_id=False, is_fd=True,
                    error_state_indicator=True, data=bytes(range(12))),  # no such ID
        can.Message(timestamp=1.3, arbitration_id=cur, is_extended_id=True, is_fd=True,
                    data=bytes(16)),  # 29-bit: our bus has none
    ]
    for m in msgs:
        pipe.feed(m)
    c = pipe.counters
    assert c[C.FRAMES_FD] == 4 and c[C.FRAMES_FD_ESI] == 1
    assert c[C.rejected("fd_frame")] == 2
    assert c[C.rejected("unknown_id")] == 1 and c[C.rejected("extended_id")] == 1
    _balanced(c)
    res = db.decode_can(msgs[1])
    assert isinstance(res, Rejected) and "CAN FD frame of 64 bytes" in res.detail


# ------------------------------------------------------------------ logs, both engines


def _compare(path: Path, make_db: Any, cfg: MonitorConfig) -> tuple[Any, MonitorPipeline,
                                                                      list[DiagnosisEvent]]:
    events: list[DiagnosisEvent] = []
    pipe = pipeline(make_db(), cfg, events=events)
    n = feed_log(pipe, read_log(path))
    res = replay_file(path, make_db(), cfg, chunk_frames=997)
    assert res.frames == n
    assert res.counters == dict(pipe.counters)
    assert res.events == events
    _balanced(res.counters)
    return res, pipe, events


@pytest.mark.parametrize("suffix", [".log", ".blf"])
def test_fd_rig_log_replays_in_both_engines(tmp_path: Path, suffix: str,
                                            caplog: pytest.LogCaptureFixture) -> None:
    frames = _fd_frames()
    path = write_log(tmp_path / f"fd{suffix}", frames)
    if suffix == ".log":
        text = path.read_text()
        assert "022##" in text and "021##" in text  # candump's FD format
    cfg = monitor_config(NO_OVERRIDES, load_rig(FD_RIG))
    with caplog.at_level("WARNING"):
        res, _, events = _compare(path, _fd_codec, cfg)
    # 16- and 64-byte messages, signals beyond byte 8: decoded in columns all the same
    assert res.columnar and res.fallback is None
    assert "frame by frame" not in caplog.text
    assert res.counters[C.FRAMES_FD] == len(frames) and res.counters[C.SAMPLES_ESTIMATED] > 1500
    assert [e.state for e in events][:3] == ["fault_free", "fault", "outage"]


def _classic_with_fd(n: int = 4000) -> list[can.Message]:
    """Our bus (node 0) with CAN FD frames among its frames: on its IDs (8 and 64 bytes),
    on an unknown ID, with BRS and ESI."""
    db = load_database()
    ecu = VirtualECU(None, db, 0, load_scenario("fault-outage-recovery"), seed=3)
    frames = list(ecu.frames(start_time=1000.0))[:n]
    cur, volt = db.frame_id("current", 0), db.frame_id("voltage", 0)
    extra = []
    for k in range(40):
        t = 1000.0005 + 0.0371 * k
        fid = (cur, volt, 0x05F, cur)[k % 4]
        data = bytes((k + i) & 0xFF for i in range((8, 64, 12, 48)[k % 4]))
        extra.append(can.Message(timestamp=t, arbitration_id=fid, is_extended_id=False,
                                 is_fd=True, bitrate_switch=k % 2 == 0,
                                 error_state_indicator=k % 5 == 0, data=data))
    return sorted(frames + extra, key=lambda m: m.timestamp)


@pytest.mark.parametrize("suffix", [".log", ".blf"])
def test_fd_frames_in_a_log_of_our_bus_get_their_outcome_in_both_engines(
        tmp_path: Path, suffix: str) -> None:
    path = write_log(tmp_path / f"mixed{suffix}", _classic_with_fd())
    res, _, events = _compare(path, load_database, MonitorConfig(nodes=(0,)))
    assert res.columnar  # our bus stays columnar: FD frames get their verdict in columns
    c = res.counters
    assert c[C.FRAMES_FD] == 40 and c[C.FRAMES_FD_ESI] == 8
    assert c[C.rejected("fd_frame")] == 30 and c[C.rejected("unknown_id")] == 10
    assert events  # the diagnosis went on around them
    # the chunks keep every FD payload whole
    want = [m for m in can.LogReader(str(path)) if m.is_fd]
    got = [ch.message(i) for ch in read_chunks(path, 512) for i in range(len(ch))
           if ch.is_fd[i]]
    assert [bytes(m.data) for m in got] == [bytes(m.data) for m in want]
    assert [(m.bitrate_switch, m.error_state_indicator) for m in got] == \
        [(m.bitrate_switch, m.error_state_indicator) for m in want]
    assert max(len(m.data) for m in got) == 64


def test_candump_fd_lines_parse_as_python_can_reads_them(tmp_path: Path) -> None:
    """The compiled scanner against python-can's reader on hand-written candump FD lines."""
    lines = [
        "(1000.000100) vcan0 123##0" + "11" * 12,
        "(1000.000200) vcan0 123##1" + "22" * 64,  # BRS
        "(1000.000300) vcan0 123##2" + "33" * 16,  # ESI
        "(1000.000400) vcan0 1ABCDEF0##3" + "44" * 20,  # 29-bit, BRS + ESI
        "(1000.000500) vcan0 123##0",  # an empty FD frame
        "(1000.000600) vcan0 124#0102030405060708",
    ]
    path = tmp_path / "fd.log"
    path.write_text("\n".join(lines) + "\n")
    (chunk,) = list(read_chunks(path))
    assert chunk.data.shape[1] == 64
    want = list(can.LogReader(str(path)))
    got = [chunk.message(i) for i in range(len(chunk))]
    for g, w in zip(got, want, strict=True):
        assert (g.timestamp, g.arbitration_id, g.is_extended_id, g.is_fd, g.bitrate_switch,
                g.error_state_indicator, bytes(g.data)) == \
            (w.timestamp, w.arbitration_id, w.is_extended_id, w.is_fd, w.bitrate_switch,
             w.error_state_indicator, bytes(w.data))
    assert np.array_equal(chunk.length, [12, 64, 16, 20, 0, 8])


@pytest.mark.parametrize("engine", ["columnar", "per-frame"])
def test_replay_command_takes_an_fd_log(tmp_path: Path, engine: str) -> None:
    path = write_log(tmp_path / "fd.log", _fd_frames(scenario="fault-outage-recovery"))
    # node 1's frames: --nodes 1 (the rig's node 2 would have no sample, which is no success)
    rep = motor_monitor("replay", str(path), "--rig", str(FD_RIG), "--nodes", "1",
                        "--engine", engine)
    assert rep.returncode == 0, rep.stderr
    events = [json.loads(x) for x in rep.stdout.splitlines()]
    assert [e["state"] for e in events if e["cause"] == "estimate"][:3] == \
        ["fault_free", "fault", "outage"]
    assert ", 0 rejected" in rep.stderr, rep.stderr
    assert "frame by frame" not in rep.stderr, rep.stderr


# ------------------------------------------------------------------ the socket


def test_open_bus_asks_socketcan_for_fd(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: dict[str, Any] = {}

    class FakeBus:
        channel_info = "fake"

    def fake_bus(**kwargs: Any) -> FakeBus:
        seen.update(kwargs)
        return FakeBus()

    monkeypatch.setattr(can, "Bus", fake_bus)
    open_bus("socketcan", "vcan-none")
    assert seen["fd"] is True
    seen.clear()
    open_bus("socketcan", "vcan-none", fd=False)
    assert "fd" not in seen
    seen.clear()
    open_bus("virtual", "x")
    assert "fd" not in seen  # other interfaces as their configuration says


def test_interface_mtu_reads_sysfs() -> None:
    assert interface_mtu("no-such-interface-here") is None
    lo = interface_mtu("lo")
    assert lo is None or lo > CAN_MTU


def test_a_classic_interface_is_named_in_the_log(monkeypatch: pytest.MonkeyPatch,
                                                 caplog: pytest.LogCaptureFixture) -> None:
    class FakeBus:
        channel_info = "fake"

    monkeypatch.setattr(can, "Bus", lambda **kwargs: FakeBus())
    monkeypatch.setattr(canbus, "interface_mtu", lambda channel: CAN_MTU)
    with caplog.at_level("INFO", logger="monitor.runtime.canbus"):
        open_bus("socketcan", "can7")
    assert "can7: classic CAN interface (MTU 16): no CAN FD frame can arrive" in caplog.text
    caplog.clear()
    monkeypatch.setattr(canbus, "interface_mtu", lambda channel: 72)
    with caplog.at_level("INFO", logger="monitor.runtime.canbus"):
        open_bus("socketcan", "can7")
    assert "can7: CAN FD frames are received (socket FD-enabled, interface MTU 72)" in caplog.text


def test_a_signal_no_8_byte_window_holds_sends_the_file_frame_by_frame() -> None:
    codec = _fd_codec()
    status = codec.message("FdAxisStatus", 1)
    signal = status.get_signal_by_name("CurrentFb")
    assert window_of(signal, 64) == 12 and window_of(signal, 8) == 0
    wide = copy.copy(signal)
    wide.start = 60  # bits 60..91: bytes 7..11, still one window
    assert window_of(wide, 64) == 7
    wide.length, wide.start = 64, 4  # bytes 0..8: no 8-byte window
    assert window_of(wide, 64) is None
    big = copy.copy(signal)
    big.byte_order, big.start = "big_endian", 8 * 60 + 7  # MSB first in byte 60: bytes 60..63
    assert window_of(big, 64) == 56
    big.start = 8 * 62 + 7  # would run past byte 63
    assert window_of(big, 64) is None
