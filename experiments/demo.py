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
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import can
import numpy as np

from monitor.bus.codec import load_database
from monitor.diagnosis import DEFAULT_THRESHOLDS, HealthState
from monitor.pipeline import DiagnosisEvent, MonitorConfig, MonitorPipeline
from monitor.sinks.rerun import RerunSink, Sink
from sim_ecu.scenario import load_scenario
from experiments.scoring import match_transitions, true_classes

__all__ = ["RecordingSink", "add_command", "run_demo"]


class RecordingSink:
    """Forwards to another sink and keeps every sample, for the report."""

    def __init__(self, inner: Sink) -> None:
        self.inner = inner
        self.rows: list[tuple[float, float, float, float, float, int, float]] = []

    def add_sample(self, node: int, t: float, measured_current: float,
                   estimated_current: float, gamma_hat: float, rule_count: int, health: int,
                   nis: float, true_gamma: float | None = None) -> None:
        tg = math.nan if true_gamma is None else true_gamma
        self.rows.append((t, measured_current, estimated_current, gamma_hat, tg, health,
                          float(rule_count)))
        self.inner.add_sample(node, t, measured_current, estimated_current, gamma_hat,
                              rule_count, health, nis, true_gamma)

    def add_voltage(self, node: int, t: float, volts: float) -> None:
        self.inner.add_voltage(node, t, volts)

    def log_event(self, node: int, t: float, text: str, level: str = "INFO") -> None:
        self.inner.log_event(node, t, text, level)

    def log_counters(self, t: float, counters: Mapping[str, int]) -> None:
        self.inner.log_counters(t, counters)

    def set_thresholds(self, f1: float, f2: float) -> None:
        self.inner.set_thresholds(f1, f2)

    def maybe_flush(self, now_monotonic: float) -> None:
        self.inner.maybe_flush(now_monotonic)

    def flush(self) -> None:
        self.inner.flush()

    def close(self) -> None:
        self.inner.close()


def _report(rows: np.ndarray, path: Path, f1: float, f2: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
    a3.set_yticks([0, 1, 2, 3], [s.label for s in HealthState])
    a3.set_xlabel("time (s)")
    a3.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def run_demo(args: argparse.Namespace) -> int:
    from sim_ecu.ecu import VirtualECU

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    db = load_database()
    scenario = load_scenario(args.scenario)
    channel = f"motor-monitor-demo-{os.getpid()}"
    ecu_bus = can.Bus(interface="virtual", channel=channel)
    mon_bus = can.Bus(interface="virtual", channel=channel)
    rrd = out / "demo.rrd"
    cfg = MonitorConfig(nodes=(0,), thresholds=DEFAULT_THRESHOLDS)
    rec = RecordingSink(RerunSink(rrd_path=rrd, nodes=(0,), f1=cfg.thresholds.f1,
                                  f2=cfg.thresholds.f2))
    events: list[DiagnosisEvent] = []
    ev_fh = (out / "events.jsonl").open("w", encoding="utf-8")

    def on_event(ev: DiagnosisEvent) -> None:
        events.append(ev)
        ev_fh.write(ev.to_json() + "\n")
        print(f"  t = {ev.t - t_start:6.2f} s  node {ev.node}: {ev.previous} -> {ev.state}"
              f"  (gamma^ = {ev.gamma:.2f})", flush=True)

    pipe = MonitorPipeline(db, cfg, sink=rec, publish=lambda m: mon_bus.send(m),
                           on_event=on_event)
    ecu = VirtualECU(ecu_bus, db, 0, scenario, rate=100.0, seed=args.seed)
    stop = threading.Event()
    print(f"demo: virtual ECU node 0 runs '{scenario.name}' ({scenario.description}) for "
          f"{scenario.duration:.0f} s in real time; the monitor listens on the same bus")
    t_start = time.time()
    th = threading.Thread(target=ecu.run, args=(scenario.duration, stop), daemon=True)
    th.start()
    try:
        while th.is_alive():
            msg = mon_bus.recv(timeout=0.05)
            if msg is not None:
                pipe.feed(msg)
            pipe.tick(time.time())
            rec.maybe_flush(time.monotonic())
        while (msg := mon_bus.recv(timeout=0.1)) is not None:
            pipe.feed(msg)
    except KeyboardInterrupt:
        stop.set()
        th.join()
    finally:
        rec.close()
        ev_fh.close()
        ecu_bus.shutdown()
        mon_bus.shutdown()
    rows = np.array(rec.rows)
    if rows.size == 0:
        print("demo: no samples were estimated", file=sys.stderr)
        return 1
    _report(rows, out / "demo_report.png", cfg.thresholds.f1, cfg.thresholds.f2)
    t = rows[:, 0] - t_start
    truth = true_classes(np.nan_to_num(rows[:, 4]), cfg.thresholds)
    matches = match_transitions(t, truth, rows[:, 5].astype(np.int64))
    print("\ntrue transition                 at (s)   detected at (s)   delay (s)")
    for m in matches:
        det = "missed" if m.t_detected is None else f"{m.t_detected:8.2f}"
        dl = "" if m.delay is None else f"{m.delay:8.2f}"
        print(f"{m.before.label:>10s} -> {m.after.label:<10s} {m.t_true:9.2f}   {det:>14s}   {dl}")
    c = pipe.counters
    print(f"\n{c.get('frames/received', 0)} frames received, "
          f"{c.get('samples/estimated', 0)} samples estimated, "
          f"{c.get('publish/sent', 0)} MonitorDiagnosis frames sent, "
          f"{sum(v for k, v in c.items() if k.startswith('rejected/'))} rejected")
    print(f"wrote {rrd} (open it: rerun {rrd}), {out / 'demo_report.png'}, "
          f"{out / 'events.jsonl'}")
    return 0


def add_command(sub: argparse._SubParsersAction[Any]) -> None:
    d = sub.add_parser("demo", help="virtual ECU + monitor in one process, no CAN hardware")
    d.add_argument("--out", default="out/demo", help="output directory")
    d.add_argument("--scenario", default="fault-outage-recovery",
                   help="built-in scenario name or TOML file")
    d.add_argument("--seed", type=int, default=1)
    d.set_defaults(func=run_demo)
