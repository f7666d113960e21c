"""End-to-end: sim-ecu, motor-monitor, can-utils and cantools together.

The ``vcan``-marked tests run real processes on a real SocketCAN ``vcan0`` (natively, or in
User-Mode Linux: see tests/support/vcan_harness.py), one kernel boot per test, and check the results
on the host: the candump capture (decoded by ``cantools decode`` and by our codec), the
monitor's JSON-lines events and its Rerun recording. The replay tests run
``motor-monitor replay`` on candump .log, Vector .asc and .blf files on the host. No mocks.

Oracle: the SimTruth frames carry the true loss of effectiveness gamma; its class under
F1 = 0.15, F2 = 0.85 (eq 76) is what the MonitorDiagnosis frames and the events must follow:
the new state within ``DELAY_BOUND_S`` of each true change in sample time (the events; the
frames get ``FRAME_LAG_S`` more for the daemon's scheduling), and no other state at any other
time (from the first sample on: no start-up transient is tolerated). Inside the window after
a true change the state may pass through the fault band (outage -> fault -> fault_free) or
flicker while the estimate settles; that is printed, not failed.

Timing on vcan: the monitor time-stamps frames with their kernel receive time and turns an
interval of >= 1.5 nominal periods into predicted-through samples. Under User-Mode Linux with
several busy processes, frames are often delayed by 10-25 ms without any being lost; the
tests print how many (``jitter_report``). A guest whose processes starve for longer (a CI
machine under load: an ECU that took 16.96 s for 16 s of samples) holds the frames a
diagnosis needs: the time the capture shows a stream standing still (``stalled``) is added
to the frame-by-frame bound, and printed.

Run with ``-s`` to see the measured detection delays.
"""

from __future__ import annotations

import bisect
import itertools
import json
import re
import shlex
import subprocess
import warnings
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np
import pyarrow as pa
import pytest
from rerun.chunk import RrdReader

from monitor.bus.codec import Decoded, MotorDatabase, load_database
from monitor.pipeline import DiagnosisEvent, MonitorConfig
from monitor.pipeline.feed import feed_log
from monitor.sinks.blueprint import counter_path
from sim_ecu.ecu import VirtualECU
from sim_ecu.scenario import Scenario, load_scenario, scenario_from_dict
from tests.support import BIN
from tests.support.dbc import REPO_DBC
from tests.support.pipeline import pipeline
from tests.support.vcan_scripts import RunOnVcan, monitor_summary, run_ready

MONITOR_EXE = BIN / "motor-monitor"
RERUN_EXE = BIN / "rerun"
CANTOOLS_EXE = BIN / "cantools"

F1, F2 = 0.15, 0.85
FAULT_FREE, FAULT, OUTAGE, NO_DATA = 0, 1, 2, 3
LABELS = {FAULT_FREE: "fault_free", FAULT: "fault", OUTAGE: "outage", NO_DATA: "no_data"}

#: Bound on truth change -> diagnosis (product target 0.15 s; UML syscalls and the 10 Hz
#: steady publication add delay).
DELAY_BOUND_S = 0.5
#: Extra room for a MonitorDiagnosis frame's own lag behind the sample it reports: in the test
#: the daemon shares the guest's one CPU with the ECUs and candump, and on a loaded machine it
#: processes the socket's backlog late. The estimator's delay itself (in sample time, from
#: the events) is held to DELAY_BOUND_S by `check_event_sequence`.
FRAME_LAG_S = 1.5
#: The nominal periods of a node's current frames and of the monitor's steady diagnosis
#: frames: an interval past 1.5 of them is a stream standing still (`stalled`).
CURRENT_PERIOD_S = 0.01
DIAGNOSIS_PERIOD_S = 0.1
#: Hand-over from no_data to the first estimate, left out of the frame-by-frame comparison.
STARTUP_S = 0.1
#: The monitor turns a node no_data after 0.5 s without current frames.
SILENCE_S = 0.5

