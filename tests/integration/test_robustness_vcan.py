"""Untrusted bus, real daemon: bad frames, bus faults, a flood and kill signals on real vcan.

"Every frame on a bus is untrusted. A malformed, unknown, out-of-range, replayed or spoofed
frame, an error frame, a silent ECU, an interface that goes down and comes back, a SIGTERM:
each gets a clear, counted, logged outcome, the daemon keeps running, and no recorded data
is lost."

Two kernel boots (module fixtures; tests/support/boots.py runs them, tests/support/scripts/
holds their shell scripts): boot A sends every kind of bad frame with ``cansend`` next to a
healthy ``sim-ecu``, takes the interface down and up, silences the ECU, replays its last
frame, deletes and re-creates the interface and ends with SIGTERM; boot B floods the bus
with ``cangen`` for 10 s and ends with SIGKILL. The host checks the daemon's counters as
logged in its ``.rrd``, every recorded sample against the candump capture (each must be a
genuine ECU frame, none an injected one), its diagnosis frames on the bus, its events, its
exit and its memory.

Run with ``-s`` to see the per-kind table, timings and margins.
"""

from __future__ import annotations

import math
import subprocess
from pathlib import Path

import numpy as np
import pytest

from monitor.bus.codec import MotorDatabase, load_database
from tests.support.bad_frames import FrameKind, check_kinds_offline, frame_kinds
from tests.support.boots import (
    F1,
    KIND_GAP_S,
    MAX_KILL_LOSS_S,
    NO_DATA,
    REPLAYS,
    SILENCE_S,
    BootA,
    BootB,
    run_boot_a,
    run_boot_b,
)
from tests.support.cli_cases import CliCase, guest_cli_outcomes, run_cli_case
from tests.support.rrd import RERUN_EXE, bad_outcomes, outcome_total
from tests.support.vcan_scripts import RunOnVcan, logs_tail


@pytest.fixture(scope="module")
def mdb() -> MotorDatabase:
    return load_database()


def _require(boot: BootA | BootB) -> None:
    res = boot.result
    assert res.returncode == 0 and boot.ok, (
        f"rc {res.returncode}\n{res.stdout}\n{res.stderr}\n{logs_tail(boot.out)}")


@pytest.fixture(scope="module")
def boot_a(vcan: RunOnVcan, mdb: MotorDatabase,
           tmp_path_factory: pytest.TempPathFactory) -> BootA:
    boot = run_boot_a(vcan, mdb, tmp_path_factory.mktemp("boot_a"))
    print(f"\n[boot A] {boot.result.backend}, {boot.wall_s:.1f} s; monitor: {boot.summary}")
    return boot


@pytest.fixture(scope="module")
def boot_b(vcan: RunOnVcan, tmp_path_factory: pytest.TempPathFactory) -> BootB:
    boot = run_boot_b(vcan, tmp_path_factory.mktemp("boot_b"))
    print(f"\n[boot B] {boot.result.backend}, {boot.wall_s:.1f} s")
    return boot


def _verify(path: Path, *footers: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(RERUN_EXE), "rrd", "verify", str(path), *footers],
                          capture_output=True, text=True, timeout=120, check=False)


# ----------------------------------------------------------------------------- on the host


def test_bad_frames_are_built_as_intended(mdb: MotorDatabase) -> None:
    """Each bad kind, fed to the pipeline offline, moves exactly its expected counters."""
    kinds = frame_kinds(mdb)
    got = check_kinds_offline(mdb, kinds)
    for kind in kinds:
        expect = {k: v * len(kind.frames) for k, v in kind.expect.items()}
        expect["frames/received"] = len(kind.frames)
        assert got[kind.key] == expect, (kind.key, got[kind.key])


@pytest.mark.parametrize(
    "rate", [
        "0",
        "-5",
        "nan",
    ])
def test_bad_rate_is_one_clear_line(rate: str, tmp_path: Path) -> None:
    case = CliCase(f"rate_{rate}", f"--rate {rate}", (
        "motor-monitor", "run", "--interface", "virtual", "--channel", "bad-rate", "--rate",
        rate), "rate")
    outcome = run_cli_case(case, tmp_path, timeout=60)
    assert outcome.clean, (outcome.returncode, outcome.lines)


