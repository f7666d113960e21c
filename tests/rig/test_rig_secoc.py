"""SecOC on a rig's own DBC (tests/rigs/secure_drive.toml): the status frame E2E profile 2
over SecOC in cantools' secured-PDU layout, the command SecOC alone (float32 voltage, 4
freshness bits inside the authentic bytes), a sync message of the rig's own with its own
signal names, node in the ID bits. The virtual twin signs and announces; a keyed monitor
verifies every frame, a keyless one decodes them unverified; forged, replayed and
unsynchronised frames get their reasons; cantools' own SecOC helpers accept the status
frames; the freshness counters survive a restart (its rig-file mistakes are cases of
mistakes.toml)."""

from __future__ import annotations

import argparse
import json
import re
import subprocess
from pathlib import Path

import can
import pytest
from cantools.autosar.secoc import verify_authenticator

from monitor.app.options import monitor_config
from monitor.bus.codec import Decoded, Rejected
from monitor.bus.rigcodec import RigCodec
from monitor.bus.secoc import SecOC
from monitor.pipeline import DiagnosisEvent, MonitorPipeline
from monitor.pipeline.feed import feed_log
from monitor.rig import RigError, build_decoder, load_rig
from sim_ecu.rig_ecu import RigECU
from sim_ecu.scenario import load_scenario
from tests.support import BIN, motor_monitor
from tests.support.paths import TEST_RIGS
from tests.support.pipeline import pipeline

RIG = TEST_RIGS / "secure_drive.toml"
KEY = bytes.fromhex("000102030405060708090a0b0c0d0e0f")
OTHER_KEY = bytes.fromhex("ff0102030405060708090a0b0c0d0e0f")
NO_OVERRIDES = argparse.Namespace(nodes=None, rate=None, thresholds=None)


def _codec(key: bytes | None = KEY) -> RigCodec:
    codec = build_decoder(load_rig(RIG), secoc_key=key)
    assert isinstance(codec, RigCodec)
    return codec


def _twin_frames(seconds: float = 6.0, node: int = 1) -> list[can.Message]:
    rig = load_rig(RIG)
    ecu = RigECU(None, _codec(), rig, node, load_scenario("fault-outage-recovery"), seed=3)
    return list(ecu.frames(seconds, start_time=1000.0))


def _monitor(key: bytes | None, frames: list[can.Message]
             ) -> tuple[MonitorPipeline, list[DiagnosisEvent]]:
    events: list[DiagnosisEvent] = []
    pipe = pipeline(_codec(key), monitor_config(NO_OVERRIDES, load_rig(RIG)), events=events)
    feed_log(pipe, frames)
    return pipe, events


def _reason(r: Decoded | Rejected) -> str | None:
    return None if isinstance(r, Decoded) else str(r.reason)


def _decode(codec: RigCodec, fid: int, ext: bool, data: bytes) -> Decoded | Rejected:
    return codec.decode(fid, data, ext, False, False, 1.0)


def test_the_twin_signs_and_a_keyed_monitor_verifies_every_frame() -> None:
    frames = _twin_frames()
    syncs = [m for m in frames if m.arbitration_id == 0x3F1]
    assert len(syncs) == 2 * 6  # two streams, at start and each second
    assert {m.arbitration_id for m in frames[:2]} == {0x3F1}  # announced before the first
    keyed, events = _monitor(KEY, frames)
    c = keyed.counters
    assert c.rejected_total() == 0, dict(c)
    assert c["samples/secoc_sync"] == len(syncs)
    assert c["samples/estimated"] >= 598  # 600 samples (the first initialises the filter)
    assert [e.state for e in events][:2] == ["fault_free", "fault"]
    # a monitor without the key reads the same samples, its sync frames unverified
    keyless, plain = _monitor(None, frames)
    assert keyless.counters["ignored/secoc_sync"] == len(syncs)
    assert keyless.counters["samples/estimated"] == c["samples/estimated"]
    assert [(e.state, e.t) for e in plain] == [(e.state, e.t) for e in events]
    # a monitor with another key accepts nothing: no sync verifies, so every data frame of a
    # stream that was never synchronised is unsynced
    wrong, none = _monitor(OTHER_KEY, frames)
    assert wrong.counters["rejected/bad_mac"] == len(syncs)
    assert wrong.counters.get("samples/estimated", 0) == 0 and none == []
    assert wrong.counters["rejected/unsynced"] == sum(
        1 for m in frames if m.arbitration_id in (0x101, 0x201))


