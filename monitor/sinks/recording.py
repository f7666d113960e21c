"""The column-batched Rerun sink: `RecordingSink` records the monitor's live state to one
``.rrd`` file and/or streams it to a viewer (`monitor.sinks.rerun` describes the entity
layout, the batching, durability and size); `monitor.sinks.rotation` splits or rotates its
files."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Final, TypedDict

import numpy as np
import rerun as rr
from numpy.typing import NDArray

from monitor.diagnosis.thresholds import DEFAULT_THRESHOLDS
from monitor.pipeline.events import PlantSignals, SampleColumns
from monitor.sinks.batch import InputColumns, NodeColumns, fill, put_output_columns, put_outputs
from monitor.sinks.blueprint import (
    BUS_EVENTS_PATH,
    COUNTER_COLOR,
    ESTIMATED_COLOR,
    INPUT_COLOR,
    MEASURED_COLOR,
    NOISE_COLOR,
    STYLES,
    BlueprintSender,
    counter_path,
    default_blueprint,
    node_path,
    series_style,
    signal_legend,
    signal_parts,
)
from monitor.sinks.outlet import DEFAULT_FLUSH_INTERVAL_S, RecordingOutlet
from monitor.sinks.runs import EXACT_LINE, RUN_TAIL_S, RUNS, SLOW_ROW_S, bin_starts

__all__ = ["DEFAULT_FLUSH_INTERVAL_S", "TIMELINE", "RecordingOptions", "RecordingSink"]

_log = logging.getLogger(__name__)

Array = NDArray[np.float64]

TIMELINE: Final = "time"


_BATCHER_TICK_S: Final = 1.0
"""The SDK's micro-batcher holds row-wise ``log`` calls at most this long; `RerunSink.flush`
pushes them sooner. Every tick wakes its threads, which a one-CPU guest (User-Mode Linux) feels:
with 0.05 s they took ~8 % of its CPU while the bus was idle."""

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


class RecordingOptions(TypedDict, total=False):
    """The settings of a recording: `RecordingSink`'s keyword arguments other than where it
    goes (``rrd_path``, ``connect_url``, ``write_footer``), whose defaults are there. A sink
    that writes one recording into several `RecordingSink` (`RotatingRerunSink`) takes them
    as these and passes them on to each, so they are declared here and there only, and mypy
    holds the two together."""

    application_id: str
    recording_id: str | None
    nodes: Sequence[int]
    f1: float
    f2: float
    batch_size: int
    flush_interval_s: float
    signals: PlantSignals | None


class RecordingSink(RecordingOutlet):
    """Column-batched Rerun sink; see `monitor.sinks.rerun` for the entity layout.

    ``rrd_path`` records to a file, ``connect_url`` (``rerun+http://HOST:PORT/proxy``) streams
    to a viewer or gRPC proxy; both may be given at once. ``write_footer=False`` skips the
    ``.rrd`` footer, whose chunk manifest the SDK otherwise keeps in memory for the whole run
    (grows with the number of chunks; ``rerun rrd optimize`` can add a footer afterwards;
    `RotatingRerunSink` bounds it instead). ``flush_interval_s`` bounds how long a sample stays
    in the buffers when `maybe_flush` is called often enough (see the module docstring).

    Its files are split into parts by `monitor.sinks.rotation.RerunSink`, rotated by
    `RotatingRerunSink` (`switch_file`; `_before_rows` and `_after_full` are their hooks).

    ``signals`` names the inputs and outputs (entities, legends; default: our bus's): the
    rig's, `monitor.setup.plant_signals`.
    """

    def __init__(
        self,
        *,
        rrd_path: str | Path | None = None,
        connect_url: str | None = None,
        application_id: str = "motor-monitor",
        recording_id: str | None = None,
        nodes: Sequence[int] = (0,),
        f1: float = DEFAULT_THRESHOLDS.f1,
        f2: float = DEFAULT_THRESHOLDS.f2,
        batch_size: int = 2048,
        flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
        write_footer: bool = True,
        signals: PlantSignals | None = None,
    ) -> None:
        if rrd_path is None and connect_url is None:
            raise ValueError("RerunSink needs rrd_path and/or connect_url (use Sink() for none)")
        if batch_size < 1:
            raise ValueError("batch_size must be >= 1")
        if not flush_interval_s >= 0.0:
            raise ValueError("flush_interval_s must be >= 0")
        self._batch_size = int(batch_size)
        self._flush_interval_s = float(flush_interval_s)
        self._signals = signals if signals is not None else PlantSignals()
        self._in_parts, self._out_parts = signal_parts(self._signals, 0, 1)
        self._f1 = float(f1)
        self._f2 = float(f2)
        self._closed = False
        self._nodes: dict[int, NodeColumns] = {}
        self._counters: dict[str, str] = {}
        self._counter_rows: list[tuple[float, dict[str, int]]] = []
        self._event_rows: dict[str, list[tuple[float, str, str]]] = {}  # path: (t, text, level)
        self._n_events = 0
        self._last_flush = time.monotonic()
        self._rows_batched = False
        """A row-wise ``log`` call went to the SDK's batcher since the last `flush`."""
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
        self._blueprints = BlueprintSender(self._rec, application_id)
        self._send_blueprint()

    # -- hot path -------------------------------------------------------------------------

    def add_sample(
        self,
        node: int,
        t: float,
        measured: float,
        estimated: float,
        gamma_hat: float,
        rule_count: int,
        health: int,
        nis: float,
        true_gamma: float | None = None,
        model_mismatch: bool = False,
        *,
        outputs: Sequence[float] = (),
        predicted: Sequence[float] = (),
        gamma_sd: float = math.nan,
        output_noise: Sequence[float] = (),
        process_noise: float = math.nan,
    ) -> None:
        """Buffer one estimator sample of ``node`` at bus time ``t`` (epoch seconds):
        every output measured and estimated (`outputs`, `predicted`, in the order of the
        sink's ``signals``), or, where they are not given, the first one (`measured`,
        `estimated`; the others NaN); `gamma_sd` is gamma^'s standard deviation
        (`Sample.gamma_sd`; NaN: none given); `output_noise` (per output, in the same
        order) and `process_noise` the estimator's noise factors (`Sample.output_noise`,
        `.process_noise`; NaN: none given)."""
        st = self._node_for(node)
        if st is None:
            return

        def row(dst: slice, _: slice) -> None:
            i = dst.start
            st.t[i] = t
            put_outputs(st.measured[:, i], measured, outputs)
            put_outputs(st.estimated[:, i], estimated, predicted)
            st.gamma[i] = gamma_hat
            st.gamma_sd[i] = gamma_sd
            put_outputs(st.output_noise[:, i], math.nan, output_noise)
            st.process_noise[i] = process_noise
            st.true_gamma[i] = math.nan if true_gamma is None else true_gamma
            st.rules[i] = rule_count
            st.health[i] = health
            st.mismatch[i] = model_mismatch
            st.nis[i] = nis

        fill(st, 1, self._batch_size, row, lambda: self._full_samples(st))

    def add_input(self, node: int, t: float, value: float, index: int = 0) -> None:
        """Buffer one row of input `index` of ``node``, as a frame carried it."""
        st = self._node_for(node)
        if st is None:
            return
        buf = st.inputs.get(index) or self._new_input(st, index)

        def row(dst: slice, _: slice) -> None:
            buf.t[dst.start] = t
            buf.v[dst.start] = value

        fill(buf, 1, self._batch_size, row, lambda: self._full_input(buf))

    # -- rare data --------------------------------------------------------------------------

    def log_event(self, node: int, t: float, text: str, level: str = "INFO") -> None:
        """Log a text event (state transition...) for ``node``: buffered, and sent after the
        buffered samples at the next flush (every ``flush_interval_s`` live).

        A negative node is the bus itself (error frames, interface outages): the event goes
        to ``/monitor/events``, shown beside the daemon counters.
        """
        if self._closed:
            return
        if node < 0:
            path = BUS_EVENTS_PATH
        else:
            st = self._nodes.get(node) or self._new_node(node)
            path = st.path["events"]
        self._event_rows.setdefault(path, []).append((t, text, _LEVELS.get(level.upper(), level)))
        self._n_events += 1
        if self._n_events >= self._batch_size:
            self.flush()

    def _flush_events(self) -> None:
        """The buffered events, one chunk per entity path: a replay's thousands of
        transitions are not thousands of one-row chunks, each forcing the samples out."""
        rows, self._event_rows, self._n_events = self._event_rows, {}, 0
        for path, events in rows.items():
            self._rec.send_columns(
                path,
                indexes=[rr.TimeColumn(TIMELINE, timestamp=np.array([e[0] for e in events]))],
                columns=rr.TextLog.columns(text=[e[1] for e in events],
                                           level=[e[2] for e in events]),
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
                path = counter_path(name)
                self._counters[name] = path
                self._log_static(path, series_style(name, COUNTER_COLOR, 1.5, stepped=True))
            ts = np.array([t for t, c in rows if name in c], dtype=np.float64)
            vs = np.array([c[name] for _, c in rows if name in c], dtype=np.float64)
            self._rec.send_columns(
                path,
                indexes=[rr.TimeColumn(TIMELINE, timestamp=ts)],
                columns=rr.Scalars.columns(scalars=vs),
            )

    def on_sample_columns(self, node: int, cols: SampleColumns) -> None:
        """A node's samples as columns (the columnar replay): `add_sample` a slice at a time,
        into the same buffers, sent as the same chunks (gamma^'s standard deviation and the
        noise factors NaN where the columns carry none)."""
        st = self._node_for(node)
        if st is None:
            return

        def rows(dst: slice, src: slice) -> None:
            st.t[dst] = cols.t[src]
            put_output_columns(st.measured[:, dst], cols.measured[src], cols.outputs, src)
            put_output_columns(st.estimated[:, dst], cols.estimated[src], cols.predicted, src)
            st.gamma[dst] = cols.gamma[src]
            st.gamma_sd[dst] = math.nan if cols.gamma_sd is None else cols.gamma_sd[src]
            put_output_columns(st.output_noise[:, dst], math.nan, cols.output_noise, src)
            st.process_noise[dst] = (math.nan if cols.process_noise is None
                                     else cols.process_noise[src])
            st.true_gamma[dst] = cols.true_gamma[src]
            st.rules[dst] = cols.rules[src]
            st.health[dst] = cols.state[src]
            st.mismatch[dst] = cols.model_mismatch[src]
            st.nis[dst] = cols.nis[src]

        fill(st, len(cols.t), self._batch_size, rows, lambda: self._full_samples(st))

    def on_input_columns(self, node: int, t: Array, values: Array,
                         index: NDArray[np.int64]) -> None:
        """A node's inputs as columns (row i: input `index[i]`): `add_input` a slice at a
        time, each input into its own buffer."""
        st = self._node_for(node)
        if st is None:
            return
        for a in np.unique(index).tolist():
            rows = index == a
            ta, va = t[rows], values[rows]
            buf = st.inputs.get(a) or self._new_input(st, a)

            def put(dst: slice, src: slice, buf: InputColumns = buf, ta: Array = ta,
                    va: Array = va) -> None:
                buf.t[dst] = ta[src]
                buf.v[dst] = va[src]

            def full(buf: InputColumns = buf) -> None:
                self._full_input(buf)

            fill(buf, len(ta), self._batch_size, put, full)

    def set_thresholds(self, f1: float, f2: float) -> None:
        """Change the diagnosis thresholds; buffered samples keep the old ones."""
        if not self._closed:
            for st in self._nodes.values():
                self._flush_samples(st)
        self._f1 = float(f1)
        self._f2 = float(f2)

    # -- flushing ---------------------------------------------------------------------------

    def flush(self) -> None:
        """Send all buffered samples (non-blocking hand-over to the Rerun sinks)."""
        self._last_flush = time.monotonic()
        if self._closed:
            return
        for st in self._nodes.values():
            self._flush_samples(st)
            for buf in st.inputs.values():
                self._flush_input(buf)
        self._flush_events()
        self._flush_counters()
        if not self._rows_batched:
            return  # columns went to the sinks directly; a flush would only wake the SDK's threads
        self._rows_batched = False
        try:
            self._rec.flush(timeout_sec=0.0)  # start pushing to the sinks, don't wait
        except RuntimeError as exc:  # e.g. the gRPC viewer is unreachable
            _log.warning("rerun flush: %s", exc)

    def close(self, timeout_s: float = 10.0) -> None:
        """Flush, then finalise the sinks (writes the ``.rrd`` footer). Idempotent."""
        if self._closed:
            return
        self.flush()
        self._send_pending()
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
        self._send_pending()
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
            st.runs.restart()  # the new file starts its runs anew
            st.slow_last_t = -math.inf  # and its slow series' bins
            self._style_node(st)
        self._send_blueprint()

    def _before_rows(self) -> None:
        """Before rows are added: a hook for the file parts (`rotation.RerunSink`)."""

    def _after_full(self) -> None:
        """After a full batch was sent: a hook for the file parts (`rotation.RerunSink`)."""

    @property
    def nodes(self) -> tuple[int, ...]:
        """The nodes with a tab in the blueprint (announced or seen), in order of arrival."""
        return tuple(self._nodes)

    @property
    def recording(self) -> rr.RecordingStream:
        """The underlying explicit (non-global) recording stream."""
        return self._rec

    # -- internals --------------------------------------------------------------------------

    def _node_for(self, node: int) -> NodeColumns | None:
        """The buffers of ``node`` (added at its first row) for rows about to be added, or
        None once the sink is closed."""
        if self._closed:
            return None
        self._before_rows()
        return self._nodes.get(node) or self._new_node(node)

    def _full_samples(self, st: NodeColumns) -> None:
        self._flush_samples(st)
        self._after_full()

    def _full_input(self, buf: InputColumns) -> None:
        self._flush_input(buf)
        self._after_full()

    def _add_node(self, node: int) -> NodeColumns:
        st = NodeColumns(node, self._batch_size, self._out_parts)
        for index, part in enumerate(self._in_parts):  # styled with the node, like its outputs
            st.inputs[index] = InputColumns(node_path(node, part), self._batch_size)
        self._nodes[node] = st
        self._style_node(st)
        return st

    def _new_input(self, st: NodeColumns, index: int) -> InputColumns:
        """The buffer of an input beyond the names given, at its first row (named by
        `signal_parts` too)."""
        if index >= len(self._in_parts):
            self._in_parts = signal_parts(self._signals, index + 1)[0]
        buf = InputColumns(node_path(st.node, self._in_parts[index]), self._batch_size)
        st.inputs[index] = buf
        self._style_input(buf, index)
        return buf

    def _style_node(self, st: NodeColumns) -> None:
        for suffix, *_ in STYLES:
            if suffix != "gamma/true":  # styled when the first true gamma arrives
                self._style(st.path[suffix], suffix)
        for j, (measured, estimated) in enumerate(st.out_paths):
            signal = self._signals.output(j)
            self._log_static(measured, series_style(signal_legend(signal, "measured"),
                                                    MEASURED_COLOR, 1.0, False))
            self._log_static(estimated, series_style(signal_legend(signal, "estimated"),
                                                     ESTIMATED_COLOR, 1.5, False))
            # a ratio: the signal's name without its unit
            self._log_static(st.noise_paths[j], series_style(
                signal_legend((signal[0], None), "noise factor"), NOISE_COLOR, 1.0, False))
        for index, buf in st.inputs.items():
            self._style_input(buf, index)

    def _style_input(self, buf: InputColumns, index: int) -> None:
        self._log_static(buf.path, series_style(signal_legend(self._signals.input(index)),
                                                INPUT_COLOR, 1.0, False))

    def _style(self, path: str, suffix: str) -> None:
        _, name, color, width, stepped = next(s for s in STYLES if s[0] == suffix)
        style = series_style(name, color, width, stepped)
        if suffix in RUNS:
            self._log_static(path, style, EXACT_LINE)
        else:
            self._log_static(path, style)

    def _log_static(self, path: str, *archetypes: Any) -> None:
        """A static row-wise ``log``: through the SDK's batcher, which the next `flush` pushes."""
        self._rec.log(path, *archetypes, static=True)
        self._rows_batched = True

    def _new_node(self, node: int) -> NodeColumns:
        """A node not announced in ``nodes``: add it and resend the blueprint."""
        _log.info("rerun sink: new node %d", node)
        st = self._add_node(node)
        self._send_blueprint()
        return st

    def _send_blueprint(self) -> None:
        self._blueprints.send(default_blueprint(sorted(self._nodes), self._signals))

    def _flush_samples(self, st: NodeColumns) -> None:
        n = st.n
        if n == 0:
            return
        st.n = 0
        send = self._rec.send_columns
        path = st.path
        t = st.t[:n]
        index = [rr.TimeColumn(TIMELINE, timestamp=t)]
        scalars = rr.Scalars.columns
        for j, (measured, estimated) in enumerate(st.out_paths):
            send(measured, indexes=index, columns=scalars(scalars=st.measured[j, :n]))
            send(estimated, indexes=index, columns=scalars(scalars=st.estimated[j, :n]))
        send(path["gamma/estimate"], indexes=index, columns=scalars(scalars=st.gamma[:n]))
        send(path["gamma/sd"], indexes=index, columns=scalars(scalars=st.gamma_sd[:n]))
        slow = bin_starts(t, st.slow_last_t, SLOW_ROW_S)
        st.slow_last_t = float(t[-1])
        if slow.any():
            st.slow.append((t[slow], st.output_noise[:, :n][:, slow], st.process_noise[:n][slow]))
        if st.slow and t[-1] - st.slow_sent_t >= RUN_TAIL_S:
            self._send_slow(st)
        true_gamma = st.true_gamma[:n]
        given = ~np.isnan(true_gamma)
        if not st.true_styled and given.any():
            st.true_styled = True
            self._style(path["gamma/true"], "gamma/true")
        if given.any():
            self._send_runs(st, "gamma/true", t[given], true_gamma[given])
        ends = t[[0, n - 1]] if n > 1 else t[:1].copy()
        self._send_runs(st, "gamma/F1", ends, np.full(len(ends), self._f1))
        self._send_runs(st, "gamma/F2", ends, np.full(len(ends), self._f2))
        self._send_runs(st, "rules", t, st.rules[:n])
        self._send_runs(st, "health", t, st.health[:n])
        self._send_runs(st, "model_mismatch", t, st.mismatch[:n])
        send(path["nis"], indexes=index, columns=scalars(scalars=st.nis[:n]))

    def _send_runs(self, st: NodeColumns, suffix: str, t: Array, v: Array) -> None:
        """Send the rows of a piecewise-constant series (`RUNS`) that draw its line
        (`RunThinner.rows`)."""
        rows = st.runs.rows(suffix, t, v)
        if rows is not None:
            self._send_rows(st, suffix, *rows)

    def _send_rows(self, st: NodeColumns, suffix: str, t: Array, v: Array) -> None:
        self._rec.send_columns(
            st.path[suffix],
            indexes=[rr.TimeColumn(TIMELINE, timestamp=t)],
            columns=rr.Scalars.columns(scalars=v),
        )

    def _send_slow(self, st: NodeColumns) -> None:
        """Send the slowly varying series' rows held back (`NodeColumns.slow`)."""
        t = np.concatenate([b[0] for b in st.slow])
        index = [rr.TimeColumn(TIMELINE, timestamp=t)]
        output_noise = np.concatenate([b[1] for b in st.slow], axis=1)
        for j, noise in enumerate(st.noise_paths):
            self._rec.send_columns(noise, indexes=index,
                                   columns=rr.Scalars.columns(scalars=output_noise[j]))
        self._send_rows(st, "process_noise", t, np.concatenate([b[2] for b in st.slow]))
        st.slow.clear()
        st.slow_sent_t = float(t[-1])

    def _send_pending(self) -> None:
        """Send the rows the run thinning and the slow series held back, so the lines reach
        the end of the data."""
        for st in self._nodes.values():
            if st.slow:
                self._send_slow(st)
            for suffix, t, v in st.runs.held():
                self._send_rows(st, suffix, t, v)

    def _flush_input(self, buf: InputColumns) -> None:
        n = buf.n
        if n == 0:
            return
        buf.n = 0
        self._rec.send_columns(
            buf.path,
            indexes=[rr.TimeColumn(TIMELINE, timestamp=buf.t[:n])],
            columns=rr.Scalars.columns(scalars=buf.v[:n]),
        )