# ----------------------------------------------------------------------------- boot A


def _window(boot: BootA, kind: FrameKind) -> tuple[float, float]:
    return boot.mark(f"{kind.key}_start"), boot.mark(f"{kind.key}_end")


@pytest.mark.vcan
def test_bad_frames_each_counted_under_their_reason(boot_a: BootA) -> None:
    _require(boot_a)
    snaps = boot_a.snaps
    assert len(snaps) >= 20, "the daemon logged too few counter snapshots"
    print(f"\n{'kind':<60} sent  seen  counted as")
    starts = sorted(_window(boot_a, k)[0] for k in boot_a.kinds)
    for kind in boot_a.kinds:
        sent = int(boot_a.values[f"sent_{kind.key}"])
        assert sent == len(kind.frames), (kind.key, sent)
        assert boot_a.values[f"alive_{kind.key}"] == "1", f"daemon died during {kind.key}"
        seen = boot_a.injected(kind)
        assert len(seen) == sent, (kind.key, len(seen))  # all on the bus (candump)
        lo, hi = _window(boot_a, kind)
        i, j = boot_a.bracket(lo, hi)
        assert j is not None, f"no counter snapshot after {kind.key}"
        nxt = [s for s in starts if s > hi]
        assert not nxt or snaps.t[j] < nxt[0], (
            f"{kind.key}: no snapshot between its window and the next (gap {KIND_GAP_S} s)")
        delta = snaps.delta(i, j)
        moved = bad_outcomes(delta)
        expect = {k: v * sent for k, v in kind.expect.items()}
        dropped = delta.get("bus/socket_drops", 0)
        print(f"{kind.title:<60} {sent:>4}  {len(seen):>4}  {moved}"
              + (f" (kernel drops {dropped})" if dropped else ""))
        if not dropped:
            assert moved == expect, (kind.key, moved, expect)
            continue
        # The daemon fell behind and its socket overflowed (a loaded machine): the frames it
        # saw are counted under their reason, the rest under the kernel's drops.
        assert set(moved) <= set(expect), (kind.key, moved, expect)
        short = {k: expect[k] - moved.get(k, 0) for k in expect}
        assert all(v >= 0 for v in short.values()), (kind.key, moved, expect)
        assert max(short.values()) <= dropped, (kind.key, moved, expect, dropped)


def _start_windows(events: list[dict[str, object]], first: float) -> list[tuple[float, float]]:
    """The first 0.5 s of each estimator (re)start: the first sample, and each return from
    no_data (a gap of > 5 s restarts the estimator)."""
    starts = [first] + [float(e["t"]) for e in events  # type: ignore[arg-type]
                        if e["state"] == "fault_free" and e["previous"] == "no_data"]
    return [(s, s + 0.5) for s in starts]


def _outside(t: np.ndarray, windows: list[tuple[float, float]]) -> np.ndarray:
    keep = np.ones(len(t), dtype=bool)
    for lo, hi in windows:
        keep &= ~((t >= lo) & (t <= hi))
    return keep


