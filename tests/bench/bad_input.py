"""Bad-input matrix against the real daemon on vcan: `python -m tests.bench.bad_input`.

Every kind of bad frame and bus fault of the robustness brief, sent to a running
``motor-monitor run`` on a real SocketCAN vcan interface (User-Mode Linux where the host
kernel has none; the two boots of tests/support/boots.py), then malformed DBC,
threshold and scenario files and wrong command lines, run on the host (they are refused
before any bus is opened; the wrong-channel cases run in the guest, on a kernel with
SocketCAN). For each kind it records:

* sent: frames (or runs) sent;
* crashes: the daemon died during the kind, or exited non-zero, or printed a traceback
  (files and arguments: a traceback, or an exit status other than 2);
* NaN estimates: NaN gamma^ rows in the recording in the kind's window;
* samples lost: samples the daemon counted as estimated in the kind's window (between the
  counter snapshots it logs into its .rrd) minus the rows recorded there; after SIGTERM,
  its exit summary minus the rows; after SIGKILL, 0 if the file reaches to within 0.25 s of
  the kill;
* reached the estimator: recorded samples whose kernel time stamp is that of an injected
  frame (matched with the candump capture);
* accounted by: the counters that moved (or the one error line).

Prints a markdown table and a JSON line. About 3 minutes (two kernel boots of ~1.5 min and
~45 s, then ~40 short processes on the host).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from monitor.bus.codec import MotorDatabase, load_database
from tests.support.bad_frames import FrameKind
from tests.support.boots import (
    FLOOD_S,
    MAX_KILL_LOSS_S,
    NO_DATA,
    REPLAYS,
    BootA,
    BootB,
    run_boot_a,
    run_boot_b,
)
from tests.support.cli_cases import CliOutcome, cli_cases, guest_cli_outcomes, run_cli_cases
from tests.support.rrd import RERUN_EXE, bad_outcomes, outcome_total
from tests.support.vcan_harness import run_on_vcan, vcan_unavailable_reason


@dataclass
class Row:
    group: str
    kind: str
    sent: int
    crashes: int
    nan: int | None  # None: not applicable
    lost: int | None
    reached: int | None
    accounted: str
    ok: bool
    note: str = ""


def _fmt(d: dict[str, int]) -> str:
    return ", ".join(f"{k} +{v}" for k, v in sorted(d.items())) or "nothing"


def _lost(boot: BootA, i: int | None, j: int | None) -> int:
    if j is None:
        return 0
    before = 0 if i is None else boot.snaps.at(i).get("samples/estimated", 0)
    return boot.snaps.at(j).get("samples/estimated", 0) - before - boot.rows_between(i, j)


def _window_nan(boot: BootA, i: int | None, j: int | None) -> int:
    lo = -math.inf if i is None else float(boot.snaps.t[i])
    hi = math.inf if j is None else float(boot.snaps.t[j])
    return boot.nan_between(lo, hi)


def frame_rows(boot: BootA, mdb: MotorDatabase) -> list[Row]:
    rows: list[Row] = []
    reached = boot.classify_rows(mdb)
    for kind in [*boot.kinds, FrameKind("replay", "replay: the ECU's last frame again (same "
                                        "alive counter)", (), {"e2e/repeated": 1})]:
        sent = int(boot.values.get(f"sent_{kind.key}", 0))
        if not boot.has(f"{kind.key}_start"):
            rows.append(Row("frames", kind.title, sent, 1, None, None, None, "not run", False,
                            "the script did not get there"))
            continue
        lo, hi = boot.mark(f"{kind.key}_start"), boot.mark(f"{kind.key}_end")
        if kind.key == "replay":  # no snapshot while the ECU is silent: up to the new ECU
            i, j = boot.snaps.last_before(boot.mark("ecu_stop")), boot.snaps.first_after(
                boot.mark("ecu2_up"))
        else:
            i, j = boot.bracket(lo, hi)
        moved = bad_outcomes(boot.snaps.delta(i, j))
        expect = {k: v * sent for k, v in kind.expect.items()}
        extra = boot.restart_repeats(mdb) if kind.key == "replay" else 0
        if extra:  # the new ECU's first frame repeated the old one's last counter
            expect["e2e/repeated"] += extra
        crashes = int(boot.values.get(f"alive_{kind.key}") != "1")
        n_reached = reached.get(kind.key, 0)
        nan = _window_nan(boot, i, j)
        lost = _lost(boot, i, j)
        seen = len(boot.injected(kind))
        ok = (moved == expect and crashes == 0 and n_reached == 0 and nan == 0 and lost == 0
              and seen == sent == (REPLAYS if kind.key == "replay" else len(kind.frames)))
        note = "" if seen == sent else f"{seen} of {sent} seen on the bus"
        if extra:
            note += f" (+{extra}: the restarted ECU's first frame, same counter as its last)"
        if moved != expect:
            note += f" expected {_fmt(expect)}"
        rows.append(Row("frames", kind.title, sent, crashes, nan, lost, n_reached, _fmt(moved),
                        ok, note.strip()))
    return rows


def fault_rows(boot: BootA, mdb: MotorDatabase) -> list[Row]:
    rows: list[Row] = []
    t, _ = boot.gamma()

    # a silent ECU
    if boot.has("ecu2_up"):
        stopped = boot.mark("ecu_stopped")
        last = max((x for x, _ in boot.genuine_current(mdb) if x <= stopped), default=math.nan)
        diag = [(x, s) for x, s, _ in boot.diagnosis_frames(mdb)
                if last < x < boot.mark("replay_start")]
        first = next((x for x, s in diag if s == NO_DATA), math.nan)
        i = boot.snaps.last_before(boot.mark("ecu_stop"))
        j = boot.snaps.first_after(boot.mark("ecu2_up"))
        silent = boot.snaps.delta(i, j).get("nodes/silent", 0)
        delay = first - last
        ok = silent >= 1 and 0.5 <= delay <= 1.0
        rows.append(Row("faults", "silent ECU (sim-ecu stopped)", 1,
                        int(boot.values.get("alive_replay") != "1"), _window_nan(boot, i, j),
                        _lost(boot, i, j), None,
                        f"nodes/silent +{silent}; no_data on the bus {1e3 * delay:.0f} ms after "
                        f"the last frame, then {sum(s == NO_DATA for _, s in diag)} at 10 Hz",
                        ok))

    def link(title: str, start: str, end: str | None, resumed_after: str) -> None:
        if not boot.has(start):
            rows.append(Row("faults", title, 0, 1, None, None, None, "not run", False))
            return
        i = boot.snaps.last_before(boot.mark(start))
        j = boot.snaps.first_after(boot.mark(end)) if end else len(boot.snaps) - 1
        d = boot.snaps.delta(i, j)
        out, rec = d.get("bus/outages", 0), d.get("bus/reconnects", 0)
        after = t[t > boot.mark(resumed_after)]
        back = (after[0] - boot.mark(resumed_after)) if len(after) else math.inf
        alive = boot.values.get("alive_linkdown" if start == "down" else "alive_linkdel")
        ok = out >= 1 and rec >= 1 and back < 1.0 and alive == "1"
        note = "" if out <= 1 else f"{out} outages counted for one (see the report)"
        rows.append(Row("faults", title, 1, int(alive != "1"), _window_nan(boot, i, j),
                        _lost(boot, i, j), None,
                        f"bus/outages +{out}, bus/reconnects +{rec}; estimating again "
                        f"{1e3 * back:.0f} ms after it was back", ok and out == 1, note))

    link("interface down 1 s, up again (ip link set down/up)", "down", "ecu_stop", "up")
    link("interface deleted and re-created (ip link del/add)", "del", None, "ecu2_up")

    # SIGTERM
    s = boot.summary
    rc = boot.values.get("mon_rc")
    tb = "Traceback" in boot.mon_err
    verify = subprocess.run([str(RERUN_EXE), "rrd", "verify", str(boot.out / "a.rrd")],
                            capture_output=True, text=True, timeout=120, check=False)
    lost = (s["estimated"] - len(t)) if s else None
    nan = int(np.count_nonzero(np.isnan(boot.gamma()[1])))
    took = boot.mark("term_done") - boot.mark("term") if boot.has("term_done") else math.nan
    ok = rc == "0" and not tb and verify.returncode == 0 and lost == 0 and nan == 0
    rows.append(Row("faults", "SIGTERM (after all of the above)", 1, int(rc != "0" or tb), nan,
                    lost, None, f"exit {rc} after {took:.2f} s, 'rerun rrd verify' "
                    f"{'passes' if verify.returncode == 0 else 'FAILS'}, {len(t)} rows = "
                    f"{s['estimated'] if s else '?'} estimated", ok))
    # frame conservation over the whole run
    bad = sum(1 for k in range(len(boot.snaps))
              if boot.snaps.at(k).get("frames/received", 0) != outcome_total(boot.snaps.at(k)))
    if bad:
        rows.append(Row("faults", "frame accounting", 0, 0, None, None, None,
                        f"{bad} snapshots where the outcomes do not add up", False))
    return rows


def flood_rows(boot: BootB) -> list[Row]:
    rows: list[Row] = []
    if "mark_flood_end" not in boot.values:
        return [Row("faults", "flood", 0, 1, None, None, None, "not run", False)]
    f0, f1 = boot.mark("flood_start"), boot.mark("flood_end")
    snaps = boot.snaps
    i, j = snaps.last_before(f0), snaps.first_after(f1)
    d = snaps.delta(i, j)
    t, g = boot.gamma()
    lost = 0
    for k in range(len(snaps)):  # rows up to each snapshot = estimated at it
        lost = max(lost, snaps.at(k).get("samples/estimated", 0)
                   - int(np.count_nonzero(t <= snaps.t[k] + 1e-7)))
    rss0 = boot.rss_at(f0)
    rss_max = max((mb for x, mb in boot.rss if f0 <= x <= boot.mark("kill")), default=math.nan)
    rejected = sum(v for k, v in d.items() if k.startswith("rejected/"))
    during = int(np.count_nonzero((t > f0) & (t < f1)))
    alive = boot.values.get("alive_flood") == "1"
    nan = int(np.count_nonzero(np.isnan(g)))
    ok = (alive and d.get("bus/socket_drops", 0) > 0 and rss_max - rss0 < 32 and nan == 0
          and lost == 0)
    rows.append(Row("faults", f"flood: 2 x cangen -g 0 for {f1 - f0:.0f} s (random std; "
                    "mixed ext/RTR/FD)", boot.bus_frames(), int(not alive), nan, lost, None,
                    f"bus/socket_drops +{d.get('bus/socket_drops', 0)}, rejected/* +{rejected}, "
                    f"frames/received +{d.get('frames/received', 0)}; {during} estimates during "
                    f"it; RSS {rss0:.0f} -> max {rss_max:.0f} MB", ok))
    margin = boot.kill_margin()
    verify = subprocess.run([str(RERUN_EXE), "rrd", "verify", str(boot.out / "b.rrd"),
                             "--check-footers", "false"], capture_output=True, text=True,
                            timeout=120, check=False)
    ok = margin <= MAX_KILL_LOSS_S and verify.returncode == 0
    rows.append(Row("faults", "SIGKILL (3 s after the flood)", 1, 0, nan,
                    0 if margin <= MAX_KILL_LOSS_S else None, None,
                    f"last sample on disk {1e3 * margin:.0f} ms before the kill (goal <= "
                    f"{1e3 * MAX_KILL_LOSS_S:.0f}); lenient verify "
                    f"{'passes' if verify.returncode == 0 else 'FAILS'}", ok))
    return rows


def cli_rows(outcomes: list[CliOutcome]) -> list[Row]:
    rows = []
    for o in outcomes:
        crash = int(o.traceback or o.returncode not in (2,))
        errors = [ln for ln in o.lines if ": error: " in ln]
        shown = (errors or list(o.lines) or ["(nothing on stderr)"])[-1]
        note = "" if o.clean else (f"exit {o.returncode}, {len(o.lines)} lines"
                                   + (", traceback" if o.traceback else ""))
        rows.append(Row("files/CLI", o.case.title, 1, crash, None, None, None,
                        shown[:110], o.clean, note))
    return rows


def table(rows: list[Row]) -> str:
    def cell(v: int | None) -> str:
        return "-" if v is None else str(v)

    out = ["| kind | sent | crashes | NaN estimates | samples lost | reached estimator | "
           "accounted by | ok |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        acc = r.accounted.replace("|", "\\|")
        ok = "yes" if r.ok else f"**no**{': ' + r.note if r.note else ''}"
        out.append(f"| {r.kind} | {r.sent} | {r.crashes} | {cell(r.nan)} | {cell(r.lost)} | "
                   f"{cell(r.reached)} | {acc} | {ok} |")
    return "\n".join(out)


def main() -> int:
    ap = argparse.ArgumentParser(prog="python -m tests.bench.bad_input", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--keep", type=Path, default=None,
                    help="keep the boots' files here (default: a temporary directory)")
    ap.add_argument("--flood", type=float, default=FLOOD_S, help="flood seconds")
    ap.add_argument("--no-vcan", action="store_true", help="only the files and arguments")
    args = ap.parse_args()
    work = args.keep or Path(tempfile.mkdtemp(prefix="bad-input-"))
    work.mkdir(parents=True, exist_ok=True)
    mdb = load_database()
    rows: list[Row] = []
    timings: dict[str, float] = {}
    reason = None if not args.no_vcan else "--no-vcan"
    reason = reason or vcan_unavailable_reason()
    backend = "none"
    try:
        if reason is None:
            t0 = time.monotonic()
            a = run_boot_a(run_on_vcan, mdb, work / "boot_a")
            timings["boot_a_s"] = time.monotonic() - t0
            backend = a.result.backend
            if not a.ok:
                print(f"boot A failed: rc {a.result.returncode}\n{a.result.stdout[-2000:]}")
            rows += frame_rows(a, mdb) + fault_rows(a, mdb)
            t0 = time.monotonic()
            b = run_boot_b(run_on_vcan, work / "boot_b", flood_s=args.flood)
            timings["boot_b_s"] = time.monotonic() - t0
            if not b.ok:
                print(f"boot B failed: rc {b.result.returncode}\n{b.result.stdout[-2000:]}")
            rows += flood_rows(b)
            guest = guest_cli_outcomes(a.out)
        else:
            print(f"no vcan ({reason}): only files and arguments")
            guest = []
        t0 = time.monotonic()
        host = run_cli_cases(cli_cases(work / "files"), work)
        timings["cli_s"] = time.monotonic() - t0
        rows += cli_rows(host + guest)
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    print(table(rows))
    frames = sum(r.sent for r in rows if r.group == "frames")
    totals: dict[str, Any] = {  # the JSON line's figures: counts and the kinds not ok
        "kinds": len(rows),
        "frame_kinds": sum(r.group == "frames" for r in rows),
        "fault_kinds": sum(r.group == "faults" for r in rows),
        "file_cli_kinds": sum(r.group == "files/CLI" for r in rows),
        "bad_frames_sent": frames,
        "flood_frames": next((r.sent for r in rows if r.kind.startswith("flood")), 0),
        "crashes": sum(r.crashes for r in rows),
        "nan_estimates": sum(r.nan or 0 for r in rows),
        "samples_lost": sum(r.lost or 0 for r in rows),
        "reached_estimator": sum(r.reached or 0 for r in rows),
        "not_ok": [r.kind for r in rows if not r.ok],
    }
    print(f"\n{totals['kinds']} kinds ({totals['frame_kinds']} of frames, "
          f"{totals['fault_kinds']} bus faults and signals, {totals['file_cli_kinds']} files and "
          f"arguments); {frames} bad frames + {totals['flood_frames']} flood frames sent; "
          f"crashes {totals['crashes']}, NaN estimates {totals['nan_estimates']}, recorded "
          f"samples lost {totals['samples_lost']}, bad frames estimated "
          f"{totals['reached_estimator']}; not ok: {len(totals['not_ok'])}")
    print(json.dumps({"backend": backend, **totals, **{k: round(v, 1) for k, v in
                                                        timings.items()},
                      "rows": [asdict(r) for r in rows]}, separators=(",", ":")))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
