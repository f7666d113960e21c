"""The daemon's ``.rrd`` recordings read back: every Scalars series (`read_rrd`, `series`),
the counters it logs about once per second of bus time (`Snapshots`) and what those
counters say about the frames (`outcome_total`, `bad_outcomes`)."""

from __future__ import annotations

import shutil
import tempfile
import warnings
from collections import defaultdict
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray
from rerun.chunk import Chunk, RrdReader

# NOTE: salvage_rrd lives in monitor.sinks.salvage; if it moves, this import is the only
# line to change.
from monitor.sinks.salvage import salvage_rrd
from tests.support import BIN

__all__ = [
    "BAD_OUTCOMES",
    "COUNTERS_PREFIX",
    "OUTCOME_PREFIXES",
    "RERUN_EXE",
    "Array",
    "Snapshots",
    "bad_outcomes",
    "blueprint_names",
    "chunk_series",
    "entity_chunks",
    "outcome_total",
    "read_rrd",
    "recording_rows",
    "series",
]

Array = NDArray[np.float64]

RERUN_EXE = BIN / "rerun"  # `rerun rrd verify`

#: Outcome counters of the daemon that a genuine ECU never moves: a bad kind must move only
#: its own ones (prefixes).
BAD_OUTCOMES = ("rejected/", "ignored/", "bus/error_frames", "bus/errors/", "e2e/repeated",
                "time/non_monotonic")
#: Counters that together count every received frame exactly once (at each snapshot).
OUTCOME_PREFIXES = ("rejected/", "ignored/", "bus/error_frames", "e2e/repeated",
                    "time/non_monotonic", "samples/no_input", "samples/estimated",
                    "samples/input", "samples/truth")

COUNTERS_PREFIX = "/monitor/counters/"


def read_rrd(path: Path) -> dict[str, tuple[Array, Array]]:
    """(time [s], value) of every Scalars entity of an .rrd file, sorted by time. A file of a
    killed writer is read from a copy, salvaged if its last message is torn."""
    def read(p: Path) -> dict[str, tuple[Array, Array]]:
        ts: dict[str, list[NDArray[np.int64]]] = {}
        vs: dict[str, list[Array]] = {}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # no footer: a warning
            for chunk in RrdReader(p).stream():
                if chunk.is_static:
                    continue
                rb = chunk.to_record_batch()
                if "Scalars:scalars" not in rb.schema.names or "time" not in rb.schema.names:
                    continue
                ts.setdefault(chunk.entity_path, []).append(
                    rb.column("time").cast(pa.int64()).to_numpy())
                vs.setdefault(chunk.entity_path, []).append(
                    rb.column("Scalars:scalars").flatten().to_numpy())
        out: dict[str, tuple[Array, Array]] = {}
        for e in ts:
            t, v = np.concatenate(ts[e]), np.concatenate(vs[e])
            order = np.argsort(t, kind="stable")
            out[e] = (t[order] / 1e9, v[order].astype(np.float64))
        return out

    try:
        return read(path)
    except RuntimeError:
        with tempfile.TemporaryDirectory() as tmp:
            copy = Path(tmp) / path.name
            shutil.copyfile(path, copy)
            salvage_rrd(copy)
            return read(copy)


def series(rrd: Mapping[str, tuple[Array, Array]], entity: str) -> tuple[Array, Array]:
    return rrd.get(entity, (np.zeros(0), np.zeros(0)))