@pytest.mark.vcan
def test_bad_frames_never_reach_the_estimator(boot_a: BootA, mdb: MotorDatabase) -> None:
    """Every recorded sample is a genuine ECU frame (matched by its kernel time stamp and
    value in the candump capture), none is an injected one, and no genuine frame is missing
    except while the interface was down."""
    _require(boot_a)
    rows = boot_a.classify_rows(mdb)
    print(f"\n[boot A] recorded samples by origin: {rows}")
    assert rows == {"genuine": rows["genuine"], "unmatched": 0, "value_mismatch": 0}, rows
    t, g = boot_a.gamma()
    assert len(t) and rows["genuine"] == len(t)
    # Genuine frames while the daemon ran, outside the interface outages: each recorded, or
    # dropped by the kernel at start-up (the daemon opens its socket before its estimator is
    # ready and finds a backlog; the socket drops what it cannot hold, and counts it).
    outages = [(boot_a.mark("down"), boot_a.mark("up") + 0.5),
               (boot_a.mark("del"), boot_a.mark("ecu2_up"))]
    lo, hi = t[0], boot_a.mark("term")
    genuine = np.array([x for x, _ in boot_a.genuine_current(mdb) if lo <= x <= hi])
    genuine = genuine[_outside(genuine, outages)]
    recorded = t[np.searchsorted(t, genuine - 3e-6).clip(max=len(t) - 1)]
    missing = genuine[np.abs(recorded - genuine) > 3e-6]
    snaps = boot_a.snaps
    drops = snaps.values.get("bus/socket_drops", np.zeros(len(snaps), dtype=np.int64))
    print(f"[boot A] genuine current frames while monitoring: {len(genuine)}, not recorded: "
          f"{len(missing)} (the first {missing[-1] - lo if len(missing) else 0:.1f} s); kernel "
          f"drops counted: {drops[-1]}")
    assert len(genuine) > 2000
    assert len(missing) <= drops[-1], "genuine frames lost without being counted"
    # After start-up the daemon keeps up, but a loaded machine (the guest has one CPU for the
    # daemon, the ECU, candump and the injectors) can still hold it up until its socket
    # overflows; that is allowed only as counted drops of a small share of the frames.
    late = missing[missing > lo + 5.0]
    if len(late):
        print(f"[boot A] {len(late)} genuine frames dropped by the kernel after start-up, "
              f"at {late[0] - lo:.1f}..{late[-1] - lo:.1f} s (a loaded machine)")
    assert len(late) <= 0.05 * len(genuine), late - lo
    _, amps = boot_a.measured()
    assert not np.any(np.isnan(g))
    assert np.all(np.abs(amps) <= 300.0)
    steady = _outside(t, _start_windows(boot_a.events, float(t[0])))
    print(f"[boot A] gamma^: max {np.max(g):.3f} (max outside the first 0.5 s of each "
          f"estimator start {np.max(g[steady]):.3f}), median {np.median(g):.4f}")
    assert np.max(g[steady]) < F1, "a healthy node's gamma^ was pushed into the fault band"
    # the diagnosis on the bus and the events: healthy or no data, never fault/outage
    diag = boot_a.diagnosis_frames(mdb)
    assert len(diag) >= 200, len(diag)
    assert {s for _, s, _ in diag} <= {0, NO_DATA}, sorted({s for _, s, _ in diag})
    states = {(e["state"], e["cause"]) for e in boot_a.events if e["node"] == 0}
    assert states <= {("fault_free", "estimate"), ("no_data", "silence")}, states


@pytest.mark.vcan
def test_every_frame_has_exactly_one_outcome(boot_a: BootA) -> None:
    """At every counter snapshot: frames received = the sum of the outcome counters."""
    _require(boot_a)
    snaps = boot_a.snaps
    bad = []
    for i in range(len(snaps)):
        c = snaps.at(i)
        if c.get("frames/received", 0) != outcome_total(c):
            bad.append((i, c.get("frames/received"), outcome_total(c), c))
    assert not bad, bad[:3]
    last = snaps.at(len(snaps) - 1)
    print(f"\n[boot A] last counter snapshot: {last}")


@pytest.mark.vcan
def test_silent_ecu_turns_no_data_on_the_bus(boot_a: BootA, mdb: MotorDatabase) -> None:
    _require(boot_a)
    stop, stopped = boot_a.mark("ecu_stop"), boot_a.mark("ecu_stopped")
    genuine = [t for t, _ in boot_a.genuine_current(mdb) if t <= stopped]
    t_last = max(genuine)
    assert t_last >= stop - 0.2, "the ECU was not sending when it was stopped"
    diag = boot_a.diagnosis_frames(mdb)
    silent = [(t, s) for t, s, _ in diag if t_last < t < boot_a.mark("replay_start")]
    first = next((t for t, s in silent if s == NO_DATA), None)
    assert first is not None, silent[:10]
    delay = first - t_last
    print(f"\n[silence] last current frame -> first no_data on the bus: {1e3 * delay:.0f} ms; "
          f"{sum(s == NO_DATA for _, s in silent)} no_data frames while silent")
    assert SILENCE_S <= delay <= SILENCE_S + 0.5, delay
    assert all(s == NO_DATA for t, s in silent if t >= first)
    assert sum(s == NO_DATA for _, s in silent) >= 5  # repeated at 10 Hz
    ev = [e for e in boot_a.events if e["state"] == "no_data" and t_last < e["t"] < first + 0.01]
    assert ev and ev[0]["cause"] == "silence", ev
    i, j = boot_a.bracket(stop, boot_a.mark("ecu2_up"))
    assert boot_a.snaps.delta(i, j).get("nodes/silent", 0) >= 1


