"""`motor-monitor status FILE.prom [--watch S]`: the daemon's figures in the terminal, read
from the metrics file it writes (`run --metrics`), parsed with prometheus_client's own
text parser: per node its health, gamma^ and NIS; the bus load, frames, error frames, drops
and rejections; the busiest IDs with their period and jitter; the estimation latency."""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

from prometheus_client.parser import text_string_to_metric_families

from monitor.diagnosis import HealthState
from monitor.errors import UsageError

__all__ = ["add_command", "read_metrics", "render"]

Samples = dict[str, list[tuple[dict[str, str], float]]]


def read_metrics(path: Path) -> Samples:
    """Every sample of the file, by sample name."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise UsageError(f"{path}: cannot read metrics ({exc.strerror or exc}); is the "
                         "monitor running with --metrics?") from None
    out: Samples = {}
    try:
        for fam in text_string_to_metric_families(text):
            for s in fam.samples:
                out.setdefault(s.name, []).append((dict(s.labels), float(s.value)))
    except ValueError as exc:
        raise UsageError(f"{path}: not Prometheus text ({exc})") from None
    return out


def _one(m: Samples, name: str, default: float = math.nan) -> float:
    rows = m.get(name)
    return rows[0][1] if rows else default


def render(m: Samples, path: Path, age_s: float) -> str:
    p = "motor_monitor_"
    ev = {lab["name"]: v for lab, v in m.get(p + "events_total", [])}
    rejected = sum(v for k, v in ev.items() if k.startswith("rejected/"))
    lines = [
        f"{path} (written {age_s:.0f} s ago)",
        f"bus load {100 * _one(m, p + 'bus_load_ratio'):.1f} %, "
        f"{_one(m, p + 'bus_frames_total', ev.get('frames/received', 0)):.0f} frames, "
        f"{ev.get('bus/error_frames', 0):.0f} error frames, "
        f"{ev.get('bus/socket_drops', 0):.0f} kernel drops, {rejected:.0f} rejected, "
        f"{ev.get('e2e/lost_frames', 0):.0f} lost, "
        f"{ev.get('publish/sent', 0):.0f} diagnoses sent",
        "",
        f"{'node':>4s}  {'state':15s} {'gamma^':>7s} {'NIS':>7s} {'samples':>9s}",
    ]
    gamma = {lab["node"]: v for lab, v in m.get(p + "node_gamma", [])}
    nis = {lab["node"]: v for lab, v in m.get(p + "node_nis", [])}
    samples = {lab["node"]: v for lab, v in m.get(p + "node_samples_total", [])}
    for lab, v in sorted(m.get(p + "node_health_state", []), key=lambda r: int(r[0]["node"])):
        n = lab["node"]
        state = HealthState(int(v)).label
        lines.append(f"{n:>4s}  {state:15s} {gamma.get(n, math.nan):7.3f} "
                     f"{nis.get(n, math.nan):7.2f} {samples.get(n, 0):9.0f}")
    ids = sorted(m.get(p + "id_frames_total", []), key=lambda r: -r[1])[:8]
    if ids:
        period = {lab["id"]: v for lab, v in m.get(p + "id_period_seconds", [])}
        jitter = {lab["id"]: v for lab, v in m.get(p + "id_jitter_seconds", [])}
        lines += ["", f"{'id':>10s} {'frames':>9s} {'period ms':>10s} {'jitter ms':>10s}"]
        for lab, v in ids:
            i = lab["id"]
            lines.append(f"{i:>10s} {v:9.0f} {1e3 * period.get(i, math.nan):10.2f} "
                         f"{1e3 * jitter.get(i, math.nan):10.3f}")
    count = _one(m, p + "estimation_latency_seconds_count", 0.0)
    if count:
        mean = _one(m, p + "estimation_latency_seconds_sum") / count
        lines += ["", f"estimation latency: mean {1e3 * mean:.2f} ms over {count:.0f} samples"]
    return "\n".join(lines)


def _cmd_status(args: argparse.Namespace) -> int:
    path = Path(args.metrics)
    while True:
        m = read_metrics(path)
        age = time.time() - _one(m, "motor_monitor_last_write_timestamp_seconds", time.time())
        text = render(m, path, max(age, 0.0))
        if args.watch:
            sys.stdout.write("\x1b[H\x1b[2J" + text + "\n")
            sys.stdout.flush()
            time.sleep(args.watch)
        else:
            print(text)
            return 0


def add_command(sub: argparse._SubParsersAction[Any]) -> None:
    s = sub.add_parser("status", help="the running daemon's figures, from its metrics file")
    s.add_argument("metrics", metavar="FILE.prom", help="the file of run --metrics")
    s.add_argument("--watch", type=float, default=None, metavar="S",
                   help="redraw every S seconds, like top")
    s.set_defaults(func=_cmd_status)
