"""The per-file engine: one bus log in, its diagnosis out, behind one small interface so
that another engine (a columnar one) can take the per-frame pipeline's place.

An engine is a callable `(path, setup, open_sinks, progress) -> EngineRun`:

* it reads the log at `path` and raises `LogError` (one line naming the file) if it cannot
  open it, or if it is empty or damaged before its first frame (`LogDamaged`); it calls
  `open_sinks()` only once the log has opened, so a log that cannot be opened creates or
  overwrites no output, and it closes what `open_sinks` returned, always;
* a log damaged or cut short after its first frame is not an exception: the frames before
  the damage go through the monitor as any others (their events and recording are kept),
  and the run's `failure` says what happened (`LogDamaged`'s line: where the damage
  starts, the frames read before it);
* nothing decoded is no success either: when a configured node (or, without --nodes,
  every node) got no estimated sample, `failure` is the line of
  `monitor.pipeline.counters.nothing_decoded` (the counts by outcome, the likely cause);
* it hands the sinks the pipeline's events (health transitions to the JSON lines, samples
  to the Rerun recording; an engine may feed a recording in whole columns instead);
* it calls `progress(n)` now and then with the frames read since its previous call;
* it returns an `EngineRun`: frames read, the counters (every frame's outcome, the names of
  `monitor.pipeline.counters`), every transition, each node's samples and worst NIS, and
  the log's first and last timestamps. The summary is built from these alone.

`per_frame_engine` is today's engine: `read_log` into `feed_log` through `MonitorPipeline`.

The options that configure the monitor travel to worker processes and cluster workers as
`ReplaySettings` (file names and numbers, nothing bound to a process) and are turned into
a `MonitorSetup` once per process (`monitor.setup.monitor_setup`). Every log gets a new
pipeline (alive counters, the estimators) and, with a SecOC key, a new decoder: no state
leaks from one log into the next, so a log's result does not depend on which worker ran it
or after which log.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Protocol, TypeVar

import can
import numpy as np
from numpy.typing import NDArray

from monitor.bus.logfile import LogDamaged, read_log
from monitor.pipeline import MonitorConfig, MonitorPipeline
from monitor.pipeline.counters import nothing_decoded
from monitor.pipeline.events import DiagnosisEvent, Sample, SampleColumns
from monitor.pipeline.feed import feed_log
from monitor.setup import MonitorSettings, MonitorSetup, monitor_setup
from monitor.sinks.base import FanOut, Sink

__all__ = ["ENGINES", "PROGRESS_EVERY", "EngineRun", "FrameProgress", "MonitorSetup",
           "NodeStats", "PerFileEngine", "ReplaySettings", "RunRecorder", "columnar_engine",
           "monitor_setup", "per_frame_engine"]

if TYPE_CHECKING:
    from monitor.columnar import FrameChunk

log = logging.getLogger("motor_monitor")

PROGRESS_EVERY = 8192
"""Frames between two progress reports of an engine."""

FrameProgress = Callable[[int], None]
"""Told the number of frames read since its previous call."""


class ReplaySettings(MonitorSettings):
    """The monitor options of `replay` (`monitor.runtime.argtypes.add_monitor_options`) that
    configure the monitor, as plain values a worker process rebuilds the monitor from
    (`monitor_setup`)."""


@dataclass
class NodeStats:
    """What a node did in one log: estimated samples and the largest normalised innovation
    squared (NaN before any sample)."""

    samples: int = 0
    worst_nis: float = math.nan


@dataclass
class EngineRun:
    """What an engine reports about one log; everything the summary needs."""

    frames: int
    counters: Mapping[str, int]
    transitions: Sequence[DiagnosisEvent]
    nodes: Mapping[int, NodeStats]
    t_first: float | None
    t_last: float | None
    feed_s: float = 0.0
    """Seconds spent on the frames (reading, decoding, estimating, the sinks), without
    setting up the monitor."""
    failure: str | None = None
    """Why the log is not a success though it was read: damage after its first frame
    (what was read before it is in the rest of the run), or nothing decoded; one line
    naming the log. None: replayed."""


class PerFileEngine(Protocol):
    """One log through the monitor (see the module docstring)."""

    def __call__(self, path: Path, setup: MonitorSetup, open_sinks: Callable[[], list[Sink]],
                 progress: FrameProgress | None = None) -> EngineRun: ...


@dataclass
class RunRecorder(Sink):
    """A sink that keeps what the summary needs of the per-frame pipeline's events."""

    transitions: list[DiagnosisEvent] = field(default_factory=list)
    nodes: dict[int, NodeStats] = field(default_factory=dict)

    def on_transition(self, event: DiagnosisEvent) -> None:
        self.transitions.append(event)

    def on_sample(self, sample: Sample) -> None:
        stats = self.nodes.get(sample.node)
        if stats is None:
            stats = self.nodes[sample.node] = NodeStats()
        stats.samples += 1
        nis = sample.nis
        if nis == nis and not nis <= stats.worst_nis:  # NaN never; the first sample always
            stats.worst_nis = nis

    def on_sample_columns(self, node: int, cols: SampleColumns) -> None:
        """The columnar replay's samples: the same statistics, a column at a time."""
        stats = self.nodes.get(node)
        if stats is None:
            stats = self.nodes[node] = NodeStats()
        stats.samples += len(cols.t)
        nis = cols.nis[~np.isnan(cols.nis)]
        if len(nis) and not float(nis.max()) <= stats.worst_nis:
            stats.worst_nis = float(nis.max())

    def on_input_columns(self, node: int, t: NDArray[np.float64], values: NDArray[np.float64],
                         index: NDArray[np.int64]) -> None:
        """The inputs' own-rate rows are not part of the summary."""


