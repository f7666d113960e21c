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
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import Final, Protocol, Self, runtime_checkable

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from numpy.typing import NDArray

__all__ = ["NullSink", "RerunSink", "Sink", "default_blueprint"]

_log = logging.getLogger(__name__)

Array = NDArray[np.float64]
Color = tuple[int, int, int]

TIMELINE: Final = "time"

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
                    rrb.TimeSeriesView(origin=f"{m}/nis", name="NIS"),
                    rrb.TimeSeriesView(origin=f"{m}/voltage", name="supply voltage"),
                ),
                rrb.TextLogView(origin=f"{m}/events", name="events"),
                row_shares=[3.0, 3.0, 2.0, 2.0],
                name=f"motor {n}",
            )
        )
    tabs.append(rrb.TimeSeriesView(origin="/monitor/counters", name="daemon counters"))
    return rrb.Blueprint(rrb.Tabs(*tabs, active_tab=0), collapse_panels=False)


class RerunSink:
    """Column-batched Rerun sink; see the module docstring for the entity layout.

    ``rrd_path`` records to a file, ``connect_url`` (``rerun+http://HOST:PORT/proxy``) streams
    to a viewer or gRPC proxy; both may be given at once. ``write_footer=False`` skips the
    ``.rrd`` footer, whose chunk manifest the SDK otherwise keeps in memory for the whole run
    (grows with the number of chunks; ``rerun rrd optimize`` can add a footer afterwards).
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
        flush_interval_s: float = 0.2,
        write_footer: bool = True,
    ) -> None:
        if rrd_path is None and connect_url is None:
            raise ValueError("RerunSink needs rrd_path and/or connect_url (use NullSink for none)")
        if batch_size < 1:
            raise ValueError("batch_size must be >= 1")
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

        self._rec = rr.RecordingStream(application_id, recording_id=recording_id)
        sinks: list[rr.FileSink | rr.GrpcSink] = []
        if self.rrd_path is not None:
            sinks.append(rr.FileSink(self.rrd_path, write_footer=write_footer))
        if connect_url is not None:
            sinks.append(rr.GrpcSink(connect_url))
        self._rec.set_sinks(*sinks)
        for node in dict.fromkeys(int(n) for n in nodes):
            self._add_node(node)
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
        """Log a text event (state transition...) for ``node``, after its buffered samples."""
        if self._closed:
            return
        st = self._nodes.get(node)
        if st is None:
            st = self._new_node(node)
        self._flush_samples(st)
        self._flush_voltage(st)
        lvl = _LEVELS.get(level.upper(), level)
        self._rec.send_columns(
            st.path["events"],
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

    @property
    def closed(self) -> bool:
        return self._closed

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
        for suffix, *_ in _STYLES:
            if suffix != "gamma/true":  # styled when the first true gamma arrives
                self._style(st.path[suffix], suffix)
        return st

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
        self._rec.send_blueprint(
            default_blueprint(sorted(self._nodes)), make_active=True, make_default=True
        )

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
