"""CiA 402 twin benchmark: `python -m tests.bench.cia402 [--quick]`.

The twin of `rigs/cia402-example.toml` (`sim_ecu.cia402`: a CiA 402 drive in cyclic
synchronous velocity mode and the host that drives it) gives a healthy, excited minute
(a PRBS on the target velocity) as a candump log; `motor-monitor identify` learns the model
from it as a user would (the rig file without its `[model]`); then `motor-monitor replay`
diagnoses seeded runs of the twin with the rig's own model and with the learned one, side
by side: abrupt losses of 0.3 and 0.6, a drive Fault (the scenario's outage: the drive
reports Fault and an EMCY, and its frames are not read until it is operational again), a
loss of 0.4 followed by a drive Fault and the recovery, and a healthy hour (5 minutes with
`--quick`). The frames are the twin's own (`Cia402ECU.frames`, the frames it sends on a
bus, here without waiting for real time); `tests/integration/test_canopen_vcan.py` shows the live
monitor on vcan gives the events a replay of the capture gives.

Scored from the events (`tests.bench.zoo.score`): accuracy outside 0.3 s after each true
change and the first 2 s, outside the drive's Fault (where the node has no data: it said
so itself); false alarms; the delay from each loss >= 0.3 to the first alarm; and alarms
while the drive reported Fault (a drive's own Fault is never an actuator fault).

Targets (issue 19), with the learned model: accuracy >= 99 %, 0 false alarms in the healthy
hour, abrupt losses >= 0.3 detected within 0.15 s, no alarm during a drive Fault. A table,
then the figures as JSON on the last line.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from monitor.bus.rigcodec import RigCodec
from monitor.rig import build_decoder, load_rig
from sim_ecu.cia402 import Cia402ECU
from sim_ecu.scenario import scenario_from_dict
from tests.bench.rig_zoo import Cmd, json_safe, run_cmd
from tests.bench.zoo.score import ALARM, NodeTruth, read_events, score_node
from tests.support.paths import ROOT

EXAMPLE = ROOT / "rigs" / "cia402-example.toml"
NODE = 1
START = 1.7e9  # the capture's time base (epoch seconds, as a logger's)
LEVEL = 100.0  # rad/s: the target velocity the host holds
DETECT_S = 0.15


@dataclass(frozen=True)
class Run:
    name: str
    duration: float
    faults: tuple[tuple[float, float, float], ...]  # (start, end, gamma); gamma 1: drive Fault
    seed: int

    @property
    def drive_faults(self) -> list[tuple[float, float]]:
        return [(a, b) for a, b, g in self.faults if g >= 1.0]


def runs(quick: bool) -> list[Run]:
    return [
        Run("abrupt-0.3", 10.0, ((4.0, 10.0, 0.3),), 11),
        Run("abrupt-0.6", 10.0, ((4.0, 10.0, 0.6),), 12),
        Run("drive-fault", 10.0, ((4.0, 7.0, 1.0),), 13),
        Run("loss-then-drive-fault", 16.0, ((4.0, 8.0, 0.4), (8.0, 11.0, 1.0)), 14),
        Run("healthy-hour", 300.0 if quick else 3600.0, (), 15),
    ]


def write_frames(codec: RigCodec, scenario: dict[str, Any], seed: int, path: Path) -> int:
    """The twin's frames of `scenario` as a candump log at `path`; how many."""
    rig = load_rig(EXAMPLE)
    ecu = Cia402ECU(None, codec, rig, NODE, scenario_from_dict(scenario), seed=seed)
    n = 0
    with can.Logger(str(path)) as log:
        for msg in ecu.frames(start_time=START):
            log.on_message_received(msg)
            n += 1
    return n


def rig_without_model(d: Path) -> Path:
    """The example rig as a user starts it: its bus and signals, no `[model]`."""
    text = EXAMPLE.read_text()
    head, _, rest = text.partition("\n[model]")
    tail = rest[rest.index("\n[", 1):] if "\n[" in rest[1:] else ""
    shutil.copy(EXAMPLE.with_suffix(".eds"), d / EXAMPLE.with_suffix(".eds").name)
    path = d / "my-drive.toml"
    path.write_text(head + "\n" + tail)
    return path


@dataclass
class Scored:
    accuracy: float
    false_alarms: int
    delays: list[float]
    alarms_in_drive_fault: int
    estimated: int | None


