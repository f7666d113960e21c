"""A recorded bus through the per-frame pipeline: every frame fed in order, the timeouts
checked in bus time every `TICK_S`, as the live loop checks them in wall time. The replay
command, the archive engines and the columnar replay (whose `ticks` kernel is handed
`TICK_S`) all tick by this one rule."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from pathlib import Path

import can

from monitor.bus.logfile import read_log
from monitor.pipeline.core import MonitorPipeline

__all__ = ["TICK_S", "feed_log", "replay_frames"]

TICK_S = 0.05
"""Bus time between timeout checks, as in the live loop."""


def feed_log(pipe: MonitorPipeline, frames: Iterable[can.Message],
             on_tick: Callable[[float], None] | None = None) -> int:
    """Every frame into `pipe`, with its timeouts checked in bus time; returns the count.

    ``on_tick`` is called with the bus time of each check, after it: what else a loop does
    at that pace (a sink's ``maybe_flush`` on a simulated clock, say)."""
    last_tick = -math.inf
    n = 0
    for msg in frames:
        pipe.feed(msg)
        n += 1
        ts = msg.timestamp
        if ts - last_tick >= TICK_S:
            last_tick = ts
            pipe.tick(ts)
            if on_tick is not None:
                on_tick(ts)
    return n


def replay_frames(pipe: MonitorPipeline, path: Path) -> int:
    """`feed_log` of the capture at `path`."""
    return feed_log(pipe, read_log(path))
