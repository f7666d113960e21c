"""Command-line options shared by the commands: argument types (each refuses a bad value
with one line naming it), the options every monitoring command has, and what they build
(the database, the configuration)."""

from __future__ import annotations

import argparse
import math
from dataclasses import replace
from pathlib import Path
from typing import NoReturn

from monitor.bus.codec import MotorDatabase
from monitor.bus.rigcodec import RigCodec
from monitor.bus.secoc import load_key
from monitor.diagnosis import Thresholds, load_thresholds
from monitor.pipeline import MonitorConfig
from monitor.rig import Rig, build_decoder, build_model, builtin_rig, load_rig

__all__ = ["OneLineParser", "add_monitor_options", "add_rig_option", "database",
           "monitor_config", "nodes", "positive_float", "positive_int", "rate", "rig"]


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


def positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1: {text!r}")
    return n


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


def add_rig_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rig", default=None, metavar="FILE",
                   help="rig file: your DBC, node layout, signals and model (default: our "
                   "bus and the paper's motor, rigs/motor.toml)")


def add_monitor_options(p: argparse.ArgumentParser) -> None:
    """The options of every command that monitors frames (run, replay)."""
    add_rig_option(p)
    p.add_argument("--dbc", default=None, help="DBC file (default: the rig's)")
    p.add_argument("--nodes", type=nodes, default=None,
                   help="nodes to monitor, e.g. 0,3 (default: the rig's, else all that send)")
    p.add_argument("--rate", type=rate, default=None,
                   help="the output message's nominal rate, Hz (default: the rig's)")
    p.add_argument("--thresholds", default=None, help="thresholds TOML (motor-monitor calibrate)")
    p.add_argument("--key", default=None, metavar="FILE",
                   help="SecOC key (32 or 64 hex digits, mode 0600): reject unauthenticated frames")
    p.add_argument("--rrd", default=None, help="record to this .rrd file")
    p.add_argument("--connect", default=None, metavar="URL",
                   help="stream to a Rerun viewer, e.g. rerun+http://127.0.0.1:9876/proxy")


def rig(args: argparse.Namespace) -> Rig:
    """--rig, else the built-in rig; --dbc replaces its DBC files."""
    found = load_rig(args.rig) if getattr(args, "rig", None) else builtin_rig()
    dbc = getattr(args, "dbc", None)
    return replace(found, dbc=(Path(dbc),)) if dbc else found


def database(args: argparse.Namespace, the_rig: Rig | None = None) -> MotorDatabase | RigCodec:
    """The rig's frame decoder, with SecOC verification when --key is given (a key file
    only we can read; our own bus only)."""
    key = load_key(args.key) if getattr(args, "key", None) else None
    return build_decoder(the_rig or rig(args), secoc_key=key)


def monitor_config(args: argparse.Namespace, the_rig: Rig | None = None) -> MonitorConfig:
    """The monitor's configuration: the rig's, with the command line's overrides."""
    r = the_rig or rig(args)
    d = r.diagnosis
    thresholds = (load_thresholds(args.thresholds) if getattr(args, "thresholds", None)
                  else Thresholds(d.f1, d.f2))
    return MonitorConfig(
        nodes=args.nodes if getattr(args, "nodes", None) is not None else r.nodes,
        rate=args.rate if getattr(args, "rate", None) is not None else r.rate,
        thresholds=thresholds, dwell_s=d.dwell_s, hysteresis=d.hysteresis,
        silence_timeout_s=d.silence_timeout_s, model=build_model(r),
        mismatch_window_s=d.mismatch_window_s, mismatch_dwell_s=d.mismatch_dwell_s)