def score(run: Run, events_path: Path, c: Cmd) -> Scored:
    """Accuracy, false alarms and delays of each stretch between drive Faults (each scored
    as a run of its own: the node is silent in between, by the drive's own word), and the
    alarms raised while the drive reported Fault or within 0.3 s after it."""
    events = read_events(events_path)[0].get(NODE, [])
    bounds = [0.0]
    for a, b in run.drive_faults:
        bounds += [a, b]
    bounds.append(run.duration)
    acc_w, acc_n, fa, delays = 0.0, 0.0, 0, []
    for a, b in zip(bounds[::2], bounds[1::2], strict=True):
        steps = [(START + s, g) for s, e, g in run.faults if g < 1.0 and a <= s < b]
        steps += [(START + e, 0.0) for s, e, g in run.faults if g < 1.0 and a < e < b]
        truth = NodeTruth(START + a, b - a, sorted(steps))
        ns = score_node(events, truth)
        if not math.isnan(ns.accuracy):
            acc_w += ns.accuracy * (b - a)
            acc_n += b - a
        fa += ns.false_alarms
        delays += ns.delays
    in_fault = sum(1 for te, st, _ in events for a, b in run.drive_faults
                   if START + a <= te < START + b + 0.3 and st in ALARM)
    m = re.search(r"(\d+) estimated", c.last_line)
    return Scored(acc_w / acc_n if acc_n else math.nan, fa, delays, in_fault,
                  int(m.group(1)) if m else None)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tests.bench.cia402", description=__doc__)
    p.add_argument("--quick", action="store_true", help="a 5-minute healthy run, not an hour")
    p.add_argument("--keep", default=None, help="keep the files in this directory")
    args = p.parse_args(argv)
    d = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="cia402-bench-"))
    d.mkdir(parents=True, exist_ok=True)
    codec = build_decoder(load_rig(EXAMPLE))
    assert isinstance(codec, RigCodec)
    t0 = time.perf_counter()
    capture = {"name": "healthy-excited", "duration": 60.0,
               "voltage": {"prbs": {"level": LEVEL, "amplitude": 20.0, "clock": 0.5,
                                    "seed": 3}}}
    write_frames(codec, capture, 1, d / "healthy.log")
    mine = rig_without_model(d)
    ident = run_cmd(["identify", "healthy.log", "--rig", mine.name, "--node", str(NODE),
                     "--out", "learned.toml"], d)
    ident_s = time.perf_counter() - t0
    said = ident.stdout.strip().splitlines()
    ident_line = ident.last_line or (said[-1] if said else "")
    print(f"identify: exit {ident.rc} in {ident.seconds:.1f} s: {ident_line}")
    models = {"own": EXAMPLE}  # the rig's own model; the one identify learned
    if ident.rc == 0:
        models["learned"] = d / "learned.toml"
    table: dict[str, dict[str, Any]] = {}
    for r in runs(args.quick):
        scenario = {"name": r.name, "duration": r.duration,
                    "voltage": {"steps": [[0.0, LEVEL]]},
                    "fault": [{"start": a, "gamma": g, **({"end": b} if b < r.duration else {})}
                              for a, b, g in r.faults]}
        log = d / f"{r.name}.log"
        frames = write_frames(codec, scenario, r.seed, log)
        for label, rig_path in models.items():
            ev = d / f"{r.name}.{label}.jsonl"
            c = run_cmd(["replay", log.name, "--rig", str(rig_path), "--events", ev.name], d)
            s = score(r, ev, c)
            table.setdefault(r.name, {})[label] = {
                "exit": c.rc, "frames": frames, "estimated": s.estimated,
                "accuracy": s.accuracy, "false_alarms": s.false_alarms,
                "delays_s": s.delays, "alarms_in_drive_fault": s.alarms_in_drive_fault}
    print(f"\n{'run':24s} {'model':8s} {'accuracy':>9s} {'false al.':>9s} "
          f"{'delays s':>12s} {'alarm in Fault':>14s}")
    for name, by_model in table.items():
        for label, f in by_model.items():
            delays = ",".join(f"{x:.3f}" for x in f["delays_s"]) or "-"
            print(f"{name:24s} {label:8s} {100 * f['accuracy']:8.3f}% "
                  f"{f['false_alarms']:9d} {delays:>12s} {f['alarms_in_drive_fault']:14d}")
    learned = [v["learned"] for v in table.values() if "learned" in v]
    worst_delay = max((x for f in learned for x in f["delays_s"]), default=math.nan)
    result = {
        "identified": ident.rc == 0, "identify_s": round(ident_s, 1),
        "identify_line": ident_line,
        "learned_min_accuracy": min((f["accuracy"] for f in learned), default=math.nan),
        "learned_false_alarms": sum(f["false_alarms"] for f in learned),
        "learned_worst_delay_s": worst_delay,
        "learned_alarms_in_drive_fault": sum(f["alarms_in_drive_fault"] for f in learned),
        "targets_met": bool(learned) and ident.rc == 0
        and min(f["accuracy"] for f in learned) >= 0.99
        and sum(f["false_alarms"] for f in learned) == 0
        and worst_delay <= DETECT_S
        and sum(f["alarms_in_drive_fault"] for f in learned) == 0,
        "runs": table,
    }
    print(json.dumps(json_safe(result)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
