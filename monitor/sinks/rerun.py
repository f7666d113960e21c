"""Live state of the monitor, streamed to a Rerun viewer and/or recorded to an ``.rrd`` file.

The daemon feeds up to ~10,000 samples/s in total. A row-wise ``rr.log`` costs ~0.1 ms, so
every high-rate series goes through column batches: `RerunSink.add_sample` only stores the
values in preallocated per-node numpy buffers (float64, ``batch_size`` long, reused for the
whole run) and a full buffer, `RerunSink.flush`, or `RerunSink.maybe_flush` once
``flush_interval_s`` has elapsed, sends it with one ``RecordingStream.send_columns`` per entity.
Rerun copies the data when it builds its Arrow arrays, so reusing the buffers is safe. Rare
data (events, counters) is sent straight away; an event first flushes its node's buffers so it
never comes before samples that precede it in time.

The entity layout, the series styles and the default blueprint are in
`monitor.sinks.blueprint`.

The thresholds go with every gamma batch, at its first and last time stamp, with step
interpolation, so each threshold line spans exactly the data and a `RerunSink.set_thresholds`
change shows up as a step where it took effect.

Piecewise-constant series (`RUNS`: the thresholds, the rule count, the health state, the
model-mismatch flag, a simulator's true gamma) are recorded as their runs: of each batch
only the rows that draw the line (`run_ends`: the first and the last row of every run of
equal values) and the batch's last row, which extends the line to the end of the data --
while a run goes on, at most once a second (`_RUN_TAIL_S`; `close` and `switch_file` send
the one held back, and a row that changes the value is never held; after a SIGKILL such a
line may stop up to that much before the others, on a value that had not changed). The line
through them, stepped or straight, is the line through every sample, the latest value at any
time is the same, and the viewer draws them without its per-pixel averaging, which would
slant a run's line between two changes (`_EXACT_LINE`). They were 4 of the 8 rows of every
sample; the other series (each output measured and estimated, gamma^, NIS, and the inputs)
keep every sample.

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
the batcher: the next `RerunSink.flush` after one pushes it (``flush(timeout_sec=0)``:
started, not waited for; a flush with nothing batched leaves the SDK's threads asleep), and its
tick is set to `_BATCHER_TICK_S` explicitly, so ``RERUN_FLUSH_TICK_SECS`` in the environment
cannot hold them back longer. `RerunSink.close` writes the ``.rrd`` footer (SIGTERM/SIGINT in the
daemon), and ``rerun rrd verify`` passes. A killed process leaves a file without footer and,
if the kill hit a ``write``, with a torn last message: the SDK's streaming decoder reads it as
it is (``rerun rrd verify --check-footers false``, ``rerun rrd print``, the viewer);
``rerun rrd optimize FILE -o NEW`` writes a compacted copy with a footer;
`monitor.sinks.salvage.salvage_rrd` cuts the torn message off in place, for strict readers
(``rerun.chunk.RrdReader`` refuses the whole file otherwise).

Size. Every flush sends one chunk per entity, and a chunk costs ~1 kB besides its rows (its
Arrow schema and metadata, LZ4-compressed like the rest of the message, and ~33 bytes of footer
manifest); a row of a scalar costs 36 bytes before compression (16-byte row id, 8-byte time,
8-byte float64 value, 4-byte list offset), ~16-24 after. One 100 Hz node (``python -m
tests.bench.recording_size``, bytes per hour, against 38 MB for the candump ``.log`` of its
frames and 12 MB for the ``.blf``): flushed every 0.1 s, 292 MB (framing, ~63 chunks/s); every
2 s, which is sound when another record bounds what a kill may lose (``run --raw-dir``), 78 MB;
compacted by ``rerun rrd optimize`` (`monitor.sinks.compact`: one chunk per entity and ~2 MiB),
34-35 MB, the rows themselves: `RotatingRerunSink` compacts every file it closes.

Week-long runs: `monitor.sinks.rotation.RotatingRerunSink` writes a directory of ``.rrd``
files; when the current one exceeds a size or an age it is finished (footer) and recording
goes on into a new one, with the same `RecordingStream` and a new `FileSink`; the oldest
files beyond a count or a total size are deleted. The footer's chunk manifest, which the
SDK keeps in memory while a file is open, is freed at each rotation: memory and disk stay
bounded however long the daemon runs.
"""

from __future__ import annotations

