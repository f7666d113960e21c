"""Every estimated sample to one file, Parquet or CSV, for pandas or MATLAB (`replay
--samples FILE`): one row per estimator step of a node.

Columns, in order (`SampleTable.names`); a name is a MATLAB identifier (letters, digits,
underscores, a letter first), so `readtable`/`parquetread` keep it as it is and pandas takes
it as an attribute name; the unit, where there is one, is the name's last part:

* ``t_s``: the sample's bus time (s); ``node``: the node;
* ``u_<Input>_<unit>``: each input as held at the sample (the estimator's input);
* ``y_<Output>_<unit>``: each output as measured;
* ``yhat_<Output>_<unit>``: each output of the estimate after the sample's update,
  C x^ + D u (1 - gamma^);
* ``gamma_<Input>``: gamma^, the estimated loss of effectiveness of each input that may
  lose it (the model's fault inputs; a known input has none);
* ``f_<Input>_<unit>``: f^ = gamma^ u, the part of that input the fault takes away, in the
  input's unit (what the diagnosis reports as `fault_input` for the worst one);
* ``gamma_sd``: the standard deviation of the largest gamma^, the one the diagnosis reads
  (what `[diagnosis] significance` weighs an alarm by);
* ``noise_<Output>``: each output's noise variance as the estimator has adapted it, a
  multiple of the model's (1: the model's noise fits; above 1: the sensor is noisier than
  the model says);
* ``process_noise``: the factor the estimator has put on the model's process noise (1 to
  100; far above 1: the model misses dynamics, and the estimator is less sensitive to a
  loss);
* ``nis``: the normalised innovation squared; ``state``: the reported health state
  (``fault_free``, ``fault``, ...); ``model_mismatch``: the model-mismatch flag beside it
  (Parquet: a boolean; CSV: 1 or 0).

`<Input>`/`<Output>` is the rig's DBC signal name, `<unit>` the unit the rig gives it (else
its DBC's, else the model's), written with letters, digits and underscores: ``/`` becomes
``_per_``, ``%`` ``pct``, ``°`` ``deg``, anything else ``_`` (``rad/s`` -> ``rad_per_s``).
A signal without a unit has no unit part. The Parquet file keeps each column's unit and
signal as written in its field metadata (``unit``, ``signal``) and says it is motor-monitor's
in its key-value metadata (`PARQUET_KEY`); the CSV header is the names (a number without
a value, e.g. a NIS that is not finite, is an empty field: NaN to both readers).

The file is written in bounded memory, `batch_rows` rows at a time (a Parquet row group, a
CSV append), into a temporary file beside it that replaces it when the sink is closed
(`monitor.files.atomic_replace`): a reader never sees half a file. Rows come in the order
the replay hands them over: each node's in time order; sort by ``t_s`` and ``node`` for one
timeline (the columnar and the per-frame engine interleave nodes differently).
"""

from __future__ import annotations

import contextlib
import csv
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from numpy.typing import NDArray

from monitor.diagnosis.classifier import HealthState
from monitor.errors import MonitorError
from monitor.files import atomic_replace, shown_path
from monitor.pipeline.events import Sample, SampleColumns
from monitor.sinks.base import Sink

__all__ = ["BATCH_ROWS", "CSV_FIRST", "CSV_LAST", "PARQUET_KEY", "SUFFIXES", "SampleTable",
           "SamplesFileSink", "column_token"]

SUFFIXES = (".parquet", ".csv")
"""The formats, by the file's suffix."""

BATCH_ROWS = 65536
"""Rows buffered before they are written (a Parquet row group)."""

PARQUET_KEY = b"motor_monitor.samples"
"""The key-value metadata key of a samples Parquet file (its value: the format version)."""
_VERSION = b"2"
"""The columns' version: 2 has the noise factors (``noise_<Output>``, ``process_noise``)
that 1 lacks; a reader tells them apart by this or by the names."""

CSV_FIRST = "t_s,node,"
CSV_LAST = ",nis,state,model_mismatch"
"""How a samples CSV header begins and ends (how `monitor.runtime.paths` recognises one)."""

_STATE_LABELS = np.array([s.label for s in HealthState], dtype=object)

_UNIT_WORDS = (("/", "_per_"), ("%", "pct"), ("°", "deg"), ("µ", "u"), ("μ", "u"),
               ("Ω", "Ohm"), ("²", "2"), ("³", "3"), ("^", ""), ("*", "_"), ("·", "_"))


def column_token(text: str) -> str:
    """`text` (a signal name or a unit) as a part of a column name: letters, digits and
    single underscores, so that the whole name stays a MATLAB identifier."""
    for a, b in _UNIT_WORDS:
        text = text.replace(a, b)
    text = re.sub(r"[^A-Za-z0-9_]", "_", text)
    return re.sub(r"_+", "_", text).strip("_")