@dataclass
class Snapshots:
    """The daemon's counters as logged into the .rrd: `t[i]` and each counter at `t[i]`."""

    t: Array
    values: dict[str, NDArray[np.int64]]

    @classmethod
    def from_rrd(cls, rrd: Mapping[str, tuple[Array, Array]]) -> Snapshots:
        cols = {e[len(COUNTERS_PREFIX):]: tv for e, tv in rrd.items()
                if e.startswith(COUNTERS_PREFIX)}
        t = np.unique(np.concatenate([tv[0] for tv in cols.values()])) if cols else np.zeros(0)
        values: dict[str, NDArray[np.int64]] = {}
        for name, (ct, cv) in cols.items():
            col = np.zeros(len(t), dtype=np.int64)
            idx = np.searchsorted(t, ct)
            col[idx] = np.round(cv).astype(np.int64)  # absent from a row: did not exist yet
            values[name] = col
        return cls(t, values)

    def __len__(self) -> int:
        return len(self.t)

    def at(self, i: int) -> dict[str, int]:
        return {k: int(v[i]) for k, v in self.values.items() if v[i]}

    def last_before(self, t: float) -> int | None:
        i = int(np.searchsorted(self.t, t, side="left")) - 1
        return i if i >= 0 else None

    def first_after(self, t: float) -> int | None:
        i = int(np.searchsorted(self.t, t, side="right"))
        return i if i < len(self.t) else None

    def delta(self, i: int | None, j: int | None) -> dict[str, int]:
        """Counters that changed from snapshot i (None: the start) to snapshot j."""
        if j is None:
            return {}
        a = {} if i is None else self.at(i)
        b = self.at(j)
        return {k: b.get(k, 0) - a.get(k, 0) for k in set(a) | set(b)
                if b.get(k, 0) != a.get(k, 0)}



def blueprint_names(path: Path) -> set[str]:
    """The display names (tabs and views) of every blueprint an .rrd file holds."""
    reader = RrdReader(path)
    names: set[str] = set()
    for bp in reader.blueprints():
        for chunk in reader.stream(store=bp):
            rb = chunk.to_record_batch()
            for col in rb.schema.names:
                if col.endswith("Blueprint:display_name"):
                    names.update(x for row in rb.column(col).to_pylist() if row for x in row)
    return names

def _among(name: str, prefixes: tuple[str, ...]) -> bool:
    """`name` is one of `prefixes`, or lies under one that ends in "/"."""
    return any(name == p or (p.endswith("/") and name.startswith(p)) for p in prefixes)


def outcome_total(c: Mapping[str, int]) -> int:
    """Frames accounted for by the outcome counters (each frame in exactly one of them)."""
    return sum(v for k, v in c.items() if _among(k, OUTCOME_PREFIXES))


def bad_outcomes(c: Mapping[str, int]) -> dict[str, int]:
    return {k: v for k, v in c.items() if v and _among(k, BAD_OUTCOMES)}


def entity_chunks(path: Path) -> dict[str, list[Chunk]]:
    """Chunks of the recording in file order, grouped by entity path (temporal only)."""
    out: dict[str, list[Chunk]] = defaultdict(list)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a file without footer warns (live test)
        reader = RrdReader(path)
        for chunk in reader.stream():
            if not chunk.is_static:
                out[chunk.entity_path].append(chunk)
    return out


def chunk_series(chunks: list[Chunk]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(time [s], value) of a Scalars entity, sorted by time."""
    ts: list[NDArray[np.int64]] = []
    vs: list[NDArray[np.float64]] = []
    for chunk in chunks:
        rb = chunk.to_record_batch()
        t = rb.column("time").cast(pa.int64()).to_numpy()
        v = rb.column("Scalars:scalars").flatten().to_numpy()
        assert len(t) == len(v) == chunk.num_rows  # one scalar per row
        ts.append(t)
        vs.append(v)
    if not ts:
        return np.zeros(0), np.zeros(0)
    t_all = np.concatenate(ts)
    v_all = np.concatenate(vs)
    order = np.argsort(t_all, kind="stable")
    return t_all[order] / 1e9, v_all[order]


def _plain(col: pa.Array) -> pa.Array:
    """Time stamps as their integer nanoseconds (a datetime would drop them)."""
    return col.cast(pa.int64()) if pa.types.is_timestamp(col.type) else col


def recording_rows(path: Path) -> dict[tuple[str, bool], list[str]]:
    """Every row of every store of a recording (its row id, times and components), per
    entity, in a canonical order: what compaction must keep."""
    out: dict[tuple[str, bool], list[str]] = defaultdict(list)
    reader = RrdReader(path)
    for store in [*reader.recordings(), *reader.blueprints()]:
        for chunk in reader.stream(store=store):
            rb = chunk.to_record_batch()
            columns = {name: _plain(rb.column(name)).to_pylist() for name in rb.schema.names}
            for i in range(chunk.num_rows):
                out[(chunk.entity_path, chunk.is_static)].append(
                    repr(sorted((name, col[i]) for name, col in columns.items())))
    return {key: sorted(rows) for key, rows in out.items()}