T0 = 1_700_000_000.0  # epoch seconds, like kernel time stamps

#: Short timeline for the canplayer test: fault 1.5-3 s, outage 3-4 s, recovered 4-5 s.
SHORT_SCENARIO = {
    "name": "short-fault-outage-recovery",
    "duration": 5.0,
    "fault": [
        {"start": 1.5, "end": 3.0, "gamma": 0.4},
        {"start": 3.0, "end": 4.0, "gamma": 1.0},
    ],
}


@pytest.fixture(scope="module")
def mdb() -> MotorDatabase:
    return load_database()


# ----------------------------------------------------------------------------- helpers


def true_class(gamma: float) -> int:
    """Eq (76) on the true gamma (written out here, independent of monitor.diagnosis)."""
    if gamma < F1:
        return FAULT_FREE
    return FAULT if gamma <= F2 else OUTAGE


@dataclass
class Capture:
    """A candump capture decoded with our codec, per node."""

    truth: dict[int, list[tuple[float, float]]] = field(default_factory=lambda: defaultdict(list))
    diag: dict[int, list[tuple[float, int, float]]] = field(
        default_factory=lambda: defaultdict(list)
    )  # (t, HealthState, GammaEstimate)
    current: dict[int, list[tuple[float, int]]] = field(
        default_factory=lambda: defaultdict(list)
    )  # (t, alive counter)
    counts: Counter[tuple[str, int]] = field(default_factory=Counter)
    rejected: list[str] = field(default_factory=list)
    n_frames: int = 0


def read_capture(path: Path, mdb: MotorDatabase) -> Capture:
    cap = Capture()
    with can.LogReader(str(path)) as reader:
        for msg in reader:
            cap.n_frames += 1
            d = mdb.decode_can(msg)
            if not isinstance(d, Decoded):
                cap.rejected.append(f"{d.reason} 0x{d.arbitration_id:X} {d.detail}")
                continue
            cap.counts[(d.kind, d.node)] += 1
            if d.kind == "current":
                cap.current[d.node].append((d.timestamp, int(d.counter or 0)))
            elif d.kind == "truth":
                cap.truth[d.node].append((d.timestamp, d.value))
            elif d.kind == "diagnosis":
                cap.diag[d.node].append((d.timestamp, int(d.raw["HealthState"]), d.value))
    return cap


def class_changes(truth: list[tuple[float, float]]) -> list[tuple[float, int, int]]:
    """(t, previous class, new class) at every change of the true class."""
    out: list[tuple[float, int, int]] = []
    prev: int | None = None
    for t, g in truth:
        c = true_class(g)
        if prev is not None and c != prev:
            out.append((t, prev, c))
        prev = c
    return out


def detection_delays(
    truth: list[tuple[float, float]], diag: list[tuple[float, int, float]]
) -> list[tuple[float, int, int, float | None]]:
    """For each true change: (t, previous, new, delay until a diagnosis frame says `new`)."""
    out: list[tuple[float, int, int, float | None]] = []
    for t, prev, new in class_changes(truth):
        hit = next((td for td, s, _ in diag if td >= t and s == new), None)
        out.append((t, prev, new, None if hit is None else hit - t))
    return out


def stalled(times: list[float], period: float, t0: float, t1: float) -> float:
    """How long a stream of frames sent every `period` (`times`, sorted) stood still within
    [t0, t1]: the excess over 1.5 periods of each interval between two of its frames, as
    far as the interval lies inside [t0, t1]."""
    out = 0.0
    for a, b in itertools.pairwise(times):
        if b - a > 1.5 * period:
            out += max(0.0, min(b, t1) - max(a + 1.5 * period, t0))
    return out


def paced(times: list[float], period: float) -> list[float]:
    """Of sorted `times`, those at least `period` after the previous one kept: when a frame
    sent at that pace from samples arriving at `times` goes out."""
    out: list[float] = []
    for t in times:
        if not out or t - out[-1] >= period:
            out.append(t)
    return out


