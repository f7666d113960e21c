"""The summary table of an archive replay: one row per log and node (one row for a log
without nodes, or that could not be read), written as Parquet (pyarrow) and CSV.

Columns, in order:

* `log`: the log's path as found; `node`: the node (empty for a log without nodes or one
  that could not be read); `status`: `ok` or `failed`; `reason`: why a failed log could not be
  replayed (missing, unsupported, corrupt, ...) or is no success though it was read
  (damaged or cut short after its first frame: where, and the frames read before it, whose
  figures the row holds; nothing decoded: the counts by outcome and the likely cause);
* `frames`: frames read; `t_first`, `t_last`, `duration_s`: the log's first and last
  timestamps (bus time, s); `wall_s`: seconds its replay took;
* `seconds_<state>`: seconds the node spent in each health state (`fault_free`, `fault`,
  `outage`, `no_data`) between the log's first and last frame; a node is `no_data` until
  its first transition; `seconds_model_mismatch`: seconds its model-mismatch flag was up
  (beside the state, which it keeps);
* `transitions_count`, `transitions`: the node's health transitions, in Parquet a list of
  structs (`t`, `previous`, `state`, `cause`, `gamma`), in CSV the same list as JSON;
* `worst_nis`: the node's largest normalised innovation squared (empty without samples);
  `samples`: its estimated samples;
* `events`, `rrd`: the log's events (JSON lines) and recording, relative to the output
  directory; `rrd_parts`: the files the recording took (`rrd`, then ``<stem>-part0002.rrd``...
  beside it, one recording);
* then one column per pipeline counter (`frames/received`, `rejected/bad_crc`,
  `e2e/lost_frames`, ...), in name order: every frame's outcome, for the whole log (the
  pipeline counts per bus, not per node), 0 where a log has none.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from monitor.archive.result import STATES, LogResult

__all__ = ["COLUMNS", "summary_rows", "write_csv", "write_parquet"]

_TRANSITION = pa.struct([("t", pa.float64()), ("previous", pa.string()),
                         ("state", pa.string()), ("cause", pa.string()),
                         ("gamma", pa.float64())])

COLUMNS: tuple[tuple[str, pa.DataType], ...] = (
    ("log", pa.string()), ("node", pa.int64()), ("status", pa.string()),
    ("reason", pa.string()), ("frames", pa.int64()), ("t_first", pa.float64()),
    ("t_last", pa.float64()), ("duration_s", pa.float64()), ("wall_s", pa.float64()),
    *((f"seconds_{s}", pa.float64()) for s in STATES), ("seconds_model_mismatch", pa.float64()),
    ("transitions_count", pa.int64()), ("transitions", pa.list_(_TRANSITION)),
    ("worst_nis", pa.float64()), ("samples", pa.int64()),
    ("events", pa.string()), ("rrd", pa.string()), ("rrd_parts", pa.int64()),
)
"""The fixed columns; the counters follow, one int64 column each, in name order."""


def _relative(path: str | None, out: Path) -> str | None:
    return None if path is None else os.path.relpath(path, out)


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


def summary_rows(results: Sequence[LogResult], out: Path) -> tuple[list[dict[str, Any]],
                                                                   list[str]]:
    """The rows of the table and the counter columns' names."""
    counters = sorted({name for r in results for name in r.counters})
    rows: list[dict[str, Any]] = []
    for r in results:
        common: dict[str, Any] = {
            "log": r.log, "status": "ok" if r.ok else "failed", "reason": r.reason,
            "frames": r.frames, "t_first": r.t_first, "t_last": r.t_last,
            "duration_s": r.duration_s, "wall_s": r.wall_s,
            "events": _relative(r.events, out), "rrd": _relative(r.rrd, out),
            "rrd_parts": r.rrd_parts,
        }
        counts = {name: int(r.counters.get(name, 0)) for name in counters}
        if not r.nodes:
            rows.append({**common, "node": None, **{f"seconds_{s}": 0.0 for s in STATES},
                         "seconds_model_mismatch": 0.0,
                         "transitions_count": 0, "transitions": [], "worst_nis": None,
                         "samples": 0, **counts})
        for n in r.nodes:
            rows.append({
                **common, "node": n.node,
                **{f"seconds_{s}": n.seconds_in_state.get(s, 0.0) for s in STATES},
                "seconds_model_mismatch": n.seconds_model_mismatch,
                "transitions_count": len(n.transitions),
                "transitions": [{"t": tr.t, "previous": tr.previous, "state": tr.state,
                                 "cause": tr.cause, "gamma": tr.gamma}
                                for tr in n.transitions],
                "worst_nis": _finite(n.worst_nis), "samples": n.samples, **counts,
            })
    return rows, counters


def write_parquet(path: Path, rows: list[dict[str, Any]], counters: list[str]) -> None:
    schema = pa.schema([*COLUMNS, *((c, pa.int64()) for c in counters)])
    table = pa.Table.from_pylist(rows, schema=schema)
    pq.write_table(table, path)


def write_csv(path: Path, rows: list[dict[str, Any]], counters: list[str]) -> None:
    names = [name for name, _ in COLUMNS] + counters
    with open(path, "w", encoding="utf-8", newline="") as f:
        w = csv.DictWriter(f, fieldnames=names)
        w.writeheader()
        for row in rows:
            w.writerow({k: ("" if v is None else json.dumps(v, separators=(",", ":"))
                            if k == "transitions" else v) for k, v in row.items()})