@pytest.mark.vcan
def test_replayed_frame_is_dropped_as_repeated(boot_a: BootA, mdb: MotorDatabase) -> None:
    _require(boot_a)
    assert boot_a.replay_frames(), boot_a.values.get("replayed")
    assert int(boot_a.values["sent_replay"]) == REPLAYS
    replay = FrameKind("replay", "replay", (), {})
    assert len(boot_a.injected(replay)) == REPLAYS
    i, j = boot_a.bracket(boot_a.mark("ecu_stop"), boot_a.mark("ecu2_up"))
    moved = bad_outcomes(boot_a.snaps.delta(i, j))
    extra = boot_a.restart_repeats(mdb)
    print(f"\n[replay] counters moved from the silent ECU to the new ECU: {moved} ({extra} "
          "first frames of the new ECU repeated the old one's last counter)")
    assert moved == {"e2e/repeated": REPLAYS + extra}, moved
    assert boot_a.classify_rows(mdb).get("replay", 0) == 0
    t, _ = boot_a.gamma()
    assert not np.any((t >= boot_a.mark("replay_start")) & (t <= boot_a.mark("replay_end")))


def _outages(boot: BootA, start: str, end: str | None) -> dict[str, int]:
    """Outages and reconnects counted from the last snapshot before mark `start` to the
    first after mark `end` (None: the last snapshot, which must come after `start`)."""
    i: int | None
    j: int | None
    if end is None:
        i, last = boot.snaps.last_before(boot.mark(start)), len(boot.snaps) - 1
        assert boot.snaps.t[last] > boot.mark(start)
        j = last
    else:
        i, j = boot.bracket(boot.mark(start), boot.mark(end))
    d = boot.snaps.delta(i, j)
    return {k: d.get(k, 0) for k in ("bus/outages", "bus/reconnects")}


@pytest.mark.vcan
def test_interface_down_and_up_recovers(boot_a: BootA) -> None:
    _require(boot_a)
    assert boot_a.values["alive_linkdown"] == "1"
    counted = _outages(boot_a, "down", "ecu_stop")
    t, _ = boot_a.gamma()
    up = boot_a.mark("up")
    after = t[t > up]
    assert len(after), "no estimate after the interface came back"
    print(f"\n[link down 1 s] {counted}; first estimate {1e3 * (after[0] - up):.0f} ms after "
          f"'ip link set up'")
    assert counted["bus/outages"] >= 1 and counted["bus/reconnects"] >= 1, counted
    assert after[0] - up < 1.0
    assert np.count_nonzero((t > up) & (t < boot_a.mark("ecu_stop"))) >= 150  # ~2.5 s, 100 Hz
    assert "CAN interface failed" in boot_a.mon_err


@pytest.mark.vcan
def test_interface_down_and_up_counts_one_outage(boot_a: BootA) -> None:
    _require(boot_a)
    counted = _outages(boot_a, "down", "ecu_stop")
    assert counted == {"bus/outages": 1, "bus/reconnects": 1}, counted


@pytest.mark.vcan
def test_interface_deleted_and_recreated_recovers(boot_a: BootA) -> None:
    _require(boot_a)
    assert boot_a.values["alive_linkdel"] == "1"
    assert boot_a.values.get("ecu2_up") == "1"
    counted = _outages(boot_a, "del", None)
    print(f"\n[ip link del/add] {counted}")
    assert counted["bus/outages"] >= 1 and counted["bus/reconnects"] >= 1, counted
    assert "CAN interface back after" in boot_a.mon_err
    add = boot_a.mark("add")
    t, _ = boot_a.gamma()
    assert np.count_nonzero((t > boot_a.mark("ecu2_up")) & (t < boot_a.mark("term"))) >= 150
    back = [e for e in boot_a.events if e["t"] > add and e["state"] == "fault_free"]
    assert back, "the node did not come back to fault_free after the new interface"