def stall_allowance(cap: Capture, node: int, t0: float, t1: float) -> float:
    """The time within [t0, t1] that the node's current frames or its diagnosis frames stood
    still, whichever is longer: the ECU or the daemon starved on the guest's CPU."""
    return max(stalled([t for t, _ in cap.current[node]], CURRENT_PERIOD_S, t0, t1),
               stalled([t for t, _, _ in cap.diag[node]], DIAGNOSIS_PERIOD_S, t0, t1))


def disagreements(
    truth: list[tuple[float, float]], diag: list[tuple[float, int, float]], skip_start: float,
    settle: list[tuple[float, float]],
) -> tuple[int, list[str]]:
    """Diagnosis frames whose state is not the true class, while the ECU runs.

    Left out: the first `skip_start` s after the first truth frame and each (t, span) of
    `settle` (a true change and the time the diagnosis has to follow it). Returns (frames
    compared, descriptions of mismatches).
    """
    times = [t for t, _ in truth]
    start, end = times[0] + skip_start, times[-1]
    compared, bad = 0, []
    for td, state, g in diag:
        if not start <= td <= end or any(tc <= td < tc + span for tc, span in settle):
            continue
        compared += 1
        expected = true_class(truth[bisect.bisect_right(times, td) - 1][1])
        if state != expected:
            bad.append(
                f"t={td - times[0]:.3f}s: {LABELS.get(state, state)} (gamma^ {g:.3f}), "
                f"true {LABELS[expected]}"
            )
    return compared, bad


def check_follows_truth(cap: Capture, node: int, label: str, skip_start: float = STARTUP_S) -> None:
    truth, diag = cap.truth[node], cap.diag[node]
    assert truth and diag, f"{label}: no SimTruth or no MonitorDiagnosis frames of node {node}"
    t_first = truth[0][0]
    delays = detection_delays(truth, diag)
    settle: list[tuple[float, float]] = []  # (true change, the time its report may take)
    for t, prev, new, delay in delays:
        shown = "never" if delay is None else f"{1e3 * delay:.0f} ms"
        base = DELAY_BOUND_S + FRAME_LAG_S
        stall = stall_allowance(cap, node, t, t + (base if delay is None else delay))
        settle.append((t, base + stall))
        print(f"[{label}] node {node}: true {LABELS[prev]} -> {LABELS[new]} at "
              f"{t - t_first:.2f} s, diagnosed after {shown}"
              + (f" (the frames stood still {1e3 * stall:.0f} ms of it)" if stall else ""))
    for (t, prev, new, delay), (_, bound) in zip(delays, settle, strict=True):
        assert delay is not None and 0.0 <= delay <= bound, (
            f"{label}: {LABELS[prev]} -> {LABELS[new]} at {t - t_first:.2f} s: delay {delay} "
            f"> {bound:.2f} s ({DELAY_BOUND_S} + {FRAME_LAG_S} + the frames standing still)"
        )
    startup = [f"{td - t_first:.2f}s {LABELS[s]}" for td, s, _ in diag
               if t_first <= td < t_first + skip_start and s != true_class(truth[0][1])]
    if startup:
        print(f"[{label}] node {node}: diagnosis before {skip_start} s: "
              f"{startup[0]} .. {startup[-1]} ({len(startup)} frames)")
    compared, bad = disagreements(truth, diag, skip_start, settle)
    # The monitor publishes at 10 Hz (more at changes): expect most of those frames.
    steady = truth[-1][0] - t_first - skip_start - sum(b for _, b in settle)
    assert compared >= 0.8 * 10 * steady, \
        f"{label}: {compared} diagnosis frames in {steady:.1f} s"
    assert not bad, f"{label}: {len(bad)} of {compared} diagnosis frames disagree: {bad[:5]}"