def test_forged_replayed_and_unsynchronised_frames_are_rejected() -> None:
    tx, rx = _codec(), _codec()
    fid, ext, first = tx.encode_sample("AxisCommand", 2, [12.5], [0.0])
    assert fid == 0x202
    assert _reason(_decode(rx, fid, ext, first)) == "unsynced"
    for name in ("AxisStatus", "AxisCommand"):
        sid, sext, sync = tx.encode_sync(name, 2)
        assert _reason(_decode(rx, sid, sext, sync)) is None
    fid, ext, frame = tx.encode_sample("AxisCommand", 2, [13.5], [0.0])
    got = _decode(rx, fid, ext, frame)
    assert isinstance(got, Decoded) and got.inputs == ((0, 13.5),)
    assert _reason(_decode(rx, fid, ext, frame)) == "stale_freshness"  # replayed
    forged = bytearray(tx.encode_sample("AxisCommand", 2, [14.5], [0.0])[2])
    forged[0] ^= 0x01  # byte 0 is authentic here: no E2E CRC on this message
    assert _reason(_decode(rx, fid, ext, bytes(forged))) == "bad_mac"
    # E2E over SecOC: a corrupted byte fails the CRC first; a frame forged with a valid CRC
    # fails the MAC
    fid, ext, status = tx.encode_sample("AxisStatus", 2, [0.0], [3.25], counter=1)
    corrupt = bytes([status[0], status[1], status[2] ^ 0x10]) + status[3:]
    assert _reason(_decode(rx, fid, ext, corrupt)) == "bad_crc"
    forger = _codec(None)  # encodes a valid CRC over an unsigned frame
    fid, ext, unsigned = forger.encode_sample("AxisStatus", 2, [0.0], [3.25], counter=2)
    assert _reason(_decode(rx, fid, ext, unsigned)) == "bad_mac"
    got = _decode(rx, fid, ext, status)
    assert isinstance(got, Decoded) and got.outputs == pytest.approx((3.25,))
    # a sync frame naming a stream the rig does not have, and a forged sync
    sid, sext, sync = tx.encode_sync("AxisStatus", 2)
    assert _reason(_decode(rx, sid, sext, bytes([0x05]) + sync[1:])) == "out_of_range"
    assert _reason(_decode(rx, sid, sext, sync[:5] + bytes(3))) == "bad_mac"
    # node 1's streams are its own: node 2's sync does not synchronise them
    fid, ext, other = tx.encode_sample("AxisCommand", 1, [1.0], [0.0])
    assert _reason(_decode(rx, fid, ext, other)) == "unsynced"


def test_cantools_secoc_helpers_accept_the_status_frames() -> None:
    """AxisStatus is cantools' secured-PDU layout (8 freshness bits, then the MAC): its
    verify_authenticator, given the same CMAC, accepts the twin's frames at their full
    freshness value and refuses them at any other with the same low bits."""
    tx = _codec()
    engine = tx.secoc
    assert isinstance(engine, SecOC)
    msg = tx.message("AxisStatus", 1)
    assert msg.autosar is not None and msg.autosar.secoc is not None  # set by the codec
    fn = engine.authenticator_fn()
    for k in range(1, 300):
        frame = tx.encode_sample("AxisStatus", 1, [0.0], [k * 0.01], counter=k % 16)[2]
        no_crc = b"\0" + frame[1:]
        assert verify_authenticator(no_crc, msg, fn, k) is True
        assert verify_authenticator(no_crc, msg, fn, k + 256) is False