import glob
import logging
import math
import time
from collections.abc import Mapping, Sequence
from contextlib import suppress
from pathlib import Path
from typing import Any, Final

import numpy as np
import rerun as rr
from numpy.typing import NDArray

from monitor.pipeline.events import (
    BusEvent,
    DiagnosisEvent,
    DriveEvent,
    InputSample,
    PlantSignals,
    Sample,
    SampleColumns,
)
from monitor.sinks.base import Sink
from monitor.sinks.blueprint import (
    BUS_EVENTS_PATH,
    COUNTER_COLOR,
    ESTIMATED_COLOR,
    INPUT_COLOR,
    MEASURED_COLOR,
    STYLES,
    BlueprintSender,
    counter_path,
    default_blueprint,
    node_path,
    series_style,
    signal_legend,
    signal_parts,
)

__all__ = ["DEFAULT_FLUSH_INTERVAL_S", "REPLAY_BATCH_SIZE", "REPLAY_PART_BYTES", "RUNS",
           "RecordingOutlet", "RerunSink", "recording_parts", "run_ends"]

_log = logging.getLogger(__name__)

Array = NDArray[np.float64]

TIMELINE: Final = "time"

DEFAULT_FLUSH_INTERVAL_S: Final = 0.1
"""Buffered samples reach the file at most this long after they were added (plus the period of
the `maybe_flush` calls and ~1 ms of writing)."""

REPLAY_BATCH_SIZE: Final = 1 << 15
"""Rows per chunk when a replay is recorded (`RerunSink` ``batch_size``): nothing waits for a
replay's samples, so each chunk is as large as a compacted file's (256 KiB a float64 column;
``rerun rrd optimize`` aims at 2 MiB chunks). Against the live default of 2,048 rows, a replay
of 10^7 frames writes 16x fewer chunks (the footer manifest the SDK holds in memory until the
file closes shrinks with them), a ~30 % smaller file, ~25 % faster (`python -m
tests.bench.pipeline`)."""

REPLAY_PART_BYTES: Final = 1 << 30
"""A replay's recording goes on into a new part once its file has reached this size
(`RerunSink` ``part_bytes``): about 4*10^7 frames of a 100 Hz node, an hour of a saturated
1 Mbit/s bus. A part is what the viewer loads whole into memory, and the SDK keeps each open
file's footer manifest (a few kB a chunk) in memory until it closes: parts keep both bounded
however long the log."""

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

RUNS: Final = ("gamma/true", "gamma/F1", "gamma/F2", "rules", "health", "model_mismatch")
"""Series that are piecewise constant by nature (the truth a simulator sends, the thresholds,
the estimator's rule count, the health state and the model-mismatch flag): recorded as their
runs (`run_ends`), drawn without the viewer's zoom-dependent aggregation (`_EXACT_LINE`)."""

_RUN_TAIL_S: Final = 1.0
"""A `RUNS` series sends a row that only continues its run at most this often."""

_EXACT_LINE: Final = rr.SeriesLines.from_fields(
    aggregation_policy=rr.components.AggregationPolicy.Off)
"""The viewer averages the points that fall into one pixel (its default for a dense series,
where that keeps the line's shape). The two rows either side of a change, one sample apart,
would be averaged into one point half-way, and the line from it to the run's far end would
slant: the runs are drawn as they are, which is the line the samples draw."""


def recording_parts(rrd_path: Path) -> list[Path]:
    """`rrd_path` (if it exists) and the parts beside it that a ``part_bytes`` split wrote
    (``<stem>-partNNNN.rrd``), in order."""
    pattern = f"{glob.escape(rrd_path.stem)}-part[0-9][0-9][0-9][0-9]{glob.escape(rrd_path.suffix)}"
    parts = sorted(rrd_path.parent.glob(pattern))
    return ([rrd_path] if rrd_path.exists() else []) + parts


def run_ends(v: Array, previous: float = math.nan) -> NDArray[np.bool_]:
    """Which rows of `v` to keep so that the line through them, stepped or straight, is the
    line through all of them: every row but those inside a run of equal values (equal to the
    row before, ``previous`` for the first, and to the row after). The last row is kept, so
    the line reaches the end of the data; the latest value at any time is unchanged."""
    n = len(v)
    same_before = np.empty(n, dtype=np.bool_)
    same_after = np.zeros(n, dtype=np.bool_)
    if n:
        same_before[0] = v[0] == previous
        same_before[1:] = v[1:] == v[:-1]
        same_after[:-1] = same_before[1:]
    return ~(same_before & same_after)