@dataclass(frozen=True)
class SampleTable:
    """What a samples file's columns are named after: the rig's inputs and outputs, as
    (DBC signal name, unit or None), in the model's order, and the inputs that may lose
    effectiveness (`DiscreteModel.fault_inputs`)."""

    inputs: tuple[tuple[str, str | None], ...]
    outputs: tuple[tuple[str, str | None], ...]
    fault_inputs: tuple[int, ...]

    def _name(self, role: str, signal: str, unit: str | None) -> str:
        token = column_token(signal) or "signal"
        u = column_token(unit) if unit else ""
        return f"{role}_{token}" + (f"_{u}" if u else "")

    def columns(self) -> list[tuple[str, pa.DataType, str | None, str | None]]:
        """(name, type, unit, signal) of every column, in order; a name two signals would
        share gets ``_2``, ``_3``... so that each is unique."""
        cols: list[tuple[str, pa.DataType, str | None, str | None]] = [
            ("t_s", pa.float64(), "s", None), ("node", pa.int64(), None, None)]
        for role, refs in (("u", self.inputs), ("y", self.outputs), ("yhat", self.outputs)):
            cols += [(self._name(role, s, u), pa.float64(), u, s) for s, u in refs]
        cols += [(self._name("gamma", self.inputs[j][0], None), pa.float64(), None,
                  self.inputs[j][0]) for j in self.fault_inputs]
        cols += [(self._name("f", *self.inputs[j]), pa.float64(), self.inputs[j][1],
                  self.inputs[j][0]) for j in self.fault_inputs]
        cols += [("gamma_sd", pa.float64(), None, None)]
        cols += [(self._name("noise", s, None), pa.float64(), None, s)
                 for s, _ in self.outputs]
        cols += [("process_noise", pa.float64(), None, None),
                 ("nis", pa.float64(), None, None), ("state", pa.string(), None, None),
                 ("model_mismatch", pa.bool_(), None, None)]
        seen: dict[str, int] = {}
        unique = []
        for name, typ, unit, sig in cols:
            n = seen[name] = seen.get(name, 0) + 1
            unique.append((name if n == 1 else f"{name}_{n}", typ, unit, sig))
        return unique

    def names(self) -> list[str]:
        return [c[0] for c in self.columns()]

    def schema(self) -> pa.Schema:
        """The Parquet schema: units and signals in the fields' metadata."""
        fields = []
        for name, typ, unit, sig in self.columns():
            meta = {k: v for k, v in (("unit", unit), ("signal", sig)) if v is not None}
            fields.append(pa.field(name, typ, metadata=meta or None))
        return pa.schema(fields, metadata={PARQUET_KEY: _VERSION})


def _matrix(rows: Sequence[tuple[float, ...]], width: int) -> NDArray[np.float64]:
    """Rows of a tuple field as a (len, width) array; NaN where a producer filled none."""
    out = np.full((len(rows), width), np.nan)
    for i, r in enumerate(rows):
        if r:
            out[i] = r
    return out