@pytest.mark.vcan
def test_sigterm_loses_no_recorded_sample(boot_a: BootA) -> None:
    _require(boot_a)
    assert boot_a.values.get("mon_rc") == "0", boot_a.mon_err[-3000:]
    assert "Traceback" not in boot_a.mon_err
    summary = boot_a.summary
    assert summary is not None, boot_a.mon_err[-3000:]
    rrd = boot_a.out / "a.rrd"
    v = _verify(rrd)
    assert v.returncode == 0, v.stderr
    t, g = boot_a.gamma()
    tm, _ = boot_a.measured()
    print(f"\n[SIGTERM] summary {summary}; gamma rows {len(g)}; term -> exit "
          f"{boot_a.mark('term_done') - boot_a.mark('term'):.2f} s")
    assert len(g) == len(tm) == summary["estimated"] > 1000
    assert boot_a.mark("term") - 0.1 <= t[-1] <= boot_a.mark("term_done")


@pytest.mark.vcan
def test_final_counters_reach_the_recording(boot_a: BootA) -> None:
    _require(boot_a)
    assert boot_a.summary is not None
    last = boot_a.snaps.at(len(boot_a.snaps) - 1)
    assert last.get("frames/received") == boot_a.summary["frames"], (last, boot_a.summary)
    assert last.get("samples/estimated") == boot_a.summary["estimated"]


@pytest.mark.vcan
def test_wrong_channel_is_one_line_on_a_socketcan_kernel(boot_a: BootA) -> None:
    _require(boot_a)
    for outcome in guest_cli_outcomes(boot_a.out):
        print(f"\n[{outcome.case.key}] rc {outcome.returncode}: {outcome.lines}")
        if outcome.case.key == "guest_mon_nochan" and len(outcome.lines) > 1:
            continue  # the known bug below
        assert outcome.clean, (outcome.returncode, outcome.lines)


@pytest.mark.vcan
def test_monitor_wrong_channel_is_exactly_one_line(boot_a: BootA) -> None:
    _require(boot_a)
    outcome = guest_cli_outcomes(boot_a.out)[0]
    assert outcome.clean, (outcome.returncode, outcome.lines)


# ----------------------------------------------------------------------------- boot B