class RecordingOutlet(Sink):
    """The pipeline's events onto a recording's column API (`add_sample`, `add_input`,
    `log_event`, `log_counters`), which `RerunSink` and `RotatingRerunSink` implement."""

    def add_sample(self, node: int, t: float, measured: float, estimated: float,
                   gamma_hat: float, rule_count: int, health: int, nis: float,
                   true_gamma: float | None = None, model_mismatch: bool = False, *,
                   outputs: Sequence[float] = (), predicted: Sequence[float] = ()) -> None:
        raise NotImplementedError

    def add_input(self, node: int, t: float, value: float, index: int = 0) -> None:
        raise NotImplementedError

    def log_event(self, node: int, t: float, text: str, level: str = "INFO") -> None:
        raise NotImplementedError

    def log_counters(self, t: float, counters: Mapping[str, int]) -> None:
        raise NotImplementedError

    def on_sample(self, sample: Sample) -> None:
        self.add_sample(sample.node, sample.t, sample.measured, sample.estimated, sample.gamma,
                        sample.rules, int(sample.state), sample.nis, sample.true_gamma,
                        sample.model_mismatch, outputs=sample.outputs,
                        predicted=sample.predicted)

    def on_input(self, sample: InputSample) -> None:
        self.add_input(sample.node, sample.t, sample.value, sample.index)

    def on_transition(self, event: DiagnosisEvent) -> None:
        self.log_event(event.node, event.t, event.text, event.level)

    def on_bus_event(self, event: BusEvent) -> None:
        # what a drive says of itself goes beside its node's diagnosis
        node = event.node if isinstance(event, DriveEvent) else -1
        self.log_event(node, event.t, event.text, event.level)

    def on_counters(self, t: float, counters: Mapping[str, int]) -> None:
        self.log_counters(t, counters)


class _Input:
    """The column buffer of one input of a node: its own rate, its own rows."""

    __slots__ = ("n", "path", "t", "v")

    def __init__(self, path: str, batch_size: int) -> None:
        self.path = path
        self.n = 0
        self.t: Array = np.zeros(batch_size)
        self.v: Array = np.zeros(batch_size)


class _Node:
    """Preallocated column buffers and entity paths of one node."""

    __slots__ = (
        "estimated",
        "gamma",
        "health",
        "inputs",
        "last",
        "measured",
        "mismatch",
        "n",
        "nis",
        "node",
        "out_paths",
        "path",
        "pending",
        "rules",
        "sent_t",
        "t",
        "true_gamma",
        "true_styled",
    )

    def __init__(self, node: int, batch_size: int, outputs: Sequence[str]) -> None:
        self.node = node
        self.path: dict[str, str] = {s[0]: node_path(node, s[0]) for s in STYLES}
        self.path["events"] = node_path(node, "events")
        self.out_paths: list[tuple[str, str]] = [
            (node_path(node, f"{o}/measured"), node_path(node, f"{o}/estimated"))
            for o in outputs]
        """(measured, estimated) entity of each output."""
        self.n = 0
        self.t: Array = np.zeros(batch_size)
        # one row per output; NaN where a producer gives only the first output
        self.measured: Array = np.zeros((len(outputs), batch_size))
        self.estimated: Array = np.zeros((len(outputs), batch_size))
        self.gamma: Array = np.zeros(batch_size)
        self.true_gamma: Array = np.zeros(batch_size)
        self.rules: Array = np.zeros(batch_size)
        self.health: Array = np.zeros(batch_size)
        self.mismatch: Array = np.zeros(batch_size)
        self.nis: Array = np.zeros(batch_size)
        self.last: dict[str, float] = {}
        """The value of the last row of each series in `RUNS` so far (none yet: NaN)."""
        self.pending: dict[str, tuple[float, float]] = {}
        """A `RUNS` series' last row (time, value), held back: it only continued its run."""
        self.sent_t: dict[str, float] = {}
        """The time of the last row sent of each `RUNS` series."""
        self.true_styled = False
        self.inputs: dict[int, _Input] = {}
        """Each input's buffer, by its index (one beyond the names given from its first
        row)."""