def test_freshness_counters_survive_a_restart(tmp_path: Path) -> None:
    frames = _twin_frames(2.5)
    rx = _codec()
    first, rest = frames[:150], [m for m in frames[150:] if m.arbitration_id != 0x3F1]
    for m in first:
        assert _reason(rx.decode_can(m)) is None
    assert rx.secoc is not None
    state = tmp_path / "freshness.json"
    rx.secoc.save_state(state)
    saved = json.loads(state.read_text())
    assert {"rx/axisstatus/1", "rx/axiscommand/1"} <= set(saved["freshness"]), saved
    restarted = _codec()
    assert restarted.secoc is not None and restarted.secoc.load_state(state) == 2
    # the frames before the saved floor are replays ...
    replayed = [m for m in first if m.arbitration_id == 0x101][-3:]
    assert [_reason(restarted.decode_can(m)) for m in replayed] == ["stale_freshness"] * 3
    # ... and with no sync after the restart, the floor lets the frames after it in at once
    assert [_reason(restarted.decode_can(m)) for m in rest] == [None] * len(rest)


def test_replay_with_the_key_from_the_command_line(tmp_path: Path) -> None:
    """sim-ecu's frames in a candump log, re-diagnosed by `motor-monitor replay --rig --key`
    in its own process: every frame verified, the events those of the in-process monitor.
    The log holds node 1 only: `--nodes 1` (the rig's node 2 would have no sample, which
    is no success)."""
    frames = _twin_frames()
    log = tmp_path / "bus.log"
    with can.Logger(str(log)) as writer:
        for m in frames:
            writer.on_message_received(m)
    key = tmp_path / "key.hex"
    key.write_text(KEY.hex() + "\n")
    key.chmod(0o600)
    events = tmp_path / "events.jsonl"
    res = motor_monitor("replay", "--rig", str(RIG), "--key", str(key), "--nodes", "1",
                        "--events", str(events), str(log))
    assert res.returncode == 0, res.stderr
    lines = [json.loads(x) for x in events.read_text().splitlines()]
    _, expected = _monitor(KEY, frames)
    got = [(e["state"], round(e["t"], 6)) for e in lines if e.get("cause") == "estimate"]
    assert got == [(e.state, round(e.t, 6)) for e in expected if e.cause == "estimate"]
    # the wrong key: every data frame refused, so nothing decoded: a failure, in one line
    # with the counts by outcome and the cause
    key.write_text(OTHER_KEY.hex() + "\n")
    res = motor_monitor("replay", "--rig", str(RIG), "--key", str(key), "--nodes", "1",
                        "--events", str(events), str(log))
    assert res.returncode == 1, res.stderr
    [line] = [ln for ln in res.stderr.splitlines() if "error:" in ln]
    assert " 0 samples: " in line and "check --key" in line, res.stderr
    assert "bad_mac" in line or "unsynced" in line, res.stderr


def test_sim_ecu_signs_a_rigs_frames_and_keeps_its_counters(tmp_path: Path) -> None:
    key = tmp_path / "key.hex"
    key.write_text(KEY.hex() + "\n")
    key.chmod(0o600)
    state = tmp_path / "tx.json"
    argv = [str(BIN / "sim-ecu"), "--rig", str(RIG), "--node", "2", "--scenario", "healthy",
            "--interface", "virtual", "--channel", "secure", "--duration", "1.5", "--key",
            str(key), "--secoc-state", str(state)]
    res = subprocess.run(argv, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert re.search(r"sent AxisStatus=150 AxisCommand=\d+ SimTruth=150 sync=4\b",
                     res.stderr), res.stderr
    tx = json.loads(state.read_text())["freshness"]
    assert tx["tx/axisstatus/2"] >= 150 and "tx/axiscommand/2" in tx, tx
    # a rig without SecOC refuses the key in one line
    res = subprocess.run([*argv[:2], str(TEST_RIGS / "press.toml"), *argv[3:]], capture_output=True,
                         text=True, timeout=300)
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert "no message of the rig has SecOC" in res.stderr, res.stderr


def test_a_key_for_a_rig_without_secoc_is_one_line() -> None:
    with pytest.raises(RigError, match=r"press.toml: secoc: a SecOC key \(--key\) was given, "
                                       r"but no message of the rig has SecOC"):
        build_decoder(load_rig(TEST_RIGS / "press.toml"), secoc_key=KEY)
