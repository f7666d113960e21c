"""Operator metrics: the Prometheus text the monitor writes parses with prometheus_client's
own parser and says what the pipeline counted; `motor-monitor status` renders it; health
transitions reach journald as structured entries (checked on the native protocol's socket,
where no journald runs)."""

from __future__ import annotations

import math
import os
import socket
import subprocess
from pathlib import Path

import can
import pytest
from prometheus_client.parser import text_string_to_metric_families

from monitor.bus.codec import load_database
from monitor.bus.stats import BusStats, fd_frame_bits, frame_bits, frame_time_s
from monitor.pipeline import DiagnosisEvent, MonitorConfig, MonitorPipeline
from monitor.sinks.base import FanOut
from monitor.sinks.journal import JOURNAL_SOCKET, TRANSITION_ID, JournalSink
from monitor.sinks.metrics import MetricsSink
from sim_ecu.ecu import VirtualECU
from sim_ecu.scenario import load_scenario
from tests.support import BIN


def test_frame_bits_worst_case_stuffing() -> None:
    assert frame_bits(can.Message(arbitration_id=1, data=bytes(8), is_extended_id=False)) == 135
    assert frame_bits(can.Message(arbitration_id=1, data=bytes(8), is_extended_id=True)) == 160


def test_fd_frames_take_their_length_and_data_rate() -> None:
    """A 64-byte CAN FD frame, standard ID: 17 arbitration bits + 4 stuff + 12 trailer at
    the nominal rate; 517 (ESI, DLC, data) + 129 stuff + 4 stuff count + 21 CRC + 7 fixed
    stuff + 1 CRC delimiter in the data phase (ISO 11898-1:2015, worst-case stuffing)."""
    fd64 = can.Message(arbitration_id=0x22, data=bytes(64), is_fd=True, bitrate_switch=True,
                       is_extended_id=False)
    assert fd_frame_bits(fd64) == (33, 679)
    assert frame_time_s(fd64, 500_000, 2_000_000) == pytest.approx(33 / 500e3 + 679 / 2e6)
    slow = can.Message(arbitration_id=0x22, data=bytes(64), is_fd=True, is_extended_id=False)
    assert frame_time_s(slow, 500_000, 2_000_000) == pytest.approx(712 / 500e3)  # no BRS
    assert frame_time_s(fd64, 500_000) == pytest.approx(712 / 500e3)  # no data rate given
    classic = can.Message(arbitration_id=1, data=bytes(8), is_extended_id=False)
    assert frame_time_s(classic, 500_000, 2_000_000) == pytest.approx(135 / 500e3)
    fd8 = can.Message(arbitration_id=1, data=bytes(8), is_fd=True, is_extended_id=False)
    assert sum(fd_frame_bits(fd8)) > frame_bits(classic)  # the longer CRC and stuff count
    ext = can.Message(arbitration_id=1, data=bytes(8), is_fd=True, is_extended_id=True)
    assert fd_frame_bits(ext)[0] > fd_frame_bits(fd8)[0]
    lengths = [sum(fd_frame_bits(can.Message(data=bytes(n), is_fd=True)))
               for n in (0, 8, 12, 16, 20, 24, 32, 48, 64)]
    assert lengths == sorted(lengths) and len(set(lengths)) == len(lengths)
    # 100 such frames a second on 500 kbit/s nominal, 2 Mbit/s data: the load is their time
    stats = BusStats(bitrate=500_000, data_bitrate=2_000_000)
    for k in range(201):
        stats(can.Message(timestamp=k / 100, arbitration_id=0x22, data=bytes(64), is_fd=True,
                          bitrate_switch=True, is_extended_id=False))
    assert stats.load == pytest.approx(100 * (33 / 500e3 + 679 / 2e6), rel=0.02)


