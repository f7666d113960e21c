"""`motor-monitor calibrate`: thresholds F1 < F2 (76) by fuzzy c-means (55)-(62) on gamma^.

The samples come from a capture replayed through the monitor (candump .log, .asc, .blf; one
or more files, with the rig of the bus they were recorded on) or from a text/CSV file of
gamma^ values (first column). The run must visit all three regimes: fault-free, fault and
outage. The thresholds go to --out (./thresholds.toml by default), checked before any sample
is read (`monitor.runtime.paths`: never an input; a file calibrate did not write only with
--force) and written atomically.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from monitor.app import options
from monitor.bus.logfile import log_format, suffix_list
from monitor.diagnosis import calibrate, save_thresholds
from monitor.errors import UsageError, one_line
from monitor.files import MIB, read_user_text, shown_path
from monitor.pipeline import MonitorPipeline, Sample
from monitor.pipeline.counters import Counters, nothing_decoded
from monitor.pipeline.feed import replay_frames
from monitor.runtime.paths import Output, check_outputs, monitor_inputs
from monitor.sinks.base import Sink

__all__ = ["GAMMA_FILE_LIMIT", "add_command", "gamma_of_captures", "read_gamma_file"]


class _GammaSamples(Sink):
    def __init__(self) -> None:
        self.values: list[float] = []

    def on_sample(self, sample: Sample) -> None:
        self.values.append(sample.gamma)


def gamma_of_captures(args: argparse.Namespace, paths: list[Path]) -> np.ndarray:
    """gamma^ of every estimated sample of the captures, replayed with the rig's monitor;
    `UsageError` with the counts by outcome and the likely cause when there is none."""
    rig = options.rig(args)
    values: list[float] = []
    counters = Counters()
    samples: dict[int, int] = {}
    cfg = options.monitor_config(args, rig)
    for path in paths:
        db = options.database(args, rig)  # fresh counters and freshness per capture
        collect = _GammaSamples()
        pipe = MonitorPipeline(db, cfg, sink=collect)
        replay_frames(pipe, path)
        values += collect.values
        for name, n in pipe.counters.items():
            counters.inc(name, n)
        for node, nm in pipe.nodes.items():
            samples[node] = samples.get(node, 0) + nm.samples
    if not values:
        line = nothing_decoded(counters, samples, cfg.nodes) or "0 samples"
        raise UsageError(f"{', '.join(p.name for p in paths)}: {line}")
    return np.asarray(values, dtype=float)


GAMMA_FILE_LIMIT = 256 * MIB
"""The largest gamma^ text file read: some 15 million samples, two days of a node at 100 Hz."""


def read_gamma_file(path: Path) -> np.ndarray:
    """The gamma^ samples of a text/CSV file: the first column of each line ("," between
    columns), "#" starting a comment, blank lines skipped. Read as every file a user names
    is (`monitor.files.read_user_text`); a file without a sample, or a first column that is
    not a finite number, is one `UsageError` line naming the file and the line."""
    text = read_user_text(path, what="gamma^ file", limit=GAMMA_FILE_LIMIT)
    values: np.ndarray | None = None
    try:  # numpy's parser first: fast, and right for every well-formed file
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "input contained no data": said below, once
            values = np.loadtxt(io.StringIO(text), dtype=float, ndmin=1, comments="#",
                                delimiter=",", usecols=0)
    except ValueError:
        pass
    if values is None or not np.isfinite(values).all():
        values = _gamma_lines(text, shown_path(path))
    if values.size == 0:
        raise UsageError(f"gamma^ file {shown_path(path)}: no gamma^ samples in it (one "
                         "number per line, or CSV with gamma^ in the first column)")
    return values


def _gamma_lines(text: str, shown: str) -> np.ndarray:
    """`read_gamma_file`'s samples line by line: slower than numpy, which counts data rows
    from 0 and names no line, but says on which line of the file a sample is wrong."""
    values: list[float] = []
    for number, line in enumerate(text.split("\n"), 1):
        data = line.split("#", 1)[0]
        if not data.strip():
            continue
        field = data.split(",", 1)[0].strip()
        try:
            value = float(field)
        except ValueError:
            raise UsageError(f"gamma^ file {shown}: line {number}: "
                             f"{one_line(repr(field), limit=40)} is not a number") from None
        if not math.isfinite(value):
            raise UsageError(f"gamma^ file {shown}: line {number}: gamma^ must be a finite "
                             f"number, got {value!r}")
        values.append(value)
    return np.asarray(values, dtype=float)


def _cmd_calibrate(args: argparse.Namespace) -> int:
    paths = [Path(p) for p in args.inputs]
    captures = [p for p in paths if log_format(p) is not None]
    if captures and len(captures) != len(paths):
        raise UsageError(f"give bus captures ({suffix_list()}) or one gamma^ text file, "
                         "not both")
    config = monitor_inputs(options.rig(args), args) if captures else []
    check_outputs([*(("CAPTURE" if captures else "GAMMA_FILE", p) for p in paths), *config],
                  [Output("--out", Path(args.out), "thresholds")], force=args.force)
    if captures:
        values = gamma_of_captures(args, captures)
        source = ", ".join(p.name for p in captures)
    else:
        if len(paths) != 1:
            raise UsageError("give one gamma^ text file (or bus captures)")
        values = read_gamma_file(paths[0])
        source = str(paths[0])
    th = calibrate(values)
    save_thresholds(args.out, th, source=source)
    print(json.dumps({"f1": th.f1, "f2": th.f2, "centres": list(th.centres),
                      "samples": int(values.size)}))
    return 0


def add_command(sub: argparse._SubParsersAction[Any]) -> None:
    c = sub.add_parser("calibrate", help="learn thresholds F1 < F2 from a capture replayed "
                       "through the monitor, or from gamma^ samples")
    c.add_argument("inputs", nargs="+", metavar="CAPTURE|GAMMA_FILE",
                   help=f"bus captures ({suffix_list()}) of a run with fault-free, fault and "
                   "outage periods; or a text/CSV file, gamma^ in the first column")
    c.add_argument("--out", default="thresholds.toml", metavar="FILE",
                   help="the thresholds file to write, never one of the inputs (default: "
                   "%(default)s in the current directory)")
    c.add_argument("--force", action="store_true",
                   help="replace --out even if motor-monitor did not write it (without it, "
                   "only a thresholds file calibrate wrote is replaced)")
    options.add_rig_option(c)
    c.add_argument("--nodes", type=options.nodes, default=None, help="nodes to use")
    c.set_defaults(func=_cmd_calibrate, dbc=None, rate=None, thresholds=None, key=None)
