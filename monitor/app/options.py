"""Command-line options shared by the commands: argument types (each refuses a bad value
with one line naming it), the options every monitoring command has, and what they build
(the database, the configuration)."""

from __future__ import annotations

import argparse
import math
from typing import NoReturn

from monitor.bus.codec import MotorDatabase, load_database
from monitor.bus.secoc import load_key
from monitor.diagnosis import DEFAULT_THRESHOLDS, Thresholds, load_thresholds
from monitor.pipeline import MonitorConfig

__all__ = ["OneLineParser", "add_monitor_options", "database", "monitor_config", "nodes",
           "positive_float", "rate"]


class OneLineParser(argparse.ArgumentParser):
    """argparse prints its usage block before an error: two lines. One is enough."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (v > 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"must be positive: {text!r}")
    return v


def rate(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid float value: {text!r}") from None
    if not (math.isfinite(v) and 0.0 < v <= 100_000.0):
        raise argparse.ArgumentTypeError(f"must be a rate in Hz, 0 < rate <= 100000: {text!r}")
    return v


def nodes(text: str) -> tuple[int, ...] | None:
    if text == "all":
        return None
    try:
        found = tuple(sorted({int(x) for x in text.split(",") if x.strip()}))
    except ValueError:
        raise argparse.ArgumentTypeError(f"nodes must be 'all' or e.g. 0,1,2: {text!r}") from None
    if not found or any(not 0 <= n <= 15 for n in found):
        raise argparse.ArgumentTypeError(f"node numbers must lie in 0..15: {text!r}")
    return found


def add_monitor_options(p: argparse.ArgumentParser) -> None:
    """The options of every command that monitors frames (run, replay)."""
    p.add_argument("--dbc", default=None, help="DBC file (default: the one shipped)")
    p.add_argument("--nodes", type=nodes, default=None,
                   help="nodes to monitor, e.g. 0,3 (default: all that send)")
    p.add_argument("--rate", type=rate, default=100.0, help="ECU current-sample rate, Hz")
    p.add_argument("--thresholds", default=None, help="thresholds TOML (motor-monitor calibrate)")
    p.add_argument("--key", default=None, metavar="FILE",
                   help="SecOC key (32 or 64 hex digits, mode 0600): reject unauthenticated frames")
    p.add_argument("--rrd", default=None, help="record to this .rrd file")
    p.add_argument("--connect", default=None, metavar="URL",
                   help="stream to a Rerun viewer, e.g. rerun+http://127.0.0.1:9876/proxy")


def database(args: argparse.Namespace) -> MotorDatabase:
    """The DBC, with SecOC verification when --key is given (a key file only we can read)."""
    key = load_key(args.key) if args.key else None
    return load_database(args.dbc, secoc_key=key)


def monitor_config(args: argparse.Namespace) -> MonitorConfig:
    thresholds: Thresholds = (load_thresholds(args.thresholds) if args.thresholds
                              else DEFAULT_THRESHOLDS)
    return MonitorConfig(nodes=args.nodes, rate=args.rate, thresholds=thresholds)
