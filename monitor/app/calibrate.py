"""`motor-monitor calibrate`: thresholds F1 < F2 (76) by fuzzy c-means (55)-(62) on gamma^.

The samples come from a capture replayed through the monitor (candump .log, .asc, .blf; one
or more files, with the rig of the bus they were recorded on) or from a text/CSV file of
gamma^ values (first column). The run must visit all three regimes: fault-free, fault and
outage.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from monitor.app import options
from monitor.app.replay import LOG_SUFFIXES, replay_frames
from monitor.diagnosis import calibrate, save_thresholds
from monitor.errors import UsageError
from monitor.pipeline import MonitorPipeline, Sample
from monitor.sinks.base import Sink

__all__ = ["add_command", "gamma_of_captures"]


class _GammaSamples(Sink):
    def __init__(self) -> None:
        self.values: list[float] = []

    def on_sample(self, sample: Sample) -> None:
        self.values.append(sample.gamma)


def gamma_of_captures(args: argparse.Namespace, paths: list[Path]) -> np.ndarray:
    """gamma^ of every estimated sample of the captures, replayed with the rig's monitor."""
    rig = options.rig(args)
    values: list[float] = []
    for path in paths:
        db = options.database(args, rig)  # fresh counters and freshness per capture
        collect = _GammaSamples()
        pipe = MonitorPipeline(db, options.monitor_config(args, rig), sink=collect)
        replay_frames(pipe, path)
        values += collect.values
    return np.asarray(values, dtype=float)


def _cmd_calibrate(args: argparse.Namespace) -> int:
    paths = [Path(p) for p in args.inputs]
    captures = [p for p in paths if p.suffix.lower() in LOG_SUFFIXES]
    if captures and len(captures) != len(paths):
        raise UsageError("give bus captures (.log, .asc, .blf) or one gamma^ text file, not both")
    if captures:
        values = gamma_of_captures(args, captures)
        source = ", ".join(p.name for p in captures)
        if values.size == 0:
            raise UsageError(f"{source}: no sample was estimated (is --rig the rig the capture "
                             "was recorded on?)")
    else:
        if len(paths) != 1:
            raise UsageError("give one gamma^ text file (or bus captures)")
        try:
            values = np.loadtxt(paths[0], dtype=float, ndmin=1, comments="#", delimiter=",",
                                usecols=0)
        except (OSError, ValueError) as exc:
            raise UsageError(f"{paths[0]}: cannot read gamma^ samples ({exc})") from None
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
                   help="bus captures (.log, .asc, .blf) of a run with fault-free, fault and "
                   "outage periods; or a text/CSV file, gamma^ in the first column")
    c.add_argument("--out", default="thresholds.toml")
    options.add_rig_option(c)
    c.add_argument("--nodes", type=options.nodes, default=None, help="nodes to use")
    c.set_defaults(func=_cmd_calibrate, dbc=None, rate=None, thresholds=None, key=None)