_T = TypeVar("_T")


class _Damage:
    """Ends a log's frames at damage found after its first frame, keeping the error: the
    frames before it are the run's (damage before the first frame is raised on, as a log
    that cannot be opened)."""

    def __init__(self) -> None:
        self.error: LogDamaged | None = None

    def guard(self, items: Iterable[_T]) -> Iterator[_T]:
        started = False
        try:
            for item in items:
                started = True
                yield item
        except LogDamaged as exc:
            if not started:
                raise
            self.error = exc


def _failure(path: Path, damage: _Damage, counters: Mapping[str, int],
             nodes: Mapping[int, NodeStats], cfg: MonitorConfig) -> str | None:
    """The run's `EngineRun.failure`: the damage, else nothing decoded, else None."""
    if damage.error is not None:
        return str(damage.error)
    line = nothing_decoded(counters, {n: s.samples for n, s in nodes.items()}, cfg.nodes)
    return None if line is None else f"{path}: {line}"


class _Span:
    """Passes frames through, noting the first and last timestamps and reporting progress."""

    def __init__(self, progress: FrameProgress | None) -> None:
        self.first: float | None = None
        self.last: float | None = None
        self.progress = progress

    def over(self, frames: Iterable[can.Message]) -> Iterator[can.Message]:
        report = self.progress
        pending = 0
        for msg in frames:
            if self.first is None:
                self.first = msg.timestamp
            self.last = msg.timestamp
            yield msg
            if report is not None:
                pending += 1
                if pending == PROGRESS_EVERY:
                    report(pending)
                    pending = 0
        if report is not None and pending:
            report(pending)


def per_frame_engine(path: Path, setup: MonitorSetup, open_sinks: Callable[[], list[Sink]],
                     progress: FrameProgress | None = None) -> EngineRun:
    """The log through `MonitorPipeline` frame by frame (`read_log`, `feed_log`)."""
    db = setup.decoder()
    frames = read_log(path)  # LogError here, before any output is opened
    recorder = RunRecorder()
    damage = _Damage()
    sink = FanOut([recorder, *open_sinks()])
    try:
        pipe = MonitorPipeline(db, setup.cfg, sink=sink)
        span = _Span(progress)
        t0 = time.perf_counter()
        n = feed_log(pipe, span.over(damage.guard(frames)))
    finally:
        sink.close()
    feed_s = time.perf_counter() - t0  # with the sinks' last flush, as a run would wait
    for node in pipe.nodes:
        recorder.nodes.setdefault(node, NodeStats())
    counters = dict(pipe.counters)
    return EngineRun(frames=n, counters=counters, transitions=recorder.transitions,
                     nodes=recorder.nodes, t_first=span.first, t_last=span.last, feed_s=feed_s,
                     failure=_failure(path, damage, counters, recorder.nodes, setup.cfg))


def columnar_engine(path: Path, setup: MonitorSetup, open_sinks: Callable[[], list[Sink]],
                    progress: FrameProgress | None = None) -> EngineRun:
    """The log through the columnar replay (`monitor.columnar`: chunks of frames decoded,
    checked and estimated as arrays; the same events and counters as `per_frame_engine`).
    A decoder it cannot take (SecOC keeps per-frame freshness state) goes to
    `per_frame_engine`, said once per process in the log."""
    # the columnar engine takes seconds to import (its compiled kernels): only a replay that
    # runs it pays them, never the live daemon, whose command line imports this module
    from monitor.columnar import columnar_obstacle, read_chunks, replay_chunks

    db = setup.decoder()
    why = columnar_obstacle(db, setup.cfg)
    if why is not None:
        _fallback_once(why)
        return per_frame_engine(path, setup, open_sinks, progress)
    chunks = read_chunks(path)  # LogReadError here, before any output is opened
    recorder = RunRecorder()
    damage = _Damage()
    sink = FanOut([recorder, *open_sinks()])
    first: list[float] = []
    last: list[float] = []

    def spanned() -> Iterator[FrameChunk]:
        for c in damage.guard(chunks):
            if len(c):
                if not first:
                    first.append(float(c.t[0]))
                last[:] = [float(c.t[-1])]
            yield c
            if progress is not None:
                progress(len(c))

    t0 = time.perf_counter()
    try:
        result = replay_chunks(spanned(), db, setup.cfg, sink)
    finally:
        sink.close()
    feed_s = time.perf_counter() - t0
    for node in result.nodes:
        recorder.nodes.setdefault(node, NodeStats())
    counters = dict(result.counters)
    return EngineRun(frames=result.frames, counters=counters,
                     transitions=recorder.transitions, nodes=recorder.nodes,
                     t_first=first[0] if first else None, t_last=last[0] if last else None,
                     feed_s=feed_s,
                     failure=_failure(path, damage, counters, recorder.nodes, setup.cfg))


@cache
def _fallback_once(why: str) -> None:
    log.warning("replay: %s; logs are replayed frame by frame", why)


ENGINES: dict[str, PerFileEngine] = {"columnar": columnar_engine, "per-frame": per_frame_engine}
"""The engines `replay --engine` chooses from (the first is the default)."""