class RerunSink(RecordingOutlet):
    """Column-batched Rerun sink; see the module docstring for the entity layout.

    ``rrd_path`` records to a file, ``connect_url`` (``rerun+http://HOST:PORT/proxy``) streams
    to a viewer or gRPC proxy; both may be given at once. ``write_footer=False`` skips the
    ``.rrd`` footer, whose chunk manifest the SDK otherwise keeps in memory for the whole run
    (grows with the number of chunks; ``rerun rrd optimize`` can add a footer afterwards;
    `RotatingRerunSink` bounds it instead). ``flush_interval_s`` bounds how long a sample stays
    in the buffers when `maybe_flush` is called often enough (see the module docstring).

    ``part_bytes`` (a file without ``connect_url``) splits the recording into parts: once the
    current file has reached that size (checked after each full batch), `switch_file` goes on
    into ``<stem>-part0002.rrd``, ``-part0003``... beside ``rrd_path``, every part complete
    (footer, styles, blueprint) and of the same recording, so the viewer opens one part or
    all of them as one recording (`parts` lists them). Parts of an earlier recording to the
    same path are deleted at start: they would merge into this one.

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
        f1: float = 0.15,
        f2: float = 0.85,
        batch_size: int = 2048,
        flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
        write_footer: bool = True,
        part_bytes: int | None = None,
        signals: PlantSignals | None = None,
    ) -> None:
        if rrd_path is None and connect_url is None:
            raise ValueError("RerunSink needs rrd_path and/or connect_url (use Sink() for none)")
        if part_bytes is not None and (rrd_path is None or connect_url is not None
                                       or part_bytes < 1):
            raise ValueError("part_bytes needs rrd_path, no connect_url, and a size >= 1")
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
        self._nodes: dict[int, _Node] = {}
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
        self._part_bytes = part_bytes
        self._part_due = False
        self._parts: list[Path] = [] if self.rrd_path is None else [self.rrd_path]
        if part_bytes is not None and self.rrd_path is not None:
            for stale in recording_parts(self.rrd_path):
                if stale != self.rrd_path:
                    stale.unlink(missing_ok=True)

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
    ) -> None:
        """Buffer one estimator sample of ``node`` at bus time ``t`` (epoch seconds):
        every output measured and estimated (`outputs`, `predicted`, in the order of the
        sink's ``signals``), or, where they are not given, the first one (`measured`,
        `estimated`; the others NaN)."""
        if self._closed:
            return
        if self._part_due:
            self._next_part()
        st = self._nodes.get(node)
        if st is None:
            st = self._new_node(node)
        i = st.n
        st.t[i] = t
        _put(st.measured[:, i], measured, outputs)
        _put(st.estimated[:, i], estimated, predicted)
        st.gamma[i] = gamma_hat
        st.true_gamma[i] = math.nan if true_gamma is None else true_gamma
        st.rules[i] = rule_count
        st.health[i] = health
        st.mismatch[i] = model_mismatch
        st.nis[i] = nis
        i += 1
        st.n = i
        if i == self._batch_size:
            self._flush_samples(st)
            self._note_part_full()

    def add_input(self, node: int, t: float, value: float, index: int = 0) -> None:
        """Buffer one row of input `index` of ``node``, as a frame carried it."""
        if self._closed:
            return
        if self._part_due:
            self._next_part()
        st = self._nodes.get(node)
        if st is None:
            st = self._new_node(node)
        buf = st.inputs.get(index) or self._new_input(st, index)
        i = buf.n
        buf.t[i] = t
        buf.v[i] = value
        i += 1
        buf.n = i
        if i == self._batch_size:
            self._flush_input(buf)
            self._note_part_full()

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
            st = self._nodes.get(node)
            if st is None:
                st = self._new_node(node)
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
        into the same buffers, sent as the same chunks."""
        if self._closed:
            return
        if self._part_due:
            self._next_part()
        st = self._nodes.get(node) or self._new_node(node)
        n, i = len(cols.t), 0
        while i < n:
            at = st.n
            k = min(self._batch_size - at, n - i)
            dst, src = slice(at, at + k), slice(i, i + k)
            st.t[dst] = cols.t[src]
            _put_columns(st.measured[:, dst], cols.measured[src], cols.outputs, src)
            _put_columns(st.estimated[:, dst], cols.estimated[src], cols.predicted, src)
            st.gamma[dst] = cols.gamma[src]
            st.true_gamma[dst] = cols.true_gamma[src]
            st.rules[dst] = cols.rules[src]
            st.health[dst] = cols.state[src]
            st.mismatch[dst] = cols.model_mismatch[src]
            st.nis[dst] = cols.nis[src]
            st.n = at + k
            i += k
            if st.n == self._batch_size:
                self._flush_samples(st)
                self._note_part_full()

    def on_input_columns(self, node: int, t: Array, values: Array,
                         index: NDArray[np.int64]) -> None:
        """A node's inputs as columns (row i: input `index[i]`): `add_input` a slice at a
        time, each input into its own buffer."""
        if self._closed:
            return
        if self._part_due:
            self._next_part()
        st = self._nodes.get(node) or self._new_node(node)
        for a in np.unique(index).tolist():
            rows = index == a
            ta, va = t[rows], values[rows]
            buf = st.inputs.get(a) or self._new_input(st, a)
            n, i = len(ta), 0
            while i < n:
                at = buf.n
                k = min(self._batch_size - at, n - i)
                buf.t[at:at + k] = ta[i:i + k]
                buf.v[at:at + k] = va[i:i + k]
                buf.n = at + k
                i += k
                if buf.n == self._batch_size:
                    self._flush_input(buf)
                    self._note_part_full()

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
            st.last.clear()  # the new file starts its runs anew
            st.sent_t.clear()
            self._style_node(st)
        self._send_blueprint()

    def _note_part_full(self) -> None:
        """After a full batch: whether the current file has reached ``part_bytes``. The next
        part is opened by the next row added (`_next_part`), so none is left empty."""
        if self._part_bytes is None or self.rrd_path is None:
            return
        with suppress(OSError):
            self._part_due = self.rrd_path.stat().st_size >= self._part_bytes

    def _next_part(self) -> None:
        self._part_due = False
        first = self._parts[0]
        path = first.with_name(f"{first.stem}-part{len(self._parts) + 1:04d}{first.suffix}")
        try:
            self.switch_file(path)
        except (RuntimeError, OSError) as exc:
            _log.warning("rerun: cannot start the recording's next part %s (%s); recording "
                         "goes on into %s", path, exc, self.rrd_path)
            self._part_bytes = None
            return
        self._parts.append(path)

    @property
    def parts(self) -> tuple[Path, ...]:
        """The files recorded so far, in order (one unless ``part_bytes`` split them)."""
        return tuple(self._parts)

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def flush_interval_s(self) -> float:
        """`maybe_flush` sends the buffers once this long has passed since the last flush."""
        return self._flush_interval_s

    @property
    def nodes(self) -> tuple[int, ...]:
        """The nodes with a tab in the blueprint (announced or seen), in order of arrival."""
        return tuple(self._nodes)

    @property
    def recording(self) -> rr.RecordingStream:
        """The underlying explicit (non-global) recording stream."""
        return self._rec

    # -- internals --------------------------------------------------------------------------

    def _add_node(self, node: int) -> _Node:
        st = _Node(node, self._batch_size, self._out_parts)
        for index, part in enumerate(self._in_parts):  # styled with the node, like its outputs
            st.inputs[index] = _Input(node_path(node, part), self._batch_size)
        self._nodes[node] = st
        self._style_node(st)
        return st

    def _new_input(self, st: _Node, index: int) -> _Input:
        """The buffer of an input beyond the names given, at its first row (named by
        `signal_parts` too)."""
        if index >= len(self._in_parts):
            self._in_parts = signal_parts(self._signals, index + 1)[0]
        buf = _Input(node_path(st.node, self._in_parts[index]), self._batch_size)
        st.inputs[index] = buf
        self._style_input(buf, index)
        return buf

    def _style_node(self, st: _Node) -> None:
        for suffix, *_ in STYLES:
            if suffix != "gamma/true":  # styled when the first true gamma arrives
                self._style(st.path[suffix], suffix)
        for j, (measured, estimated) in enumerate(st.out_paths):
            signal = self._signals.output(j)
            self._log_static(measured, series_style(signal_legend(signal, "measured"),
                                                    MEASURED_COLOR, 1.0, False))
            self._log_static(estimated, series_style(signal_legend(signal, "estimated"),
                                                     ESTIMATED_COLOR, 1.5, False))
        for index, buf in st.inputs.items():
            self._style_input(buf, index)

    def _style_input(self, buf: _Input, index: int) -> None:
        self._log_static(buf.path, series_style(signal_legend(self._signals.input(index)),
                                                INPUT_COLOR, 1.0, False))

    def _style(self, path: str, suffix: str) -> None:
        _, name, color, width, stepped = next(s for s in STYLES if s[0] == suffix)
        style = series_style(name, color, width, stepped)
        if suffix in RUNS:
            self._log_static(path, style, _EXACT_LINE)
        else:
            self._log_static(path, style)

    def _log_static(self, path: str, *archetypes: Any) -> None:
        """A static row-wise ``log``: through the SDK's batcher, which the next `flush` pushes."""
        self._rec.log(path, *archetypes, static=True)
        self._rows_batched = True

    def _new_node(self, node: int) -> _Node:
        """A node not announced in ``nodes``: add it and resend the blueprint."""
        _log.info("rerun sink: new node %d", node)
        st = self._add_node(node)
        self._send_blueprint()
        return st

    def _send_blueprint(self) -> None:
        self._blueprints.send(default_blueprint(sorted(self._nodes), self._signals))

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
        for j, (measured, estimated) in enumerate(st.out_paths):
            send(measured, indexes=index, columns=scalars(scalars=st.measured[j, :n]))
            send(estimated, indexes=index, columns=scalars(scalars=st.estimated[j, :n]))
        send(path["gamma/estimate"], indexes=index, columns=scalars(scalars=st.gamma[:n]))
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

    def _send_runs(self, st: _Node, suffix: str, t: Array, v: Array) -> None:
        """Send the rows of a piecewise-constant series (`RUNS`) that draw its line: the
        first and the last row of every run of equal values (`run_ends`), and the batch's
        last row. That last row, when it only continues a run, is held back until the next
        batch unless `_RUN_TAIL_S` has passed since the series' last row was sent: small
        batches (0.1 s) then cost one row a second, not ten; the line's tail in a live view
        lags by up to that much, and `close` and `switch_file` send what was held back."""
        previous = st.last.get(suffix, math.nan)
        held = st.pending.pop(suffix, None)
        if held is not None:  # it may end its run: it goes first, to be judged with the rest
            t = np.concatenate(([held[0]], t))
            v = np.concatenate(([held[1]], v))
        keep = run_ends(v, previous)
        st.last[suffix] = float(v[-1])
        before = v[-2] if len(v) > 1 else previous
        kept = t[:-1][keep[:-1]]
        last_sent = kept[-1] if len(kept) else st.sent_t.get(suffix, -math.inf)
        if v[-1] == before and t[-1] - last_sent < _RUN_TAIL_S:
            keep[-1] = False
            st.pending[suffix] = (float(t[-1]), float(v[-1]))
        if keep.any():
            self._send_rows(st, suffix, t[keep], v[keep])

    def _send_rows(self, st: _Node, suffix: str, t: Array, v: Array) -> None:
        st.sent_t[suffix] = float(t[-1])
        self._rec.send_columns(
            st.path[suffix],
            indexes=[rr.TimeColumn(TIMELINE, timestamp=t)],
            columns=rr.Scalars.columns(scalars=v),
        )

    def _send_pending(self) -> None:
        """Send the rows `_send_runs` held back, so the lines reach the end of the data."""
        for st in self._nodes.values():
            for suffix, (t, v) in st.pending.items():
                self._send_rows(st, suffix, np.array([t]), np.array([v]))
            st.pending.clear()

    def _flush_input(self, buf: _Input) -> None:
        n = buf.n
        if n == 0:
            return
        buf.n = 0
        self._rec.send_columns(
            buf.path,
            indexes=[rr.TimeColumn(TIMELINE, timestamp=buf.t[:n])],
            columns=rr.Scalars.columns(scalars=buf.v[:n]),
        )


def _put(dst: Array, first: float, values: Sequence[float]) -> None:
    """One sample's outputs into a column of the output rows: `values` where given (as many
    as there are rows), else `first` into the first row and NaN into the others."""
    if len(values):
        k = min(len(values), len(dst))
        dst[:k] = values[:k]
        dst[k:] = math.nan
    else:
        dst[0] = first
        dst[1:] = math.nan


def _put_columns(dst: Array, first: Array, values: Array | None, rows: slice) -> None:
    """`_put` for a slice of samples: `values` (one column per output) where given, else
    `first`."""
    if values is not None and values.shape[1]:
        k = min(values.shape[1], len(dst))
        dst[:k] = values[rows, :k].T
        dst[k:] = math.nan
    else:
        dst[0] = first
        dst[1:] = math.nan
