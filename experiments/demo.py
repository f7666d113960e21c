"""`motor-monitor demo`: the virtual ECU and the monitor in one process, no CAN hardware.

The ECU (sim_ecu) runs the `fault-outage-recovery` scenario in real time in a thread and
sends on python-can's in-process virtual bus; the monitor receives on the same channel,
exactly as `motor-monitor run` does on a real interface, and answers with its
MonitorDiagnosis frames. Writes DIR/demo.rrd (open it with `rerun DIR/demo.rrd`),
DIR/demo_report.png and DIR/events.jsonl, and prints true against detected transitions.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import can
import numpy as np

from experiments.scoring import match_transitions, true_classes
from monitor.bus.codec import MotorDatabase
from monitor.bus.rigcodec import RigCodec
from monitor.diagnosis import DEFAULT_THRESHOLDS, HealthState
from monitor.estimation.model import DCMotorParameters
from monitor.pipeline import Counters, DiagnosisEvent, MonitorPipeline, Sample
from monitor.pipeline import counters as C
from monitor.pipeline.events import HEALTH
from monitor.plotting import pyplot
from monitor.rig import Rig, model_of
from monitor.runtime.argtypes import add_rig_option
from monitor.setup import frame_decoder, monitor_config, setup_rig
from monitor.sinks.base import FanOut, Sink
from monitor.sinks.jsonl import JsonLinesSink
from monitor.sinks.log import LogSink
from monitor.sinks.publisher import BusPublisher
from monitor.sinks.rerun import RerunSink
from sim_ecu.ecu import VirtualECU
from sim_ecu.rig_ecu import RigECU
from sim_ecu.scenario import Scenario, load_scenario

__all__ = ["SampleRows", "add_command", "run_demo"]


class SampleRows(Sink):
    """Keeps every estimator sample, for the report."""

    def __init__(self) -> None:
        self.rows: list[tuple[float, float, float, float, float, int, float]] = []

    def on_sample(self, sample: Sample) -> None:
        tg = math.nan if sample.true_gamma is None else sample.true_gamma
        self.rows.append((sample.t, sample.measured, sample.estimated, sample.gamma, tg,
                          int(sample.state), float(sample.rules)))


class _PrintTransitions(Sink):
    """Prints each transition as it happens, relative to the start of the demo."""

    def __init__(self, t_start: float) -> None:
        self.t_start = t_start

    def on_transition(self, event: DiagnosisEvent) -> None:
        what = (f"{event.previous} -> {event.state}  (gamma^ = {event.gamma:.2f})"
                if event.kind == HEALTH else event.text)  # the model-mismatch flag's
        print(f"  t = {event.t - self.t_start:6.2f} s  node {event.node}: {what}", flush=True)


def _report(rows: np.ndarray, path: Path, f1: float, f2: float) -> None:
    plt = pyplot()

    t = rows[:, 0] - rows[0, 0]
    fig, (a1, a2, a3) = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    a1.plot(t, rows[:, 1], lw=0.6, color="tab:gray", label="measured (CAN)")
    a1.plot(t, rows[:, 2], lw=1.0, color="tab:blue", label="estimated")
    a1.set_ylabel("armature current (A)")
    a1.legend(loc="upper right")
    a1.set_title("motor-monitor demo: node 0, scenario fault-outage-recovery")
    a2.plot(t, rows[:, 4], color="k", lw=1.5, label="true gamma (SimTruth)")
    a2.plot(t, rows[:, 3], color="tab:blue", lw=0.9, label="gamma^ (fuzzy UKF)")
    a2.axhline(f1, color="tab:orange", ls="--", lw=0.8, label=f"F1 = {f1:.2f}")
    a2.axhline(f2, color="tab:red", ls="--", lw=0.8, label=f"F2 = {f2:.2f}")
    a2.set_ylabel("loss of effectiveness")
    a2.legend(loc="upper left", fontsize=8)
    truth = true_classes(np.nan_to_num(rows[:, 4]), DEFAULT_THRESHOLDS)
    a3.step(t, truth, where="post", color="k", lw=1.5, label="true class")
    a3.step(t, rows[:, 5], where="post", color="tab:blue", lw=1.0, label="diagnosed")
    a3.set_yticks([int(s) for s in HealthState], [s.label for s in HealthState])
    a3.set_xlabel("time (s)")
    a3.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _ecu(args: argparse.Namespace, rig: Rig, db: MotorDatabase | RigCodec, node: int,
         scenario: Scenario, bus: can.BusABC) -> VirtualECU | RigECU:
    """The rig's virtual ECU: ours on our bus (with the rig's motor), else its twin."""
    if isinstance(db, MotorDatabase):
        spec, rate = model_of(rig)
        motor = (replace(DCMotorParameters(), **spec.motor)
                 if spec.kind == "dc_motor" else None)
        return VirtualECU(bus, db, node, scenario, rate=rate, seed=args.seed, motor=motor)
    return RigECU(bus, db, rig, node, scenario, seed=args.seed)


def run_demo(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rig = setup_rig(args.rig)
    db = frame_decoder(rig)
    node = 0 if isinstance(db, MotorDatabase) else db.nodes[0]
    scenario = load_scenario(args.scenario)
    ecu_db = frame_decoder(rig)  # its own alive counters
    channel = f"motor-monitor-demo-{os.getpid()}"
    ecu_bus = can.Bus(interface="virtual", channel=channel)
    mon_bus = can.Bus(interface="virtual", channel=channel)
    rrd = out / "demo.rrd"
    cfg = replace(monitor_config(rig), nodes=(node,))
    rows = SampleRows()
    t_start = time.time()
    counters = Counters()
    publisher: list[Sink] = ([BusPublisher(db, mon_bus.send, counters)]
                             if isinstance(db, MotorDatabase) else [])
    sink = FanOut([
        LogSink(),
        *publisher,
        RerunSink(rrd_path=rrd, nodes=(node,), f1=cfg.thresholds.f1, f2=cfg.thresholds.f2),
        JsonLinesSink((out / "events.jsonl").open("w", encoding="utf-8"), owned=True),
        _PrintTransitions(t_start),
        rows,
    ])
    pipe = MonitorPipeline(db, cfg, sink=sink, counters=counters)
    ecu = _ecu(args, rig, ecu_db, node, scenario, ecu_bus)
    stop = threading.Event()
    print(f"demo: virtual ECU node {node} runs '{scenario.name}' ({scenario.description}) for "
          f"{scenario.duration:.0f} s in real time; the monitor listens on the same bus")
    th = threading.Thread(target=ecu.run, args=(scenario.duration, stop), daemon=True)
    th.start()
    try:
        while th.is_alive():
            msg = mon_bus.recv(timeout=0.05)
            if msg is not None:
                pipe.feed(msg)
            pipe.tick(time.time())
            sink.maybe_flush(time.monotonic())
        while (msg := mon_bus.recv(timeout=0.1)) is not None:
            pipe.feed(msg)
    except KeyboardInterrupt:
        stop.set()
        th.join()
    finally:
        sink.close()
        ecu_bus.shutdown()
        mon_bus.shutdown()
    table = np.array(rows.rows)
    if table.size == 0:
        print("demo: no samples were estimated", file=sys.stderr)
        return 1
    _report(table, out / "demo_report.png", cfg.thresholds.f1, cfg.thresholds.f2)
    t = table[:, 0] - t_start
    truth = true_classes(np.nan_to_num(table[:, 4]), cfg.thresholds)
    matches = match_transitions(t, truth, table[:, 5].astype(np.int64))
    print("\ntrue transition                 at (s)   detected at (s)   delay (s)")
    for m in matches:
        det = "missed" if m.t_detected is None else f"{m.t_detected:8.2f}"
        dl = "" if m.delay is None else f"{m.delay:8.2f}"
        print(f"{m.before.label:>10s} -> {m.after.label:<10s} {m.t_true:9.2f}   {det:>14s}   {dl}")
    c = pipe.counters
    print(f"\n{c.get(C.FRAMES_RECEIVED, 0)} frames received, "
          f"{c.get(C.SAMPLES_ESTIMATED, 0)} samples estimated, "
          f"{c.get(C.PUBLISH_SENT, 0)} MonitorDiagnosis frames sent, "
          f"{c.rejected_total()} rejected")
    print(f"wrote {rrd} (open it: rerun {rrd}), {out / 'demo_report.png'}, "
          f"{out / 'events.jsonl'}")
    return 0


def add_command(sub: argparse._SubParsersAction[Any]) -> None:
    d = sub.add_parser("demo", help="virtual ECU + monitor in one process, no CAN hardware")
    d.add_argument("--out", default="out/demo", help="output directory")
    d.add_argument("--scenario", default="fault-outage-recovery",
                   help="built-in scenario name or TOML file")
    d.add_argument("--seed", type=int, default=1)
    add_rig_option(d)
    d.set_defaults(func=run_demo)
