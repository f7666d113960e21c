"""`BacklogFeed`: the live daemon's frames into the monitor, whatever its socket held.

A receive that finds a few frames hands them to `MonitorPipeline.feed` one by one, so a
frame at low load reaches its diagnosis with nothing added; a receive that finds a backlog
(a daemon held up for a moment, a bus faster than the per-frame path, a small computer)
hands it to the `ColumnarEngine` in one call, on the same pipeline's state, at the
columnar engine's speed. Both give the same events, samples and counters for the same
frames (`tests/columnar/test_backlog.py`), so where the line falls changes only the speed.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import can

from monitor.columnar.chunk import chunk_from_messages
from monitor.columnar.decode import NotColumnar
from monitor.columnar.replay import ColumnarEngine
from monitor.pipeline import MonitorPipeline

__all__ = ["COLUMNAR_MIN_FRAMES", "BacklogFeed"]

log = logging.getLogger("motor_monitor")

COLUMNAR_MIN_FRAMES = 48
"""The fewest frames handed to the columnar engine in one call. On our bus
(`python -m tests.bench.backlog`) a chunk costs about 1 ms whatever its size (on a quiet
machine), a frame about 60 us on the per-frame path and 10 us in columns: the two break even
between 10 and 30 frames, and from about 50 on a chunk takes under half the per-frame
time."""


class BacklogFeed:
    """`feed(frames)`: frames one by one below `min_frames`, in one chunk from it.

    The timeouts are the caller's (`MonitorPipeline.tick`): the engine does not tick
    inside a chunk. A codec whose frames must go one by one (SecOC: `NotColumnar`) has every
    frame fed one by one; `obstacle` says why."""

    def __init__(self, pipe: MonitorPipeline, min_frames: int = COLUMNAR_MIN_FRAMES) -> None:
        self.pipe = pipe
        self.min_frames = max(1, min_frames)
        self.engine: ColumnarEngine | None = None
        self.obstacle: str | None = None
        try:
            self.engine = ColumnarEngine(pipe, ticks=False)
        except NotColumnar as exc:
            self.obstacle = str(exc)
        self.chunks = 0  # backlogs taken in one call, for the benchmark and the tests

    def feed(self, frames: Sequence[can.Message]) -> None:
        """Every frame of `frames` (in bus order) into the pipeline; never raises on what a
        frame holds."""
        engine = self.engine
        if engine is not None and len(frames) >= self.min_frames:
            try:
                chunk = chunk_from_messages(frames)
            except Exception as exc:  # a driver's odd object: the per-frame path counts it
                log.debug("backlog not in columns (%s): frame by frame", exc)
            else:
                engine.chunk(chunk)
                self.chunks += 1
                return
        feed = self.pipe.feed
        for msg in frames:
            feed(msg)