@pytest.mark.vcan
def test_flood_is_survived_counted_and_bounded(boot_b: BootB) -> None:
    _require(boot_b)
    assert boot_b.values.get("alive_flood") == "1", boot_b.mon_err[-3000:]
    assert "Traceback" not in boot_b.mon_err
    f0, f1 = boot_b.mark("flood_start"), boot_b.mark("flood_end")
    snaps = boot_b.snaps
    i, j = snaps.last_before(f0), snaps.first_after(f1)
    delta = snaps.delta(i, j)
    frames = boot_b.bus_frames()
    rss0 = boot_b.rss_at(f0)
    during = [mb for t, mb in boot_b.rss if f0 <= t <= boot_b.mark("kill")]
    mid = boot_b.rss_at((f0 + f1) / 2)
    end = boot_b.rss_at(f1)
    print(f"\n[flood {f1 - f0:.1f} s] {frames} frames on the bus; counted over the flood: "
          f"{ {k: v for k, v in sorted(delta.items())} }")
    print(f"[flood] RSS MB: before {rss0:.1f}, middle {mid:.1f}, end {end:.1f}, "
          f"max {max(during):.1f} ({len(boot_b.rss)} samples)")
    # A flood: the bus carries more than twice the healthy ECU's own 220 frames/s (current and
    # truth at 100 Hz, voltage at 20 Hz); ~1,000 frames/s on a quiet machine, 450 in a CI
    # guest on a slow host. Beyond the daemon's pace either way: its socket drops, next line.
    assert frames > 2 * 220 * (f1 - f0), frames
    assert delta.get("bus/socket_drops", 0) > 0, delta  # dropped frames are counted
    # (a few hundred at least, even on a guest the two cangens starve; ~20k on a quiet one)
    assert delta.get("rejected/unknown_id", 0) > 100, delta
    assert delta.get("rejected/extended_id", 0) > 0 and delta.get("rejected/remote_frame", 0) > 0
    assert max(during) - rss0 < 32.0, (rss0, max(during))
    # estimation goes on, and fully after the flood
    t, g = boot_b.gamma()
    assert not np.any(np.isnan(g))
    in_flood = np.count_nonzero((t > f0) & (t < f1))
    assert boot_b.values.get("caught_up") == "1", (
        f"the daemon never caught up after the flood (CPU ticks in its last 0.5 s: "
        f"{boot_b.values.get('busy_ticks')} of 50)")
    calm0, calm1 = boot_b.mark("calm"), boot_b.mark("kill") - 0.3
    calm = np.count_nonzero((t > calm0) & (t < calm1))
    print(f"[flood] estimates during the flood: {in_flood}; in the {calm1 - calm0:.1f} s of calm "
          f"after it: {calm}")
    assert calm >= 0.8 * 100 * (calm1 - calm0), calm
    steady = _outside(t, _start_windows(boot_b.events, float(t[0])))
    above = np.flatnonzero(steady & (g >= F1))
    print(f"[flood] gamma^ max {np.max(g):.3f}, outside the first 0.5 s of each estimator "
          f"start {np.max(g[steady]):.3f}; samples at or above F1: {len(above)}")
    # The flood makes the kernel drop samples, which the estimator predicts through; a sample
    # after such a gap may lift gamma^ into the fault band for a moment (0.22 for one sample
    # in a CI run), never for long enough to change the diagnosis (the states, below).
    assert len(above) <= 3 and np.max(g[steady]) < 0.4, (len(above), np.max(g[steady]))
    states = {(e["state"], e["cause"]) for e in boot_b.events}
    assert states <= {("fault_free", "estimate"), ("no_data", "silence")}, states


@pytest.mark.vcan
def test_flood_every_frame_has_one_outcome_and_no_sample_is_lost(boot_b: BootB) -> None:
    """At each counter snapshot the outcome counters add up (but a last one the SIGKILL
    provably tore: some of its counters not written), and the rows recorded up to its
    time are at least the estimated-sample counter (equal when the snapshot was taken at a
    sample; the snapshot goes to disk after its samples, so a SIGKILL cannot reverse that)."""
    _require(boot_b)
    snaps = boot_b.snaps
    assert len(snaps) >= 10
    t, _ = boot_b.gamma()
    last = len(snaps) - 1
    for i in range(len(snaps)):
        c = snaps.at(i)
        if i == last and not set(snaps.at(i - 1)) <= set(c):
            # The SIGKILL ends the run and may land inside the flush of the last snapshot,
            # whose counters are a chunk each: a counter the previous snapshot had is
            # missing (counters never fall back to 0), so this write was torn, not miscounted.
            continue
        assert c.get("frames/received", 0) == outcome_total(c), c
        rows = int(np.count_nonzero(t <= snaps.t[i] + 1e-7))
        assert rows >= c.get("samples/estimated", 0), (i, rows, c.get("samples/estimated", 0))


@pytest.mark.vcan
def test_sigkill_recording_readable_to_a_quarter_second(boot_b: BootB) -> None:
    _require(boot_b)
    assert boot_b.values.get("mon_rc") == "137", boot_b.values  # 128 + SIGKILL
    v = _verify(boot_b.out / "b.rrd", "--check-footers", "false")
    assert v.returncode == 0, v.stderr
    margin = boot_b.kill_margin()
    shell = boot_b.mark("killed") - boot_b.mark("kill")
    print(f"\n[SIGKILL] kill time - last sample on disk: {1e3 * margin:.0f} ms "
          f"(the kill itself took {1e3 * shell:.0f} ms of shell time)")
    # A sample on disk may be as late as the kill itself (the daemon runs until the signal
    # lands; a daemon that keeps up records what arrives while the shell sends it).
    assert math.isfinite(margin) and margin >= -(shell + 0.01)
    assert margin <= MAX_KILL_LOSS_S, f"{1e3 * margin:.0f} ms lost"