class SamplesFileSink(Sink):
    """Every sample (`on_sample`, or `on_sample_columns` from the columnar replay) to a
    Parquet or CSV file at `path` (by its suffix), replaced when the sink closes. Raises
    `MonitorError` (one line naming `path`) when the file cannot be written."""

    def __init__(self, path: str | Path, table: SampleTable, *,
                 batch_rows: int = BATCH_ROWS) -> None:
        self.path = Path(path)
        self.table = table
        self.batch_rows = batch_rows
        self._cols = table.columns()
        self._schema = table.schema()
        suffix = self.path.suffix.lower()
        if suffix not in SUFFIXES:
            raise MonitorError(f"samples file {shown_path(self.path)}: the suffix must be "
                               f".parquet or .csv, not {suffix or 'none'!r}")
        self._parquet = suffix == ".parquet"
        self._rows: list[Sample] = []
        self._chunks: list[tuple[int, SampleColumns]] = []
        self._buffered = 0
        self.written = 0
        self._closed = False
        self._stack = contextlib.ExitStack()
        self._writer: pq.ParquetWriter | None = None
        self._file: IO[str] | None = None
        self._csv: Any = None
        try:
            tmp = self._stack.enter_context(atomic_replace(self.path))
            if self._parquet:
                self._writer = pq.ParquetWriter(tmp, self._schema)
            else:
                self._file = self._stack.enter_context(
                    open(tmp, "w", encoding="utf-8", newline=""))  # noqa: SIM115 (the stack closes it)
                self._csv = csv.writer(self._file, lineterminator="\n")
                self._csv.writerow([c[0] for c in self._cols])
        except OSError as exc:
            self._abort(exc)
            raise self._cannot(exc) from None

    def _cannot(self, exc: OSError) -> MonitorError:
        # exc's own text names the temporary file: only its reason is shown
        return MonitorError(f"samples file {shown_path(self.path)}: cannot write "
                            f"({exc.strerror or type(exc).__name__})")

    def _abort(self, exc: BaseException) -> None:
        """Drop the temporary file; `path` stays as it was."""
        self._closed = True
        with contextlib.suppress(Exception):
            if self._writer is not None:
                self._writer.close()
        with contextlib.suppress(OSError):
            self._stack.__exit__(type(exc), exc, exc.__traceback__)

    # ------------------------------------------------------------------ samples in

    def on_sample(self, sample: Sample) -> None:
        if self._closed:
            return
        self._rows.append(sample)
        self._buffered += 1
        if self._buffered >= self.batch_rows:
            self.flush()

    def on_sample_columns(self, node: int, cols: SampleColumns) -> None:
        """The columnar replay's samples, a node's chunk at a time."""
        if self._closed or not len(cols.t):
            return
        self._chunks.append((node, cols))
        self._buffered += len(cols.t)
        if self._buffered >= self.batch_rows:
            self.flush()

    def on_input_columns(self, node: int, t: NDArray[np.float64], values: NDArray[np.float64],
                         index: NDArray[np.int64]) -> None:
        """Inputs alone are not samples: each row holds the inputs held at its sample."""

    # ------------------------------------------------------------------ out

    def _arrays(self) -> list[NDArray[Any]]:
        """The buffered rows as one array per column (rows first, then chunks: one sink is
        fed one way or the other)."""
        m, p = len(self.table.inputs), len(self.table.outputs)
        parts: list[tuple[NDArray[Any], ...]] = []
        if self._rows:
            rs = self._rows
            parts.append((
                np.array([r.t for r in rs]), np.array([r.node for r in rs], np.int64),
                _matrix([r.inputs for r in rs], m), _matrix([r.outputs for r in rs], p),
                _matrix([r.predicted for r in rs], p), _matrix([r.gammas for r in rs], m),
                np.array([r.gamma_sd for r in rs]), _matrix([r.output_noise for r in rs], p),
                np.array([r.process_noise for r in rs]), np.array([r.nis for r in rs]),
                np.array([r.state.label for r in rs], dtype=object),
                np.array([bool(getattr(r, "model_mismatch", False)) for r in rs]),
            ))
        for node, c in self._chunks:
            n = len(c.t)

            def full(a: NDArray[np.float64] | None, width: int, n: int = n) -> NDArray[Any]:
                return np.full((n, width), np.nan) if a is None else a

            mm = getattr(c, "model_mismatch", None)
            parts.append((
                c.t, np.full(n, node, np.int64), full(c.inputs, m), full(c.outputs, p),
                full(c.predicted, p), full(c.gammas, m),
                np.full(n, np.nan) if c.gamma_sd is None else c.gamma_sd,
                full(c.output_noise, p),
                np.full(n, np.nan) if c.process_noise is None else c.process_noise, c.nis,
                _STATE_LABELS[c.state],
                np.zeros(n, np.bool_) if mm is None else np.asarray(mm, np.bool_),
            ))
        t, nodes, u, y, yh, g, gsd, on, pn, nis, state, flag = (
            np.concatenate(x) for x in zip(*parts, strict=True))
        fi = list(self.table.fault_inputs)
        gf = g[:, fi]
        return [t, nodes, *u.T, *y.T, *yh.T, *gf.T, *(gf * u[:, fi]).T, gsd, *on.T, pn, nis,
                state, flag]

    def flush(self) -> None:
        """Write the buffered rows: one Parquet row group, or CSV lines."""
        if self._closed or not self._buffered:
            return
        arrays = self._arrays()
        self._rows, self._chunks, n, self._buffered = [], [], self._buffered, 0
        try:
            if self._writer is not None:
                table = pa.Table.from_arrays(
                    [pa.array(a, type=typ) for a, (_, typ, _, _) in
                     zip(arrays, self._cols, strict=True)], schema=self._schema)
                self._writer.write_table(table, row_group_size=self.batch_rows)
            else:
                self._csv.writerows(zip(*(self._csv_column(a) for a in arrays), strict=True))
        except OSError as exc:
            self._abort(exc)
            raise self._cannot(exc) from None
        self.written += n

    @staticmethod
    def _csv_column(a: NDArray[Any]) -> list[Any]:
        values = a.tolist()
        if a.dtype.kind == "f":  # a value that is not finite: an empty field (missing)
            return ["" if not math.isfinite(v) else v for v in values]
        if a.dtype.kind == "b":  # 1/0: a number to MATLAB's readtable, not a word
            return [int(v) for v in values]
        return values

    def close(self) -> None:
        """Write what is buffered, then put the file in place."""
        if self._closed:
            return
        try:
            self.flush()
            self._closed = True
            if self._writer is not None:
                self._writer.close()
        except BaseException as exc:
            self._abort(exc)
            if isinstance(exc, OSError):
                raise self._cannot(exc) from None
            raise
        try:
            self._stack.close()  # the CSV file closed, fsync, rename
        except OSError as exc:
            raise self._cannot(exc) from None
