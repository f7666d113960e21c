"""The columnar replay (`monitor.columnar`) against the per-frame path and cantools.

* Signals decoded per column equal cantools' ``Message.decode`` on random payloads, for
  every message of our DBC and of the rigs in tests/rigs; the E2E CRC table equals
  cantools' profile-2 CRC.
* The chunk reader gives python-can's frames, for .log, .asc and .blf.
* `replay_file` gives the per-frame path's (`feed_log(MonitorPipeline, read_log)`)
  transitions, due diagnoses, bus events, samples, voltages and counters, on logs made by
  sim_ecu (healthy, fault-outage-recovery, with every kind of bad frame of
  tests/support/bad_frames injected, lost and repeated frames) and by the rigs' twins,
  with small chunks so that chunk boundaries fall everywhere; SecOC falls back to the
  per-frame path, with the same results.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from cantools.autosar.end_to_end import compute_profile2_crc
from hypothesis import given, settings
from hypothesis import strategies as st

from monitor.app.options import monitor_config
from monitor.bus.codec import load_database
from monitor.bus.logfile import read_log
from monitor.bus.rigcodec import RigCodec
from monitor.columnar.e2e import crc_table, profile2_ok
from monitor.columnar.reader import read_chunks
from monitor.columnar.replay import replay_file
from monitor.columnar.signals import SignalExtractor, payload_integers
from monitor.pipeline import MonitorConfig, MonitorPipeline
from monitor.pipeline.feed import TICK_S, feed_log
from monitor.rig import build_decoder, load_rig
from sim_ecu.rig_ecu import RigECU
from sim_ecu.scenario import load_scenario
from tests.support.engines import compare_engines, sim_frames
from tests.support.log_readers import write_log
from tests.support.paths import TEST_RIGS
from tests.support.pipeline import Recorder

NO_OVERRIDES = argparse.Namespace(nodes=None, rate=None, thresholds=None)


# ------------------------------------------------------------------ signals and CRC


def _all_messages() -> list[Any]:
    msgs = list(load_database()._db.messages)
    for rig in ("servo.toml", "press.toml", "twin.toml"):
        msgs += list(build_decoder(load_rig(TEST_RIGS / rig))._db.messages)
    return msgs


MESSAGES = _all_messages()


@settings(max_examples=60, deadline=None)
@given(st.integers(0, len(MESSAGES) - 1),
       st.lists(st.binary(min_size=8, max_size=8), min_size=1, max_size=40))
def test_signals_equal_cantools_decode(which: int, payloads: list[bytes]) -> None:
    msg = MESSAGES[which]
    data = np.frombuffer(b"".join(payloads), np.uint8).reshape(-1, 8).copy()
    data[:, msg.length:] = 0
    le, be = payload_integers(data)
    for sig in msg.signals:
        got = SignalExtractor(sig, msg.length).extract(le, be)
        for row, p in enumerate(data):
            want = float(msg.decode(bytes(p[:msg.length]), decode_choices=False,
                                    scaling=True)[sig.name])
            assert got[row] == want or (got[row] != got[row] and want != want), \
                (msg.name, sig.name, bytes(p).hex())


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(st.binary(min_size=8, max_size=8), st.booleans()),
                min_size=1, max_size=30), st.sampled_from(["current", "voltage", "diagnosis"]))
def test_crc_equals_cantools(rows: list[tuple[bytes, bool]], kind: str) -> None:
    assert crc_table().shape == (256,)
    db = load_database()
    msg = db.message(kind, 3)  # type: ignore[arg-type]
    data = np.frombuffer(b"".join(p for p, _ in rows), np.uint8).reshape(-1, 8).copy()
    for p, (_, fix) in zip(data, rows, strict=True):
        if fix:  # half of them valid
            p[0] = int(compute_profile2_crc(bytes(p), msg) or 0)
    ok = profile2_ok(msg, data, 8)
    from cantools.autosar.end_to_end import check_profile2_crc

    assert ok.tolist() == [bool(check_profile2_crc(bytes(p), msg)) for p in data]


# ------------------------------------------------------------------ logs


def test_a_silence_is_reported_at_the_same_tick_by_both_engines(tmp_path: Path) -> None:
    """Node 0 falls silent for 1.2 s while frames of an id of no node go on every 7.3 ms.
    Both engines tick at frames, every `TICK_S` of bus time (`feed_log`'s rule; the
    columnar `ticks` kernel compiles its own copy of the period), and report the silence at
    the first tick `silence_timeout_s` or more after the node's last output frame: a kernel
    that ticked at another period would report it at another time."""
    db = load_database()
    gap = (1005.0, 1006.2)
    frames = [m for m in sim_frames("healthy") if not gap[0] <= m.timestamp < gap[1]]
    frames += [can.Message(timestamp=gap[0] + 0.0001 + 0.0073 * k, arbitration_id=0x7F0,
                           data=bytes(8), is_extended_id=False) for k in range(160)]
    frames.sort(key=lambda m: m.timestamp)
    path = write_log(tmp_path / "silence.log", frames)
    cfg = MonitorConfig(nodes=(0,))
    res, _, a = compare_engines(path, db, load_database(), cfg)
    assert res.columnar
    current = db.frame_id("current", 0)
    frames = list(read_log(path))  # the time stamps as the log holds them
    last_output = max(m.timestamp for m in frames
                      if m.arbitration_id == current and m.timestamp < gap[0])
    ticks, last_tick = [], -math.inf
    for m in frames:
        if m.timestamp - last_tick >= TICK_S:
            last_tick = m.timestamp
            ticks.append(last_tick)
    want = next(t for t in ticks if t - last_output >= cfg.silence_timeout_s)
    silences = [e for e in a.transitions if e.cause == "silence"]
    assert [e.t for e in silences] == [want]
    assert [e.t for e in res.events if e.cause == "silence"] == [want]


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_reader_gives_python_cans_frames(tmp_path: Path, suffix: str) -> None:
    frames = sim_frames("healthy", bad=True)[:3000]
    frames.append(can.Message(timestamp=frames[-1].timestamp + 0.01, arbitration_id=0x123,
                              data=bytes(range(12)), is_fd=True, is_extended_id=False))
    frames.append(can.Message(timestamp=frames[-1].timestamp + 0.01, arbitration_id=0x124,
                              data=bytes(range(64)), is_fd=True, bitrate_switch=True,
                              error_state_indicator=True, is_extended_id=False))
    path = write_log(tmp_path / f"x{suffix}", frames)
    want = list(can.LogReader(str(path)))
    got = [c.message(i) for c in read_chunks(path, 256) for i in range(len(c))]
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        assert g.timestamp == w.timestamp
        assert (g.arbitration_id, g.is_extended_id, g.is_remote_frame, g.is_error_frame) == \
            (w.arbitration_id, w.is_extended_id, w.is_remote_frame, w.is_error_frame)
        assert (g.is_fd, g.bitrate_switch, g.error_state_indicator) == \
            (w.is_fd, w.bitrate_switch, w.error_state_indicator)
        assert bytes(g.data) == bytes(w.data)  # CAN FD payloads whole, not cut to 8 bytes
    lengths = [int(c.length[i]) for c in read_chunks(path, 256) for i in range(len(c))]
    assert lengths == [len(w.data) for w in want]


@pytest.mark.parametrize(("scenario", "bad", "drop", "repeat", "late", "suffix"), [
    ("fault-outage-recovery", False, 0, 0, False, ".log"),
    ("healthy", False, 0, 0, False, ".blf"),
    ("fault-outage-recovery", True, 97, 211, False, ".log"),
    ("fault-outage-recovery", True, 0, 0, False, ".asc"),
    ("fault-outage-recovery", True, 0, 0, True, ".log"),
])
def test_columnar_equals_per_frame_on_sim_logs(tmp_path: Path, scenario: str, bad: bool,
                                               drop: int, repeat: int, late: bool,
                                               suffix: str) -> None:
    frames = sim_frames(scenario, bad=bad, drop=drop, repeat=repeat, late=late)
    path = write_log(tmp_path / f"run{suffix}", frames)
    res, _, a = compare_engines(path, load_database(), load_database(), MonitorConfig(nodes=(0,)))
    assert res.columnar
    assert a.transitions  # something to compare
    if bad:
        c = res.counters
        for name in ("rejected/unknown_id", "rejected/wrong_length", "rejected/bad_crc",
                     "rejected/out_of_range", "rejected/malformed", "rejected/remote_frame",
                     "rejected/extended_id", "ignored/node", "ignored/diagnosis"):
            assert c.get(name, 0) > 0, name
        if repeat:
            assert c.get("e2e/repeated", 0) > 0 and c.get("e2e/lost_frames", 0) > 0
        assert c.get("estimator/restarts", 0) > 0 and c.get("nodes/silent", 0) > 0
    if late:
        c = res.counters
        assert c.get("e2e/repeated", 0) == 1 and c.get("e2e/counter_jumps", 0) >= 2, c
        assert c.get("samples/predicted_through", 0) >= 15 + 31, c


def test_columnar_equals_per_frame_two_nodes_all_monitored(tmp_path: Path) -> None:
    frames = sim_frames("fault-outage-recovery", nodes=(0, 1), drop=53)
    path = write_log(tmp_path / "two.log", frames)
    compare_engines(path, load_database(), load_database(), MonitorConfig(nodes=None), chunk=4096)


@pytest.mark.parametrize(("rig", "scenario", "node", "drop"), [
    ("servo.toml", "servo_scenario.toml", 1, 0),
    ("press.toml", "press_excite.toml", 1, 50),
    ("twin.toml", "twin_fault.toml", 1, 50),
])
def test_columnar_equals_per_frame_on_rigs(tmp_path: Path, rig: str, scenario: str,
                                           node: int, drop: int) -> None:
    r = load_rig(TEST_RIGS / rig)
    codec = build_decoder(r)
    assert isinstance(codec, RigCodec)
    ecu = RigECU(None, codec, r, node, load_scenario(TEST_RIGS / scenario), seed=5)
    frames = [m for i, m in enumerate(ecu.frames(start_time=1000.0))
              if not (drop and i % drop == 7)]
    path = write_log(tmp_path / "rig.log", frames)
    res, _, a = compare_engines(path, build_decoder(r), build_decoder(r),
                                monitor_config(NO_OVERRIDES, r), chunk=1500)
    assert res.columnar and a.samples


def test_secoc_falls_back_to_the_per_frame_path(tmp_path: Path,
                                                caplog: pytest.LogCaptureFixture) -> None:
    path = write_log(tmp_path / "s.log", sim_frames("healthy")[:2000])
    key = bytes(range(16))
    a = Recorder()
    pipe = MonitorPipeline(load_database(secoc_key=key), MonitorConfig(nodes=(0,)), sink=a)
    feed_log(pipe, read_log(path))
    b = Recorder()
    with caplog.at_level("WARNING"):
        res = replay_file(path, load_database(secoc_key=key), MonitorConfig(nodes=(0,)), b)
    assert not res.columnar and res.fallback and "SecOC" in res.fallback
    assert "frame by frame" in caplog.text
    assert res.counters == dict(pipe.counters)
    assert (b.transitions, b.diagnoses, b.samples) == (a.transitions, a.diagnoses, a.samples)


def test_rerun_sink_gets_the_same_columns(tmp_path: Path) -> None:
    """The RerunSink's column buffers, filled by slices, carry the rows that sample by
    sample feeding gives them (they are cut into batches at other places: the per-frame path
    flushes a node's buffers at each of its events, the columnar one per chunk)."""
    from monitor.sinks.rerun import RerunSink

    path = write_log(tmp_path / "r.log", sim_frames("fault-outage-recovery"))
    names = ("t", "measured", "estimated", "gamma", "gamma_sd", "rules", "health", "nis",
             "output_noise", "process_noise")

    def spy(sink: RerunSink) -> dict[str, list[np.ndarray]]:
        rows: dict[str, list[np.ndarray]] = {k: [] for k in (*names, "tu", "u")}
        flush_s, flush_u = sink._flush_samples, sink._flush_input

        def samples(st: Any) -> None:
            for k in names:
                rows[k].append(getattr(st, k)[..., :st.n].copy())  # outputs: 2-D
            flush_s(st)

        def inputs(buf: Any) -> None:
            rows["tu"].append(buf.t[:buf.n].copy())
            rows["u"].append(buf.v[:buf.n].copy())
            flush_u(buf)

        sink._flush_samples = samples  # type: ignore[method-assign]
        sink._flush_input = inputs  # type: ignore[method-assign]
        return rows

    a = RerunSink(rrd_path=tmp_path / "a.rrd", nodes=(0,))
    rows_a = spy(a)
    pipe = MonitorPipeline(load_database(), MonitorConfig(nodes=(0,)), sink=a)
    feed_log(pipe, read_log(path))
    a.close()
    b = RerunSink(rrd_path=tmp_path / "b.rrd", nodes=(0,))
    rows_b = spy(b)
    replay_file(path, load_database(), MonitorConfig(nodes=(0,)), b, chunk_frames=1001)
    b.close()
    for k in rows_a:
        assert np.array_equal(np.concatenate(rows_a[k], axis=-1),
                              np.concatenate(rows_b[k], axis=-1)), k
    assert len(np.concatenate(rows_a["t"])) == pipe.counters["samples/estimated"]