def read_events(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def check_event_sequence(
    events: list[dict[str, Any]],
    node: int,
    t_start: float,
    expected: list[tuple[str, float]],
    label: str,
    tolerance: float = DELAY_BOUND_S,
) -> list[float]:
    """The node's estimate-caused events: fault_free at its first sample (`t_start`), then
    only inside the window [t, t + tolerance] of each `expected` (state, absolute time t of
    the true change), the last one in each window being that state. Returns the delays
    (first event of the expected state - t).

    Inside a window the state may pass through another one (on the way down from outage the
    estimate crosses the fault band) or flicker while the estimate settles; such extra
    events are printed.
    """
    mine = [e for e in events if e["node"] == node and e["cause"] == "estimate"]
    assert mine, f"{label}: no events of node {node}"
    first = mine[0]
    assert (first["state"], first["previous"]) == ("fault_free", "no_data"), (label, first)
    assert -0.005 <= first["t"] - t_start < 0.1, (label, first, t_start)
    windows: list[list[dict[str, Any]]] = [[] for _ in expected]
    for e in mine[1:]:
        hits = [i for i, (_, t) in enumerate(expected) if t <= e["t"] <= t + tolerance]
        assert hits, f"{label}: node {node}: {e['state']} at {e['t'] - t_start:.3f} s is " \
            f"outside every window after a true change: {mine}"
        windows[hits[0]].append(e)
    delays: list[float] = []
    for (state, t), evs in zip(expected, windows, strict=True):
        seq = [f"{e['state']}@{e['t'] - t_start:.2f}s" for e in evs]
        assert evs and evs[-1]["state"] == state, (
            f"{label}: node {node}: after the true change to {state} at {t - t_start:.2f} s "
            f"the events were {seq}"
        )
        delays.append(next(e["t"] for e in evs if e["state"] == state) - t)
        if len(evs) > 1:
            print(f"[{label}] node {node}: events settling after the change to {state} at "
                  f"{t - t_start:.2f} s: {', '.join(seq)}")
    print(f"[{label}] node {node} events: " + ", ".join(
        f"{state} +{1e3 * d:.0f} ms" for (state, _), d in zip(expected, delays, strict=True)))
    return delays


def expected_from_truth(truth: list[tuple[float, float]]) -> list[tuple[str, float]]:
    """The (state, time) of each true class change, as `check_event_sequence` takes them."""
    return [(LABELS[new], t) for t, _, new in class_changes(truth)]


def jitter_report(cap: Capture, node: int, label: str) -> None:
    """Print how many current frames came >= 1.5 periods after the previous one although
    none was lost (alive counters consecutive): the monitor counts those as missed samples."""
    cur = cap.current[node]
    late = sum(
        1 for (t0, c0), (t1, c1) in itertools.pairwise(cur)
        if (c1 - c0) % 16 == 1 and t1 - t0 >= 0.015
    )
    gaps = [t1 - t0 for (t0, _), (t1, _) in itertools.pairwise(cur)]
    print(f"[{label}] node {node}: {len(cur)} current frames, max interval "
          f"{1e3 * max(gaps):.1f} ms, {late} arrived >= 15 ms after the previous one with "
          "none lost")


def rrd_series(path: Path, entity: str) -> tuple[np.ndarray, np.ndarray]:
    """(time [s], value) of a Scalars entity of an .rrd file, sorted by time."""
    ts: list[np.ndarray] = []
    vs: list[np.ndarray] = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for chunk in RrdReader(path).stream():
            if chunk.is_static or chunk.entity_path != entity:
                continue
            rb = chunk.to_record_batch()
            ts.append(rb.column("time").cast(pa.int64()).to_numpy())
            vs.append(rb.column("Scalars:scalars").flatten().to_numpy())
    if not ts:
        return np.zeros(0), np.zeros(0)
    t, v = np.concatenate(ts), np.concatenate(vs)
    order = np.argsort(t, kind="stable")
    return t[order] / 1e9, v[order]


def rrd_verify(path: Path) -> None:
    proc = subprocess.run(
        [str(RERUN_EXE), "rrd", "verify", str(path)],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert proc.returncode == 0, f"rerun rrd verify {path}: {proc.stdout}{proc.stderr}"


def ecu_sent(stderr: str) -> dict[str, int]:
    m = re.search(r"sent current=(\d+) voltage=(\d+) truth=(\d+), send errors (\d+)", stderr)
    assert m, f"no summary line in sim-ecu's stderr:\n{stderr}"
    return dict(zip(("current", "voltage", "truth", "errors"), map(int, m.groups()),
                    strict=True))


def offline_events(mdb: MotorDatabase, frames: Iterable[can.Message]) -> list[DiagnosisEvent]:
    events: list[DiagnosisEvent] = []
    feed_log(pipeline(mdb, MonitorConfig(nodes=(0,)), events=events), frames)
    return events


def live_run(vcan: RunOnVcan, run: str, out: Path, programs: tuple[str, ...]) -> dict[str, int]:
    """Run ``RUN=run`` of tests/support/scripts/integration.sh into ``out``: each of
    `programs` (``<name>_rc``, stderr in ``<name>.err``), the monitor and candump must have
    exited 0. Returns the monitor's summary after SIGTERM."""
    values = run_ready(vcan, "integration.sh", out, env={"RUN": run}, timeout=480.0)
    for name in (*programs, "mon", "dump"):
        err = out / ("candump.err" if name == "dump" else f"{name}.err")
        assert values[f"{name}_rc"] == "0", err.read_text()
    mon_err = (out / "mon.err").read_text()
    summary = monitor_summary(mon_err)
    assert summary, f"no summary line after SIGTERM in the monitor's stderr:\n{mon_err}"
    print(f"[{run}] monitor: {summary}")
    return summary


# ----------------------------------------------------------------------------- 1: live

@pytest.mark.vcan
def test_live_ecu_and_monitor_on_vcan(vcan: RunOnVcan, mdb: MotorDatabase, tmp_path: Path) -> None:
    summary = live_run(vcan, "live", tmp_path, ("ecu",))
    ecu_err = (tmp_path / "ecu.err").read_text()
    sent = ecu_sent(ecu_err)
    print(f"[live] sim-ecu: {ecu_err.strip()}")
    assert sent["errors"] == 0 and sent["current"] >= 1550, ecu_err  # 1600 without overruns

    # cantools decodes the capture, the monitor's own frames included.
    cap_log = tmp_path / "cap.log"
    with cap_log.open("rb") as fh:
        dec = subprocess.run(
            [str(CANTOOLS_EXE), "decode", str(REPO_DBC)], stdin=fh, capture_output=True, text=True,
            timeout=120, check=False,
        )
    assert dec.returncode == 0, dec.stderr
    names = Counter(re.findall(r"^(\w+)\($", dec.stdout, re.MULTILINE))
    assert names["MotorCurrent_N0"] == sent["current"], names
    assert names["MotorVoltage_N0"] == sent["voltage"], names
    assert names["SimTruth_N0"] == sent["truth"], names
    assert names["MonitorDiagnosis_N0"] == summary["sent"] >= 100, names
    assert re.search(r"HealthState: outage,", dec.stdout)

    # Our codec: every frame valid (CRCs and alive counters of the monitor's frames too),
    # and the monitor received every frame the ECU sent.
    cap = read_capture(cap_log, mdb)
    assert not cap.rejected, cap.rejected[:5]
    # Every frame is received or counted as dropped by the kernel (a one-CPU guest that
    # stalls the daemon for a moment: its socket overflows; the counter reaches the recording).
    rrd = tmp_path / "live.rrd"
    _, kernel_drops = rrd_series(rrd, counter_path("bus/socket_drops"))
    drops = int(kernel_drops[-1]) if len(kernel_drops) else 0
    if drops:
        print(f"[live] {drops} frames dropped by the kernel (counted)")
    assert summary["frames"] + drops == sent["current"] + sent["voltage"] + sent["truth"]
    assert summary["rejected"] == 0
    # the first current precedes a voltage
    assert summary["estimated"] >= sent["current"] - 1 - drops
    jitter_report(cap, 0, "live")
    check_follows_truth(cap, 0, "live")

    # Events: fault at 4 s, outage at 8 s, fault_free at 11 s, no_data once the ECU stopped.
    truth = cap.truth[0]
    t_start = truth[0][0]
    events = read_events(tmp_path / "ev.jsonl")
    assert [s for s, _ in expected_from_truth(truth)] == ["fault", "outage", "fault_free"]
    check_event_sequence(events, 0, t_start, expected_from_truth(truth), "live")
    last = events[-1]
    assert (last["state"], last["cause"]) == ("no_data", "silence"), last
    assert SILENCE_S <= last["t"] - truth[-1][0] <= SILENCE_S + 1.0, last
    assert [e["state"] for e in events if e["cause"] == "estimate"][-1] == "fault_free"

    # The recording: closed cleanly on SIGTERM, gamma^ over the run.
    rrd_verify(rrd)
    t_bus, v = rrd_series(rrd, "/node/0/gamma/estimate")
    assert len(v) == summary["estimated"] >= 300, len(v)
    assert t_bus[-1] - t_bus[0] == pytest.approx(truth[-1][0] - t_start, abs=0.05)
    # the windows in scenario time, from the SimTruth frame sent with each sample (an ECU held
    # up in the busy guest sends samples late, which stretches bus time)
    t = np.interp(t_bus, np.array([tt for tt, _ in truth]), np.arange(len(truth)) / 100.0)
    fault = v[(t >= 5.0) & (t <= 7.0)]
    outage = v[(t >= 9.0) & (t <= 10.5)]
    healthy = v[(t >= 1.0) & (t <= 3.9)]
    assert len(fault) >= 150 and len(outage) >= 100 and len(healthy) >= 200
    assert abs(np.median(fault) - 0.4) < 0.05 and np.all(np.abs(fault - 0.4) < 0.15), fault
    assert abs(np.median(outage) - 1.0) < 0.05 and np.all(outage > F2), outage
    assert np.all(healthy < F1), healthy.max()


# ----------------------------------------------------------------------------- 2: canplayer

@pytest.mark.vcan
def test_canplayer_replays_a_log_into_the_monitor(
    vcan: RunOnVcan, mdb: MotorDatabase, tmp_path: Path
) -> None:
    scenario = scenario_from_dict(SHORT_SCENARIO)
    frames = list(VirtualECU(None, mdb, 0, scenario, seed=0).frames(start_time=T0))
    # As recorded on a real bus "can0": canplayer maps it to vcan0 (vcan0=can0).
    with can.CanutilsLogWriter(tmp_path / "short.log", channel="can0") as writer:
        for msg in frames:
            writer.on_message_received(msg)
    n_current = sum(1 for m in frames if m.arbitration_id == 0x110)
    assert n_current == 500

    summary = live_run(vcan, "player", tmp_path, ("player",))

    cap = read_capture(tmp_path / "cap.log", mdb)
    assert not cap.rejected, cap.rejected[:5]
    # Every frame of the log went out on vcan0 with its payload, and reached the monitor.
    assert cap.counts[("current", 0)] == n_current
    assert summary["frames"] == len(frames) and summary["rejected"] == 0
    replayed = [m for m in can.LogReader(str(tmp_path / "cap.log")) if m.arbitration_id != 0x180]
    assert [bytes(m.data) for m in replayed] == [bytes(m.data) for m in frames]
    # ... at the original pace (5 s of frames).
    assert replayed[-1].timestamp - replayed[0].timestamp == pytest.approx(4.99, abs=0.3)

    jitter_report(cap, 0, "canplayer")
    check_follows_truth(cap, 0, "canplayer")
    t_start = cap.truth[0][0][0]
    events = read_events(tmp_path / "ev.jsonl")
    expected = expected_from_truth(cap.truth[0])
    assert [s for s, _ in expected] == ["fault", "outage", "fault_free"]
    assert [t - t_start for _, t in expected] == pytest.approx([1.5, 3.0, 4.0], abs=0.05)
    check_event_sequence(events, 0, t_start, expected, "canplayer")
    assert (events[-1]["state"], events[-1]["cause"]) == ("no_data", "silence")

    # The live monitor on the replayed bus agrees with the same pipeline fed the log offline.
    offline = offline_events(mdb, frames)
    live = [e for e in events if e["cause"] == "estimate"]
    assert [e["state"] for e in live] == [e.state for e in offline]
    for e_live, e_off in zip(live, offline, strict=True):
        assert e_live["t"] - t_start == pytest.approx(e_off.t - T0, abs=0.2), (e_live, e_off)


# ----------------------------------------------------------------------------- 3: two nodes

@pytest.mark.vcan
def test_two_nodes_one_monitor(vcan: RunOnVcan, mdb: MotorDatabase, tmp_path: Path) -> None:
    summary = live_run(vcan, "two_nodes", tmp_path, ("ecu0", "ecu1"))
    for node in (0, 1):
        print(f"[two nodes] {(tmp_path / f'ecu{node}.err').read_text().strip()}")
    assert summary["rejected"] == 0

    cap = read_capture(tmp_path / "cap.log", mdb)
    assert not cap.rejected, cap.rejected[:5]
    for node in (0, 1):
        assert cap.counts[("current", node)] >= 1550, cap.counts
        assert cap.counts[("diagnosis", node)] >= 100, cap.counts

    # Node 0 goes through fault and outage and back, as its truth does.
    for node in (0, 1):
        jitter_report(cap, node, "two nodes")
    check_follows_truth(cap, 0, "two nodes")
    events = read_events(tmp_path / "ev.jsonl")
    expected = expected_from_truth(cap.truth[0])
    assert [s for s, _ in expected] == ["fault", "outage", "fault_free"]
    check_event_sequence(events, 0, cap.truth[0][0][0], expected, "two nodes")

    # Node 1 (healthy) is fault_free from its first sample to
    # its last, in every diagnosis frame and event, while node 0 is faulty.
    truth1 = cap.truth[1]
    assert {true_class(g) for _, g in truth1} == {FAULT_FREE}
    t1_first, t1_last = truth1[0][0], truth1[-1][0]
    during = [(t, s, g) for t, s, g in cap.diag[1] if t1_first + 0.1 <= t <= t1_last]
    # One frame every 0.1 s of the node's samples (the times its current frames arrived:
    # a starved guest spreads them, 137 frames in 16 s with intervals up to 133 ms).
    due = paced([t for t, _ in cap.current[1]], DIAGNOSIS_PERIOD_S)
    due_during = sum(1 for t in due if t1_first + 0.1 <= t <= t1_last)
    assert due_during >= 100 and len(during) >= due_during - 2, (len(during), due_during)
    assert all(s == FAULT_FREE for _, s, _ in during), [x for x in during if x[1]][:5]
    assert max(g for _, _, g in during) < F1
    check_follows_truth(cap, 1, "two nodes")
    ev1 = [e for e in events if e["node"] == 1]
    assert [(e["state"], e["previous"]) for e in ev1] == [
        ("fault_free", "no_data"), ("no_data", "fault_free")
    ], ev1
    assert ev1[-1]["cause"] == "silence"
    # The nodes really overlapped: node 1 was fault_free while node 0 was in outage.
    outage0 = [t for t, s, _ in cap.diag[0] if s == OUTAGE]
    assert outage0 and t1_first < outage0[0] < t1_last


# ----------------------------------------------------------------------------- 4: replay


@pytest.fixture(scope="module")
def fault_run(mdb: MotorDatabase) -> list[can.Message]:
    scenario: Scenario = load_scenario("fault-outage-recovery")
    return list(VirtualECU(None, mdb, 0, scenario, seed=1).frames(start_time=T0))


WRITERS: dict[str, Callable[[Path], Any]] = {
    "log": lambda p: can.CanutilsLogWriter(p, channel="vcan0"),
    "asc": lambda p: can.ASCWriter(p),
    "blf": lambda p: can.BLFWriter(p),
}


@pytest.mark.parametrize("fmt", sorted(WRITERS))
def test_replay_log_asc_blf(
    fmt: str, fault_run: list[can.Message], mdb: MotorDatabase, tmp_path: Path
) -> None:
    log_path = tmp_path / f"run.{fmt}"
    with WRITERS[fmt](log_path) as writer:
        for msg in fault_run:
            writer.on_message_received(msg)
    with can.LogReader(str(log_path)) as reader:
        t_start = next(iter(reader)).timestamp  # .asc reads back relative to its start
    rrd = tmp_path / "replay.rrd"
    proc = subprocess.run(
        [str(MONITOR_EXE), "replay", str(log_path), "--rrd", str(rrd)],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert proc.returncode == 0, proc.stderr
    assert f"replayed {len(fault_run)} frames" in proc.stderr, proc.stderr
    assert re.search(r", 0 rejected$", proc.stderr.strip()), proc.stderr
    events = [json.loads(line) for line in proc.stdout.splitlines()]
    assert events and all(e["node"] == 0 for e in events), proc.stdout

    delays = check_event_sequence(
        events, 0, t_start, [("fault", t_start + 4.0), ("outage", t_start + 8.0),
                             ("fault_free", t_start + 11.0)], f"replay .{fmt}", tolerance=0.3)
    assert len(delays) == 3
    # The same events, at the same times, as the pipeline fed the frames directly.
    expected = offline_events(mdb, fault_run)
    assert [e["state"] for e in events] == [e.state for e in expected]
    for got, exp in zip(events, expected, strict=True):
        assert got["t"] - t_start == pytest.approx(exp.t - T0, abs=1e-3)
        assert got["gamma"] == pytest.approx(exp.gamma, abs=1e-6)

    rrd_verify(rrd)
    t, v = rrd_series(rrd, "/node/0/gamma/estimate")
    n_current = sum(1 for m in fault_run if m.arbitration_id == 0x110)
    assert len(v) == n_current - 1  # the first current frame precedes the first voltage
    t = t - t[0]
    assert abs(np.median(v[(t >= 5.0) & (t <= 7.0)]) - 0.4) < 0.05
    assert np.all(v[(t >= 9.0) & (t <= 10.5)] > F2)


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("missing.log", None, "no such file"),
        ("notes.txt", "(1.0) vcan0 110#00\n", "unsupported log format"),
    ],
)
def test_replay_bad_log_is_one_line_and_touches_no_output(
    name: str, content: str | None, message: str, tmp_path: Path
) -> None:
    log_path = tmp_path / name
    if content is not None:
        log_path.write_text(content)
    rrd = tmp_path / "precious.rrd"
    rrd.write_bytes(b"an earlier recording that must survive")
    events = tmp_path / "events.jsonl"
    # --force: the recording is not one motor-monitor wrote, and may be replaced; the bad
    # log must still be found before it is touched
    cmd = [str(MONITOR_EXE), "replay", str(log_path), "--rrd", str(rrd), "--events", str(events),
           "--force"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 2, (shlex.join(cmd), proc.stderr)
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("motor-monitor: error: ") and message in lines[0], lines
    assert str(log_path) in lines[0]
    assert proc.stdout == ""
    # The error comes before any output is opened: nothing created or overwritten.
    assert rrd.read_bytes() == b"an earlier recording that must survive"
    assert not events.exists()