def test_metrics_file_parses_and_agrees_with_the_counters(tmp_path: Path) -> None:
    db = load_database()
    frames = list(VirtualECU(None, db, 0, load_scenario("fault-outage-recovery"), seed=3)
                  .frames(start_time=1.7e9))
    stats = BusStats(bitrate=500_000)
    path = tmp_path / "monitor.prom"
    metrics = MetricsSink(path, bus=stats, live=False)
    pipe = MonitorPipeline(db, MonitorConfig(), sink=FanOut([metrics]))
    for m in frames:
        stats(m)
        pipe.feed(m)
    pipe.emit_counters(frames[-1].timestamp)
    metrics.close()
    fams = {f.name: f for f in text_string_to_metric_families(path.read_text())}
    events = {s.labels["name"]: s.value for s in fams["motor_monitor_events"].samples
              if s.name.endswith("_total")}
    assert events["frames/received"] == len(frames) == pipe.counters["frames/received"]
    assert events["samples/estimated"] == pipe.counters["samples/estimated"]
    (state,) = fams["motor_monitor_node_health_state"].samples
    assert state.labels == {"node": "0"} and state.value == int(pipe.nodes[0].state)
    (sd,) = fams["motor_monitor_node_gamma_sd"].samples  # the last sample's, to the digit
    assert sd.labels == {"node": "0"}
    assert sd.value == float(pipe.nodes[0].estimator.out.gamma_sd[0]) > 0.0
    # the estimator's noise factors after the last sample, to the digit: finite, >= 1 (on
    # the model's), the output named as the rig names it
    out = pipe.nodes[0].estimator.out
    (noise,) = fams["motor_monitor_node_output_noise_factor"].samples
    assert noise.labels == {"node": "0", "output": "ArmatureCurrent"}
    assert noise.value == float(out.output_noise[0]) >= 1.0 and math.isfinite(noise.value)
    (process,) = fams["motor_monitor_node_process_noise_factor"].samples
    assert process.labels == {"node": "0"}
    assert process.value == float(out.process_noise[0]) >= 1.0
    assert math.isfinite(process.value)
    ids = {s.labels["id"]: s.value for s in fams["motor_monitor_id_period_seconds"].samples}
    assert ids["0x110"] == pytest.approx(0.01, rel=1e-6)  # MotorCurrent_N0 at 100 Hz
    (load,) = fams["motor_monitor_bus_load_ratio"].samples
    # 100 + 100 + 20 frames/s of 135 bits on 500 kbit/s
    assert load.value == pytest.approx(220 * 135 / 500_000, rel=0.05)
    res = subprocess.run([str(BIN / "motor-monitor"), "status", str(path)],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "bus load 5.9 %" in res.stdout and "   0  fault_free" in res.stdout, res.stdout
    # node, state, mismatch, gamma^, NIS, the noise factors (three digits), samples
    (row,) = (ln.split() for ln in res.stdout.splitlines() if ln.startswith("   0  "))
    assert " noise x process x " in res.stdout
    assert float(row[5]) == pytest.approx(noise.value, rel=5e-3)
    assert float(row[6]) == pytest.approx(process.value, rel=5e-3)


def test_status_of_a_missing_file_is_one_line(tmp_path: Path) -> None:
    res = subprocess.run([str(BIN / "motor-monitor"), "status", str(tmp_path / "no.prom")],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr


@pytest.mark.skipif(JOURNAL_SOCKET.exists() or os.geteuid() != 0,
                    reason="a real journald owns the socket here, or not root")
def test_transition_reaches_journald_with_its_fields() -> None:
    JOURNAL_SOCKET.parent.mkdir(parents=True, exist_ok=True)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(JOURNAL_SOCKET))
    try:
        JournalSink().on_transition(DiagnosisEvent(1.0, 3, "fault", "fault_free", 0.41, 90.2,
                                                   4, "estimate"))
        sock.settimeout(5)
        fields = dict(line.split("=", 1) for line in sock.recv(65536).decode().splitlines())
    finally:
        sock.close()
        JOURNAL_SOCKET.unlink()
    assert fields["MESSAGE_ID"] == TRANSITION_ID
    assert (fields["NODE"], fields["STATE"], fields["PREVIOUS"]) == ("3", "fault", "fault_free")
    assert fields["GAMMA"] == "0.4100" and fields["PRIORITY"] == "4"
    assert fields["SYSLOG_IDENTIFIER"] == "motor-monitor"
