"""Live state of the monitor, streamed to a Rerun viewer and/or recorded to an ``.rrd`` file.

The daemon feeds up to ~10,000 samples/s in total. A row-wise ``rr.log`` costs ~0.1 ms, so
every high-rate series goes through column batches: `RerunSink.add_sample` only stores the
values in preallocated per-node numpy buffers (float64, ``batch_size`` long, reused for the
whole run) and a full buffer, `RerunSink.flush`, or `RerunSink.maybe_flush` once
``flush_interval_s`` has elapsed, sends it with one ``RecordingStream.send_columns`` per entity.
Rerun copies the data when it builds its Arrow arrays, so reusing the buffers is safe. Rare
data (events, counters) is sent straight away; an event first flushes its node's buffers so it
never comes before samples that precede it in time.

Entity layout (``<n>`` is the CAN node id)::

    /motor/<n>/current/measured   Scalars   measured armature current
    /motor/<n>/current/estimated  Scalars   UKF output estimate
    /motor/<n>/gamma/estimate     Scalars   actuator loss of effectiveness gamma^
    /motor/<n>/gamma/true         Scalars   true gamma (only rows where it is given: sim/HIL)
    /motor/<n>/gamma/F1           Scalars   diagnosis threshold F1 (step line, see below)
    /motor/<n>/gamma/F2           Scalars   diagnosis threshold F2
    /motor/<n>/rules              Scalars   number of fuzzy rules of the estimator (step line)
    /motor/<n>/health             Scalars   health state 0..3 (step line)
    /motor/<n>/nis                Scalars   normalised innovation squared
    /motor/<n>/voltage            Scalars   supply voltage (own rate, own buffer)
    /motor/<n>/events             TextLog   state transitions etc.
    /monitor/counters/<name>      Scalars   daemon health counters (frames ok, rejected, ...);
                                            a ``/`` in a counter name nests the entity

The thresholds are sent with every gamma batch as two rows, at the first and the last time
stamp of the batch, with step interpolation, so each threshold line spans exactly the data
and a `RerunSink.set_thresholds` change shows up as a step where it took effect.

All data goes on one timeline, ``time``: a timestamp timeline of the bus time in float seconds
since the Unix epoch (CAN kernel time stamps), sent as ``rr.TimeColumn("time",
timestamp=...)``. Series names, colours and interpolation modes are logged once as static
``rr.SeriesLines``. A default blueprint (one tab per node, plus one for the counters) is sent
with the recording.

The sink is not thread-safe: call it from one thread (the daemon's main loop).

Durability. `RecordingStream.send_columns` bypasses the SDK's micro-batcher: the chunk goes
straight to the `FileSink`'s writer thread, which writes every message (16-byte header and
payload) with one unbuffered ``write(2)``, about a millisecond later. Data in the kernel's page
cache survives a SIGKILL of the process (not a power cut: nothing calls ``fsync``). So the only
delay is this sink's own buffering: `RerunSink.maybe_flush` sends everything once
``flush_interval_s`` (default `DEFAULT_FLUSH_INTERVAL_S` = 0.1 s) has passed, so a SIGKILL
loses at most ``flush_interval_s`` plus the period of the ``maybe_flush`` calls (0.05 s in the
daemon's loop) plus ~1 ms. The rare row-wise ``log`` calls (static series styles) do go through
the batcher: `RerunSink.flush` pushes it (``flush(timeout_sec=0)``: started, not waited for),
and its tick is set to 0.05 s explicitly, so ``RERUN_FLUSH_TICK_SECS`` in the environment
cannot hold them back. `RerunSink.close` writes the ``.rrd`` footer (SIGTERM/SIGINT in the
daemon), and ``rerun rrd verify`` passes. A killed process leaves a file without footer and,
if the kill hit a ``write``, with a torn last message: the SDK's streaming decoder reads it as
it is (``rerun rrd verify --check-footers false``, ``rerun rrd print``, the viewer);
``rerun rrd optimize FILE -o NEW`` writes a compacted copy with a footer; `salvage_rrd` cuts the
torn message off in place, for strict readers (``rerun.chunk.RrdReader`` refuses the whole file
otherwise).

The price of flushing every 0.1 s is small chunks: each costs ~1 kB of Arrow framing in the
file (a 10-row chunk of one scalar ~1.1 kB, a 1000-row one ~10 kB), and an entry in the footer
manifest. ``rerun rrd optimize`` compacts a finished file (several times fewer chunks).

Week-long runs: `RotatingRerunSink` writes a directory of ``.rrd`` files; when the current one
exceeds a size or an age it is finished (footer) and recording goes on into a new one, with the
same `RecordingStream` and a new `FileSink`; the oldest files beyond a count or a total size are
deleted. The footer's chunk manifest, which the SDK keeps in memory while a file is open, is
freed at each rotation: memory and disk stay bounded however long the daemon runs.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import re
import struct
import time
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import Final, Protocol, Self, runtime_checkable

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import rerun_bindings
from numpy.typing import NDArray

__all__ = [
    "DEFAULT_FLUSH_INTERVAL_S",
    "NullSink",
    "RerunSink",
    "RotatingRerunSink",
    "Sink",
    "default_blueprint",
    "salvage_rrd",
]

_log = logging.getLogger(__name__)

Array = NDArray[np.float64]
Color = tuple[int, int, int]

TIMELINE: Final = "time"

DEFAULT_FLUSH_INTERVAL_S: Final = 0.1
"""Buffered samples reach the file at most this long after they were added (plus the period of
the `maybe_flush` calls and ~1 ms of writing)."""

_BATCHER_TICK_S: Final = 0.05

_LEVELS: Final[Mapping[str, str]] = {
    "CRITICAL": "CRITICAL",
    "FATAL": "CRITICAL",
    "ERROR": "ERROR",
    "WARN": "WARN",
    "WARNING": "WARN",
    "INFO": "INFO",
    "DEBUG": "DEBUG",
    "TRACE": "TRACE",
}

_STEP: Final = rr.components.InterpolationMode.StepAfter

# (entity suffix, legend name, colour, line width, stepped)
_STYLES: Final[tuple[tuple[str, str, Color, float, bool], ...]] = (
    ("current/measured", "measured current", (120, 144, 156), 1.0, False),
    ("current/estimated", "estimated current", (255, 127, 14), 1.5, False),
    ("gamma/estimate", "gamma^ (estimate)", (31, 119, 180), 2.0, False),
    ("gamma/true", "gamma (true)", (44, 160, 44), 1.5, False),
    ("gamma/F1", "F1", (230, 171, 2), 1.0, True),
    ("gamma/F2", "F2", (214, 39, 40), 1.0, True),
    ("rules", "fuzzy rules", (148, 103, 189), 1.5, True),
    ("health", "health state (0..3)", (23, 190, 207), 2.0, True),
    ("nis", "NIS", (127, 127, 127), 1.0, False),
    ("voltage", "supply voltage", (188, 189, 34), 1.0, False),
)
_COUNTER_COLOR: Final[Color] = (140, 86, 75)


@runtime_checkable
class Sink(Protocol):
    """What the daemon needs from a live-state sink (`RerunSink` or `NullSink`)."""

    def add_sample(
        self,
        node: int,
        t: float,
        measured_current: float,
        estimated_current: float,
        gamma_hat: float,
        rule_count: int,
        health: int,
        nis: float,
        true_gamma: float | None = None,
    ) -> None: ...

    def add_voltage(self, node: int, t: float, volts: float) -> None: ...

    def log_event(self, node: int, t: float, text: str, level: str = "INFO") -> None: ...

    def log_counters(self, t: float, counters: Mapping[str, int]) -> None: ...

    def set_thresholds(self, f1: float, f2: float) -> None: ...

    def maybe_flush(self, now_monotonic: float) -> None: ...

    def flush(self) -> None: ...

    def close(self) -> None: ...


class NullSink:
    """A sink that drops everything (runs without Rerun)."""

    def add_sample(
        self,
        node: int,
        t: float,
        measured_current: float,
        estimated_current: float,
        gamma_hat: float,
        rule_count: int,
        health: int,
        nis: float,
        true_gamma: float | None = None,
    ) -> None:
        pass

    def add_voltage(self, node: int, t: float, volts: float) -> None:
        pass

    def log_event(self, node: int, t: float, text: str, level: str = "INFO") -> None:
        pass

    def log_counters(self, t: float, counters: Mapping[str, int]) -> None:
        pass

    def set_thresholds(self, f1: float, f2: float) -> None:
        pass

    def maybe_flush(self, now_monotonic: float) -> None:
        pass

    def flush(self) -> None:
        pass

    def close(self) -> None:
        pass

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


class _Node:
    """Preallocated column buffers and entity paths of one node."""

    __slots__ = (
        "estimated",
        "gamma",
        "health",
        "measured",
        "n",
        "nis",
        "nv",
        "path",
        "rules",
        "t",
        "true_gamma",
        "true_styled",
        "tv",
        "volts",
    )

    def __init__(self, node: int, batch_size: int) -> None:
        self.path: dict[str, str] = {s[0]: f"/motor/{node}/{s[0]}" for s in _STYLES}
        self.path["events"] = f"/motor/{node}/events"
        self.n = 0
        self.t: Array = np.zeros(batch_size)
        self.measured: Array = np.zeros(batch_size)
        self.estimated: Array = np.zeros(batch_size)
        self.gamma: Array = np.zeros(batch_size)
        self.true_gamma: Array = np.zeros(batch_size)
        self.rules: Array = np.zeros(batch_size)
        self.health: Array = np.zeros(batch_size)
        self.nis: Array = np.zeros(batch_size)
        self.true_styled = False
        self.nv = 0
        self.tv: Array = np.zeros(batch_size)
        self.volts: Array = np.zeros(batch_size)


def _counter_path(name: str) -> str:
    parts = [rr.escape_entity_path_part(p) for p in name.split("/") if p]
    if not parts:
        raise ValueError(f"invalid counter name {name!r}")
    return "/monitor/counters/" + "/".join(parts)


def _series_style(name: str, color: Color, width: float, stepped: bool) -> rr.SeriesLines:
    return rr.SeriesLines(
        names=name,
        colors=[color],
        widths=width,
        interpolation_mode=_STEP if stepped else None,
    )


BUS_EVENTS_PATH = "/monitor/events"


def default_blueprint(nodes: Sequence[int]) -> rrb.Blueprint:
    """One tab per node (current, gamma^ vs thresholds, rules, health, NIS, voltage, events)
    and one tab with the daemon counters."""
    tabs: list[rrb.Container | rrb.View] = []
    for n in nodes:
        m = f"/motor/{n}"
        tabs.append(
            rrb.Vertical(
                rrb.TimeSeriesView(origin=f"{m}/current", name="measured vs estimated current"),
                rrb.TimeSeriesView(origin=f"{m}/gamma", name="gamma^ vs thresholds"),
                rrb.Horizontal(
                    rrb.TimeSeriesView(origin=f"{m}/rules", name="rule count"),
                    rrb.TimeSeriesView(
                        origin=f"{m}/health",
                        name="health state",
                        axis_y=rrb.ScalarAxis(range=(-0.25, 3.25), zoom_lock=True),
                    ),
                    rrb.TimeSeriesView(
                        origin=f"{m}/nis",
                        name="NIS",
                        # chi-square(1): a fitting model stays mostly below 4; a start-up
                        # spike of 1000 would otherwise flatten the whole plot
                        axis_y=rrb.ScalarAxis(range=(0.0, 20.0), zoom_lock=False),
                    ),
                    rrb.TimeSeriesView(origin=f"{m}/voltage", name="supply voltage"),
                ),
                rrb.TextLogView(origin=f"{m}/events", name="events"),
                row_shares=[3.0, 3.0, 2.0, 2.0],
                name=f"motor {n}",
            )
        )
    tabs.append(
        rrb.Vertical(
            rrb.TimeSeriesView(origin="/monitor/counters", name="daemon counters"),
            rrb.TextLogView(origin=BUS_EVENTS_PATH, name="bus events"),
            row_shares=[3.0, 1.0],
            name="daemon",
        )
    )
    return rrb.Blueprint(rrb.Tabs(*tabs, active_tab=0), collapse_panels=False)


class _BlueprintSender:
    """Sends blueprints to a recording through one long-lived blueprint stream.

    `RecordingStream.send_blueprint` creates a new blueprint `RecordingStream` per call, and the
    Python SDK never frees a stream's threads (rerun-io/rerun#2116): each call costs two threads
    and about 1 MB for the rest of the process, which a rotation per hour turns into a leak. This
    keeps one blueprint stream and gives it a fresh memory sink per blueprint -- the steps of
    ``rerun.sinks.send_blueprint`` in SDK 0.41, whose internals it uses; if they are missing
    (another SDK version) it falls back to the public call.
    """

    def __init__(self, rec: rr.RecordingStream, application_id: str) -> None:
        self._rec = rec
        self._stream: rr.RecordingStream | None = None
        try:
            self._stream = rr.RecordingStream._from_native(
                rerun_bindings.new_blueprint(
                    application_id=application_id,
                    make_default=False,
                    make_thread_default=False,
                    default_enabled=True,
                )
            )
        except (AttributeError, TypeError) as exc:  # pragma: no cover - other SDK versions
            _log.debug("rerun sink: public send_blueprint (%s)", exc)

    def send(self, blueprint: rrb.Blueprint) -> None:
        stream = self._stream
        if stream is not None:
            try:
                memory = stream.memory_recording()
                stream.set_time("blueprint", sequence=0)
                blueprint._log_to_stream(stream)
                rerun_bindings.send_blueprint(
                    memory.storage, True, True, recording=self._rec.to_native()
                )
                return
            except (AttributeError, TypeError) as exc:  # pragma: no cover - other SDK versions
                _log.debug("rerun sink: public send_blueprint (%s)", exc)
                self._stream = None
        self._rec.send_blueprint(blueprint, make_active=True, make_default=True)


class RerunSink:
    """Column-batched Rerun sink; see the module docstring for the entity layout.

    ``rrd_path`` records to a file, ``connect_url`` (``rerun+http://HOST:PORT/proxy``) streams
    to a viewer or gRPC proxy; both may be given at once. ``write_footer=False`` skips the
    ``.rrd`` footer, whose chunk manifest the SDK otherwise keeps in memory for the whole run
    (grows with the number of chunks; ``rerun rrd optimize`` can add a footer afterwards;
    `RotatingRerunSink` bounds it instead). ``flush_interval_s`` bounds how long a sample stays
    in the buffers when `maybe_flush` is called often enough (see the module docstring).
    """

    def __init__(
        self,
        *,
        rrd_path: str | Path | None = None,
        connect_url: str | None = None,
        application_id: str = "motor-monitor",
        recording_id: str | None = None,
        nodes: Sequence[int] = (0,),
        f1: float = 0.15,
        f2: float = 0.85,
        batch_size: int = 2048,
        flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
        write_footer: bool = True,
    ) -> None:
        if rrd_path is None and connect_url is None:
            raise ValueError("RerunSink needs rrd_path and/or connect_url (use NullSink for none)")
        if batch_size < 1:
            raise ValueError("batch_size must be >= 1")
        if not flush_interval_s >= 0.0:
            raise ValueError("flush_interval_s must be >= 0")
        self._batch_size = int(batch_size)
        self._flush_interval_s = float(flush_interval_s)
        self._f1 = float(f1)
        self._f2 = float(f2)
        self._closed = False
        self._nodes: dict[int, _Node] = {}
        self._counters: dict[str, str] = {}
        self._counter_rows: list[tuple[float, dict[str, int]]] = []
        self._last_flush = time.monotonic()
        self.rrd_path = None if rrd_path is None else Path(rrd_path)
        self._connect_url = connect_url
        self._write_footer = bool(write_footer)
        self._start_ns = time.time_ns()

        # An explicit batcher configuration, so that RERUN_FLUSH_* variables of the environment
        # cannot hold the (rare) row-wise `log` calls back; `send_columns` bypasses the batcher.
        self._rec = rr.RecordingStream(
            application_id,
            recording_id=recording_id,
            batcher_config=rr.ChunkBatcherConfig(flush_tick=_BATCHER_TICK_S),
        )
        sinks: list[rr.FileSink | rr.GrpcSink] = []
        if self.rrd_path is not None:
            sinks.append(rr.FileSink(self.rrd_path, write_footer=write_footer))
        if connect_url is not None:
            sinks.append(rr.GrpcSink(connect_url))
        self._rec.set_sinks(*sinks)
        for node in dict.fromkeys(int(n) for n in nodes):
            self._add_node(node)
        self._blueprints = _BlueprintSender(self._rec, application_id)
        self._send_blueprint()

    # -- hot path -------------------------------------------------------------------------

    def add_sample(
        self,
        node: int,
        t: float,
        measured_current: float,
        estimated_current: float,
        gamma_hat: float,
        rule_count: int,
        health: int,
        nis: float,
        true_gamma: float | None = None,
    ) -> None:
        """Buffer one estimator sample of ``node`` at bus time ``t`` (epoch seconds)."""
        if self._closed:
            return
        st = self._nodes.get(node)
        if st is None:
            st = self._new_node(node)
        i = st.n
        st.t[i] = t
        st.measured[i] = measured_current
        st.estimated[i] = estimated_current
        st.gamma[i] = gamma_hat
        st.true_gamma[i] = math.nan if true_gamma is None else true_gamma
        st.rules[i] = rule_count
        st.health[i] = health
        st.nis[i] = nis
        i += 1
        st.n = i
        if i == self._batch_size:
            self._flush_samples(st)

    def add_voltage(self, node: int, t: float, volts: float) -> None:
        """Buffer one supply-voltage reading of ``node``."""
        if self._closed:
            return
        st = self._nodes.get(node)
        if st is None:
            st = self._new_node(node)
        i = st.nv
        st.tv[i] = t
        st.volts[i] = volts
        i += 1
        st.nv = i
        if i == self._batch_size:
            self._flush_voltage(st)

    # -- rare data --------------------------------------------------------------------------

    def log_event(self, node: int, t: float, text: str, level: str = "INFO") -> None:
        """Log a text event (state transition...) for ``node``, after its buffered samples.

        A negative node is the bus itself (error frames, interface outages): the event goes
        to ``/monitor/events``, shown beside the daemon counters.
        """
        if self._closed:
            return
        if node < 0:
            path = BUS_EVENTS_PATH
        else:
            st = self._nodes.get(node)
            if st is None:
                st = self._new_node(node)
            self._flush_samples(st)
            self._flush_voltage(st)
            path = st.path["events"]
        lvl = _LEVELS.get(level.upper(), level)
        self._rec.send_columns(
            path,
            indexes=[rr.TimeColumn(TIMELINE, timestamp=np.array([t], dtype=np.float64))],
            columns=rr.TextLog.columns(text=[text], level=[lvl]),
        )

    def log_counters(self, t: float, counters: Mapping[str, int]) -> None:
        """Buffer the daemon's health counters, scalars under ``/monitor/counters/<name>``.

        Rows are sent as columns with the next flush: one chunk per counter per flush,
        not one per call, so a long run does not pile up tiny chunks.
        """
        if self._closed or not counters:
            return
        self._counter_rows.append((t, dict(counters)))
        if len(self._counter_rows) >= self._batch_size:
            self._flush_counters()

    def _flush_counters(self) -> None:
        rows = self._counter_rows
        if not rows:
            return
        self._counter_rows = []
        names = dict.fromkeys(name for _, c in rows for name in c)
        for name in names:
            path = self._counters.get(name)
            if path is None:
                path = _counter_path(name)
                self._counters[name] = path
                self._rec.log(
                    path, _series_style(name, _COUNTER_COLOR, 1.5, stepped=True), static=True
                )
            ts = np.array([t for t, c in rows if name in c], dtype=np.float64)
            vs = np.array([c[name] for _, c in rows if name in c], dtype=np.float64)
            self._rec.send_columns(
                path,
                indexes=[rr.TimeColumn(TIMELINE, timestamp=ts)],
                columns=rr.Scalars.columns(scalars=vs),
            )

    def set_thresholds(self, f1: float, f2: float) -> None:
        """Change the diagnosis thresholds; buffered samples keep the old ones."""
        if not self._closed:
            for st in self._nodes.values():
                self._flush_samples(st)
        self._f1 = float(f1)
        self._f2 = float(f2)

    # -- flushing ---------------------------------------------------------------------------

    def maybe_flush(self, now_monotonic: float) -> None:
        """Flush everything if ``flush_interval_s`` has passed since the last flush."""
        if now_monotonic - self._last_flush >= self._flush_interval_s:
            self.flush()
            self._last_flush = now_monotonic

    def flush(self) -> None:
        """Send all buffered samples (non-blocking hand-over to the Rerun sinks)."""
        self._last_flush = time.monotonic()
        if self._closed:
            return
        for st in self._nodes.values():
            self._flush_samples(st)
            self._flush_voltage(st)
        self._flush_counters()
        try:
            self._rec.flush(timeout_sec=0.0)  # start pushing to the sinks, don't wait
        except RuntimeError as exc:  # e.g. the gRPC viewer is unreachable
            _log.warning("rerun flush: %s", exc)

    def close(self, timeout_s: float = 10.0) -> None:
        """Flush, then finalise the sinks (writes the ``.rrd`` footer). Idempotent."""
        if self._closed:
            return
        self.flush()
        self._closed = True
        try:
            self._rec.flush(timeout_sec=timeout_s)
        except RuntimeError as exc:
            _log.warning("rerun flush on close: %s", exc)
        # Drops the sinks: the FileSink writes its footer and closes the file, the gRPC client
        # says goodbye (or, if it never connected, gives up after ~5 s).
        self._rec.disconnect()

    def switch_file(self, rrd_path: str | Path, timeout_s: float = 10.0) -> None:
        """Finish the current ``.rrd`` file and go on recording into ``rrd_path``, with the same
        `RecordingStream` (same recording id, no new SDK threads).

        The buffers are flushed into the current file; replacing its `FileSink` (``set_sinks``)
        makes the SDK send it everything pending, write the footer and close it before the call
        returns, and frees the sink's chunk manifest. The new file is self-contained: the SDK
        writes the store info, this sends the recording start time, the blueprint and the static
        series styles again; the thresholds go with the next gamma batch as always. If the new
        file cannot be created (`RuntimeError` from the SDK, e.g. its directory is gone), the
        current file stays open and recording goes on into it. Only for a sink without
        ``connect_url`` (its gRPC connection would be replaced too).
        """
        if self._closed:
            raise RuntimeError("the sink is closed")
        if self.rrd_path is None or self._connect_url is not None:
            raise ValueError("switch_file needs a sink with rrd_path and without connect_url")
        self.flush()
        try:
            self._rec.flush(timeout_sec=timeout_s)
        except RuntimeError as exc:
            _log.warning("rerun flush before switching files: %s", exc)
        path = Path(rrd_path)
        self._rec.set_sinks(rr.FileSink(path, write_footer=self._write_footer))
        self.rrd_path = path
        self._rec.send_recording_start_time_nanos(self._start_ns)
        self._counters.clear()
        for st in self._nodes.values():
            st.true_styled = False
            self._style_node(st)
        self._send_blueprint()

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def nodes(self) -> tuple[int, ...]:
        """The nodes with a tab in the blueprint (announced or seen), in order of arrival."""
        return tuple(self._nodes)

    @property
    def recording(self) -> rr.RecordingStream:
        """The underlying explicit (non-global) recording stream."""
        return self._rec

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- internals --------------------------------------------------------------------------

    def _add_node(self, node: int) -> _Node:
        st = _Node(node, self._batch_size)
        self._nodes[node] = st
        self._style_node(st)
        return st

    def _style_node(self, st: _Node) -> None:
        for suffix, *_ in _STYLES:
            if suffix != "gamma/true":  # styled when the first true gamma arrives
                self._style(st.path[suffix], suffix)

    def _style(self, path: str, suffix: str) -> None:
        _, name, color, width, stepped = next(s for s in _STYLES if s[0] == suffix)
        self._rec.log(path, _series_style(name, color, width, stepped), static=True)

    def _new_node(self, node: int) -> _Node:
        """A node not announced in ``nodes``: add it and resend the blueprint."""
        _log.info("rerun sink: new node %d", node)
        st = self._add_node(node)
        self._send_blueprint()
        return st

    def _send_blueprint(self) -> None:
        self._blueprints.send(default_blueprint(sorted(self._nodes)))

    def _flush_samples(self, st: _Node) -> None:
        n = st.n
        if n == 0:
            return
        st.n = 0
        send = self._rec.send_columns
        path = st.path
        t = st.t[:n]
        index = [rr.TimeColumn(TIMELINE, timestamp=t)]
        scalars = rr.Scalars.columns
        send(path["current/measured"], indexes=index, columns=scalars(scalars=st.measured[:n]))
        send(path["current/estimated"], indexes=index, columns=scalars(scalars=st.estimated[:n]))
        send(path["gamma/estimate"], indexes=index, columns=scalars(scalars=st.gamma[:n]))
        true_gamma = st.true_gamma[:n]
        given = ~np.isnan(true_gamma)
        if not st.true_styled and given.any():
            st.true_styled = True
            self._style(path["gamma/true"], "gamma/true")
        if given.all():
            send(path["gamma/true"], indexes=index, columns=scalars(scalars=true_gamma))
        elif given.any():
            send(
                path["gamma/true"],
                indexes=[rr.TimeColumn(TIMELINE, timestamp=t[given])],
                columns=scalars(scalars=true_gamma[given]),
            )
        ends = t[[0, n - 1]] if n > 1 else t[:1].copy()
        ends_index = [rr.TimeColumn(TIMELINE, timestamp=ends)]
        k = len(ends)
        send(path["gamma/F1"], indexes=ends_index, columns=scalars(scalars=np.full(k, self._f1)))
        send(path["gamma/F2"], indexes=ends_index, columns=scalars(scalars=np.full(k, self._f2)))
        send(path["rules"], indexes=index, columns=scalars(scalars=st.rules[:n]))
        send(path["health"], indexes=index, columns=scalars(scalars=st.health[:n]))
        send(path["nis"], indexes=index, columns=scalars(scalars=st.nis[:n]))

    def _flush_voltage(self, st: _Node) -> None:
        n = st.nv
        if n == 0:
            return
        st.nv = 0
        self._rec.send_columns(
            st.path["voltage"],
            indexes=[rr.TimeColumn(TIMELINE, timestamp=st.tv[:n])],
            columns=rr.Scalars.columns(scalars=st.volts[:n]),
        )


# -- crash recovery ---------------------------------------------------------------------------

_RRD_MAGIC: Final = b"RRF2"
_RRD_FILE_HEADER: Final = 12  # magic, SDK version (4 bytes), encoding options (4 bytes)
_RRD_MSG_HEADER: Final = struct.Struct("<QQ")  # message kind, payload length
_RRD_KIND_END: Final = 0  # end of stream: the footer payload and a 32-byte trailer follow
_RRD_KINDS: Final = frozenset({1, 2, 3})  # SetStoreInfo, ArrowMsg, BlueprintActivationCommand
_RRD_TRAILER: Final = 32


def salvage_rrd(path: str | Path) -> int:
    """Cut a torn last message (or a torn footer) off an ``.rrd`` file whose writer was killed;
    return the number of bytes removed (0 for an intact file, with or without footer).

    A killed writer leaves no footer, and if the kill hit a ``write(2)``, a partial last
    message, for which strict readers (``rerun.chunk.RrdReader``) refuse the whole file while
    ``rerun rrd verify --check-footers false`` and the viewer read up to it. This walks the
    message framing of the RRD stream (Rerun 0.41: the 12-byte ``RRF2`` file header, then
    messages of a 16-byte header -- kind and payload length, little-endian u64 -- and the
    payload; kind 0 carries the footer) and truncates the file after the last complete
    message. Only the 16-byte headers are read. Raises `ValueError` for a file that is not an
    RRD stream (nothing is changed). Never call it on a file that a live process is writing.
    """
    p = Path(path)
    with p.open("r+b") as fh:
        size = os.fstat(fh.fileno()).st_size
        head = fh.read(_RRD_FILE_HEADER)
        if head[:4] != _RRD_MAGIC[: len(head[:4])]:
            raise ValueError(f"{p}: not an RRD file")
        if len(head) < _RRD_FILE_HEADER:
            return 0  # killed before the first message: nothing to salvage
        offset = _RRD_FILE_HEADER
        while offset < size:
            fh.seek(offset)
            raw = fh.read(_RRD_MSG_HEADER.size)
            if len(raw) < _RRD_MSG_HEADER.size:
                break  # torn message header
            kind, length = _RRD_MSG_HEADER.unpack(raw)
            end = offset + _RRD_MSG_HEADER.size + length
            if kind == _RRD_KIND_END:
                if end + _RRD_TRAILER <= size:
                    return 0  # complete footer
                break  # torn footer: the file is complete without it
            if kind not in _RRD_KINDS:
                raise ValueError(f"{p}: unknown RRD message kind {kind} at byte {offset}")
            if end > size:
                break  # torn payload
            offset = end
        else:
            return 0  # ends on a message boundary
        fh.truncate(offset)
        return size - offset


# -- rotation ---------------------------------------------------------------------------------

_PREFIX_RE: Final = re.compile(r"[A-Za-z0-9_.-]+")
_RETRY_MAX_S: Final = 60.0


class RotatingRerunSink:
    """A `Sink` that records into a directory of ``.rrd`` files, rotated by size and age.

    Files are named ``<prefix>-YYYYmmddTHHMMSS-NNNN.rrd``: the UTC time the file was opened and
    a sequence number (one more than the highest in the directory at start, then +1 per file),
    so names sort chronologically. After every flush (`flush`, or `maybe_flush` once
    ``flush_interval_s`` has passed) the current file is rotated when it has reached
    ``max_bytes`` (one ``os.stat``) or is ``max_age_s`` old: `RerunSink.switch_file` flushes
    the buffers into it, the SDK writes its footer and closes it (``rerun rrd verify`` passes
    on every rotated file) and recording goes on into the next file. Every sample goes to
    exactly one file (no gap, no duplicate at a boundary). Each file is self-contained: store
    info, recording start time, blueprint (every node seen so far), static series styles, and
    the current thresholds with its first gamma batch.

    Retention, applied whenever a file is opened, counts every file of this pattern in the
    directory (earlier runs too) and never deletes the one being written: the oldest are
    deleted while there are more than ``keep`` files (the current one included), and while the
    closed ones total more than ``max_total_bytes - max_bytes`` (the room the current file may
    take), so the directory stays within ``max_total_bytes``. A file ends up larger than
    ``max_bytes`` by what was sent after the size check saw it reached (one flush, plus what the
    SDK's writer thread had not written yet) and its footer (~50-100 kB plus ~35 bytes a chunk).
    The defaults (64 MiB, 1 h, 48 files) bound the directory to ~3 GiB.

    Sizing: at 100 Hz per node and a flush every 0.1 s, a node makes ~90 chunks/s of ~1 kB,
    ~0.35 GB/h; the SDK keeps ~0.3-0.45 kB of footer manifest in memory per chunk of the open
    file (measured), which without rotation would grow by ~20 GB per node and week.

    Memory: one `RecordingStream` serves the whole run (the Python SDK never frees a
    `RecordingStream`'s threads, so a new one per file would leak them); only its `FileSink` is
    replaced at each rotation, and with it the footer's chunk manifest that the SDK keeps while
    a file is open. So memory is bounded by ``max_bytes``/``max_age_s`` however long the run.

    All files of a run share its recording id (``recording_id``, or a random one): opened
    together (``rerun DIR/*.rrd``) they form one continuous recording. ``connect_url`` streams
    to a viewer/gRPC proxy through a second `RerunSink` that lives for the whole run and is
    never rotated (one connection; a gRPC sink keeps no manifest), with the same recording id
    -- so do not load the files into the viewer that received the live stream: the rows would
    show twice.

    If the next file cannot be created (disk full, directory removed), the error is logged and
    recording goes on into the current file; the rotation is retried after 1 s, then with
    doubling back-off up to a minute. One sink per directory: retention deletes files that
    another writer might be using.
    """

    def __init__(
        self,
        directory: str | Path,
        *,
        max_bytes: int | None = 64 * 2**20,
        max_age_s: float | None = 3600.0,
        keep: int | None = 48,
        max_total_bytes: int | None = None,
        prefix: str = "monitor",
        connect_url: str | None = None,
        application_id: str = "motor-monitor",
        recording_id: str | None = None,
        nodes: Sequence[int] = (0,),
        f1: float = 0.15,
        f2: float = 0.85,
        batch_size: int = 2048,
        flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
    ) -> None:
        if max_bytes is not None and max_bytes < 1:
            raise ValueError("max_bytes must be >= 1 (or None)")
        if max_age_s is not None and not max_age_s > 0:
            raise ValueError("max_age_s must be > 0 (or None)")
        if keep is not None and keep < 1:
            raise ValueError("keep must be >= 1 (or None)")
        if max_total_bytes is not None and (
            max_total_bytes < 1 or (max_bytes is not None and max_total_bytes < max_bytes)
        ):
            raise ValueError("max_total_bytes must be >= max_bytes (or None)")
        if not _PREFIX_RE.fullmatch(prefix):
            raise ValueError(f"prefix must match [A-Za-z0-9_.-]+: {prefix!r}")
        self.directory = Path(directory)
        self.max_bytes = max_bytes
        self.max_age_s = None if max_age_s is None else float(max_age_s)
        self.keep = keep
        self.max_total_bytes = max_total_bytes
        self.prefix = prefix
        self.recording_id = recording_id if recording_id is not None else uuid.uuid4().hex
        self.rotations = 0
        """Files closed by rotation so far."""
        self._pattern = re.compile(re.escape(prefix) + r"-(\d{8}T\d{6})-(\d{4,})\.rrd")
        self._flush_interval_s = float(flush_interval_s)
        self._closed = False
        self._last_flush = time.monotonic()
        self._retry_at = 0.0
        self._retry_s = 1.0

        self.directory.mkdir(parents=True, exist_ok=True)
        self._seq = 1 + max((seq for _, seq, _ in self._scan()), default=-1)
        path = self._next_path()
        self._file = RerunSink(
            rrd_path=path,
            application_id=application_id,
            recording_id=self.recording_id,
            nodes=nodes,
            f1=f1,
            f2=f2,
            batch_size=batch_size,
            flush_interval_s=flush_interval_s,
        )
        self._path = path
        self._opened = time.monotonic()
        # RERUN=off in the environment: no file is written, nothing to rotate
        self._enabled = rr.is_enabled(self._file.recording)
        self._live: RerunSink | None = None
        try:
            self._prune()
            if connect_url is not None:
                self._live = RerunSink(
                    connect_url=connect_url,
                    application_id=application_id,
                    recording_id=self.recording_id,
                    nodes=nodes,
                    f1=f1,
                    f2=f2,
                    batch_size=batch_size,
                    flush_interval_s=flush_interval_s,
                )
        except BaseException:
            self.close()
            raise

    # -- the Sink protocol: forwarded to the file sink and the live stream ----------------------

    def add_sample(
        self,
        node: int,
        t: float,
        measured_current: float,
        estimated_current: float,
        gamma_hat: float,
        rule_count: int,
        health: int,
        nis: float,
        true_gamma: float | None = None,
    ) -> None:
        """Buffer one estimator sample (see `RerunSink.add_sample`)."""
        self._file.add_sample(
            node, t, measured_current, estimated_current, gamma_hat, rule_count, health, nis,
            true_gamma,
        )  # fmt: skip
        live = self._live
        if live is not None:
            live.add_sample(
                node, t, measured_current, estimated_current, gamma_hat, rule_count, health, nis,
                true_gamma,
            )  # fmt: skip

    def add_voltage(self, node: int, t: float, volts: float) -> None:
        for sink in self._sinks():
            sink.add_voltage(node, t, volts)

    def log_event(self, node: int, t: float, text: str, level: str = "INFO") -> None:
        for sink in self._sinks():
            sink.log_event(node, t, text, level)

    def log_counters(self, t: float, counters: Mapping[str, int]) -> None:
        for sink in self._sinks():
            sink.log_counters(t, counters)

    def set_thresholds(self, f1: float, f2: float) -> None:
        """Change the thresholds (buffered samples keep the old ones; later files start with
        the new ones)."""
        for sink in self._sinks():
            sink.set_thresholds(f1, f2)

    def maybe_flush(self, now_monotonic: float) -> None:
        """Flush (and maybe rotate) if ``flush_interval_s`` has passed since the last flush."""
        if now_monotonic - self._last_flush >= self._flush_interval_s:
            self.flush()
            self._last_flush = now_monotonic

    def flush(self) -> None:
        """Send all buffered data, then rotate if the current file is too big or too old."""
        now = time.monotonic()
        self._last_flush = now
        if self._closed:
            return
        for sink in self._sinks():
            sink.flush()
        if now >= self._retry_at and self._due(now):
            self.rotate()

    def rotate(self) -> Path:
        """Close the current file (footer written), start the next one and apply retention;
        return the path being written (the old one if the new one could not be created)."""
        if self._closed:
            return self._path
        path = self._next_path()
        started = time.monotonic()
        old = self._path
        try:
            self._file.switch_file(path)
        except (RuntimeError, OSError) as exc:
            _log.error(
                "rerun sink: cannot start %s: %s; still recording to %s (retry in %.0f s)",
                path,
                exc,
                old,
                self._retry_s,
            )
            self._retry_at = started + self._retry_s
            self._retry_s = min(2.0 * self._retry_s, _RETRY_MAX_S)
            return old
        self._retry_s = 1.0
        self._path = path
        self._opened = time.monotonic()
        self.rotations += 1
        _log.info(
            "rerun sink: closed %s (%s bytes) in %.3f s, recording to %s",
            old,
            self._size(old),
            self._opened - started,
            path,
        )
        self._prune()
        return path

    def close(self, timeout_s: float = 10.0) -> None:
        """Flush and close the current file (footer written) and the live stream. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._file.close(timeout_s)
        finally:
            if self._live is not None:
                self._live.close(timeout_s)

    # -- introspection ------------------------------------------------------------------------

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def path(self) -> Path:
        """The file being written (after `close`: the last one written)."""
        return self._path

    @property
    def nodes(self) -> tuple[int, ...]:
        return self._file.nodes

    @property
    def recording(self) -> rr.RecordingStream:
        """The `RecordingStream` of the files (one for the whole run)."""
        return self._file.recording

    def files(self) -> list[Path]:
        """The files of this pattern in the directory, oldest first (the current one last)."""
        return [p for _, _, p in self._scan()]

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- internals --------------------------------------------------------------------------

    def _sinks(self) -> tuple[RerunSink, ...]:
        return (self._file,) if self._live is None else (self._file, self._live)

    def _due(self, now: float) -> bool:
        if not self._enabled:
            return False
        if self.max_age_s is not None and now - self._opened >= self.max_age_s:
            return True
        if self.max_bytes is not None:
            size = self._size(self._path)
            # removed under us: start a new file rather than write into an unlinked one
            return size is None or size >= self.max_bytes
        return False

    @staticmethod
    def _size(path: Path) -> int | None:
        try:
            return os.stat(path).st_size
        except OSError:
            return None

    def _scan(self) -> list[tuple[str, int, Path]]:
        """(UTC stamp, sequence number, path) of this pattern's files, oldest first."""
        out: list[tuple[str, int, Path]] = []
        try:
            names = os.listdir(self.directory)
        except OSError:
            return out
        for name in names:
            m = self._pattern.fullmatch(name)
            if m is not None:
                out.append((m.group(1), int(m.group(2)), self.directory / name))
        out.sort()
        return out

    def _next_path(self) -> Path:
        with contextlib.suppress(OSError):  # if it fails, creating the file reports it
            self.directory.mkdir(parents=True, exist_ok=True)
        stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime())
        while True:
            path = self.directory / f"{self.prefix}-{stamp}-{self._seq:04d}.rrd"
            self._seq += 1
            if not path.exists():
                return path

    def _prune(self) -> None:
        """Delete the oldest closed files beyond ``keep`` and ``max_total_bytes``."""
        if self.keep is None and self.max_total_bytes is None:
            return
        closed = [p for _, _, p in self._scan() if p != self._path]
        sizes = [self._size(p) or 0 for p in closed]
        count = len(closed) + 1  # with the current file
        total = sum(sizes)
        room = (
            None if self.max_total_bytes is None else self.max_total_bytes - (self.max_bytes or 0)
        )
        for p, size in zip(closed, sizes, strict=True):
            if (self.keep is None or count <= self.keep) and (room is None or total <= room):
                break
            try:
                p.unlink(missing_ok=True)
                _log.info("rerun sink: deleted %s (%d bytes)", p, size)
            except OSError as exc:
                _log.warning("rerun sink: cannot delete %s: %s", p, exc)
            count -= 1
            total -= size
