"""`motor-monitor replay LOG`: a recorded bus (candump .log, Vector .asc or .blf), run
through the same pipeline as a live one, as fast as it goes. Diagnosis events go to
standard output as JSON lines (or to --events)."""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Iterable, Iterator
from contextlib import suppress
from pathlib import Path
from struct import error as StructError
from typing import Any

import can

from monitor.app import options, outputs
from monitor.errors import MonitorError
from monitor.pipeline import MonitorPipeline
from monitor.pipeline import counters as C
from monitor.sinks.base import FanOut, Sink
from monitor.sinks.log import LogSink

__all__ = ["LOG_SUFFIXES", "LogError", "add_command", "feed_log", "read_log", "replay_frames",
           "run_replay"]

LOG_SUFFIXES = (".log", ".asc", ".blf")
TICK_S = 0.05  # bus time between timeout checks, as in the live loop


class LogError(MonitorError):
    """A bus log that cannot be read (one line naming the file)."""


def read_log(path: Path) -> Iterator[can.Message]:
    """Frames of a candump .log, Vector .asc or .blf file, through python-can's readers.

    Not a generator itself: a bad path raises `LogError` here, before the caller opens
    any output (--rrd, --events) that an error must not create or overwrite.
    """
    if path.suffix.lower() not in LOG_SUFFIXES:
        raise LogError(f"{path}: unsupported log format (use {', '.join(LOG_SUFFIXES)})")
    if not path.is_file():
        raise LogError(f"{path}: no such file")
    try:
        reader = can.LogReader(str(path))
    except (OSError, ValueError) as exc:
        raise LogError(f"{path}: cannot read log ({exc})") from None
    return _frames(path, reader)


def _frames(path: Path, reader: can.io.generic.MessageReader) -> Iterator[can.Message]:
    try:
        yield from reader
    except (ValueError, IndexError, OSError, StructError) as exc:
        raise LogError(f"{path}: malformed log ({exc})") from None
    finally:
        with suppress(Exception):
            reader.stop()


def feed_log(pipe: MonitorPipeline, frames: Iterable[can.Message]) -> int:
    """Every frame into `pipe`, with its timeouts checked in bus time; returns the count."""
    last_tick = -math.inf
    n = 0
    for msg in frames:
        pipe.feed(msg)
        n += 1
        ts = msg.timestamp
        if ts - last_tick >= TICK_S:
            last_tick = ts
            pipe.tick(ts)
    return n


def replay_frames(pipe: MonitorPipeline, path: Path) -> int:
    """`feed_log` of the capture at `path`."""
    return feed_log(pipe, read_log(path))


def run_replay(args: argparse.Namespace) -> int:
    rig = options.rig(args)
    db = options.database(args, rig)
    cfg = options.monitor_config(args, rig)
    frames = read_log(Path(args.log))
    sinks: list[Sink] = [LogSink()]
    recording = outputs.rerun_sink(args, cfg)
    events = outputs.event_lines(args.events, to_stdout=True)
    sinks += [s for s in (recording, events) if s is not None]
    sink = FanOut(sinks)
    pipe = MonitorPipeline(db, cfg, sink=sink)
    t0 = time.perf_counter()
    try:
        n = feed_log(pipe, frames)
    finally:
        sink.close()
    el = time.perf_counter() - t0
    c = pipe.counters
    print(f"motor-monitor: replayed {n} frames in {el:.2f} s ({n / max(el, 1e-9):.0f} frames/s): "
          f"{c.get(C.SAMPLES_ESTIMATED, 0)} estimated, {c.rejected_total()} rejected",
          file=sys.stderr)
    return 0


def add_command(sub: argparse._SubParsersAction[Any]) -> None:
    p = sub.add_parser("replay", help="run a candump .log, .asc or .blf file as fast as possible")
    p.add_argument("log", help="log file")
    p.add_argument("--events", default=None, help="JSON lines to this file (default: stdout)")
    options.add_monitor_options(p)
    p.set_defaults(func=run_replay)
