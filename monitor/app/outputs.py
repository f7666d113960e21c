"""The sinks a command's options ask for: the Rerun recording (--rrd, --record-dir) or live
viewer (--connect), JSON lines of the events (--events), the log."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from monitor.errors import MonitorError, UsageError
from monitor.pipeline import MonitorConfig
from monitor.sinks.base import Sink
from monitor.sinks.jsonl import JsonLinesSink
from monitor.sinks.rerun import RerunSink
from monitor.sinks.rotation import RotatingRerunSink

__all__ = ["event_lines", "rerun_sink"]


def rerun_sink(args: argparse.Namespace, cfg: MonitorConfig) -> Sink | None:
    """Rotating files (--record-dir), one file (--rrd) and/or a live viewer (--connect), or
    None when none is asked for."""
    record_dir = getattr(args, "record_dir", None)
    if args.rrd and record_dir:
        raise UsageError("--rrd and --record-dir exclude each other (one file, or rotating files)")
    if not (args.rrd or args.connect or record_dir):
        return None
    if args.rrd:
        parent = Path(args.rrd).parent
        if not parent.is_dir():
            raise UsageError(f"--rrd: directory {parent} does not exist")
    common: dict[str, Any] = {"nodes": cfg.nodes or (), "f1": cfg.thresholds.f1,
                              "f2": cfg.thresholds.f2, "connect_url": args.connect}
    try:
        if record_dir:
            if not Path(record_dir).is_dir():
                raise UsageError(f"--record-dir: directory {record_dir} does not exist")
            return RotatingRerunSink(record_dir, max_bytes=int(args.rotate_mb * 2**20),
                                     max_age_s=args.rotate_minutes * 60.0, keep=args.keep,
                                     max_total_bytes=int(args.max_total_gb * 2**30), **common)
        return RerunSink(rrd_path=args.rrd, **common)
    except (ValueError, RuntimeError, OSError) as exc:
        raise MonitorError(f"cannot start the Rerun recording: {exc}") from None


def event_lines(path: str | None, *, to_stdout: bool) -> Sink | None:
    """JSON lines of the diagnosis events, appended to `path`, else to standard output if
    `to_stdout`, else none."""
    if path:
        return JsonLinesSink(open(path, "a", encoding="utf-8"), owned=True)
    return JsonLinesSink(sys.stdout) if to_stdout else None
