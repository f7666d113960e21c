"""Argument types of the command lines, each refusing a bad value with one line naming it, and
the parser that prints that one line. Nothing here imports the estimator: ``sim-ecu`` parses
its options with these and starts without numba (in a one-CPU User-Mode Linux guest, importing
it costs seconds of CPU beside a running daemon)."""

from __future__ import annotations

import argparse
import math
from typing import NoReturn, TypeVar

__all__ = ["OneLineParser", "add_monitor_options", "add_rig_option", "nodes", "positive_float",
           "positive_int", "rate"]

N = TypeVar("N", int, float)


class OneLineParser(argparse.ArgumentParser):
    """argparse prints its usage block before an error: two lines. One is enough."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def add_rig_option(p: argparse.ArgumentParser, *, model_optional: bool = False) -> None:
    """--rig; `model_optional`: the command learns the model (a rig file without [model] is
    taken, `monitor.setup.setup_rig(..., model_optional=True)`)."""
    what = ("your DBC, node layout and signals; its [model], if any, is replaced"
            if model_optional else "your DBC, node layout, signals and model")
    p.add_argument("--rig", default=None, metavar="FILE",
                   help=f"rig file: {what} (default: our bus and the paper's motor, "
                   "rigs/motor.toml)")


def _number(text: str, kind: type[N], refusal: str) -> N:
    """`text` read as `kind` (``int`` or ``float``), or the one line `refusal` naming it."""
    try:
        return kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{refusal}: {text!r}") from None


def positive_float(text: str) -> float:
    v = _number(text, float, "not a number")
    if not (v > 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"must be positive: {text!r}")
    return v


def positive_int(text: str) -> int:
    n = _number(text, int, "not a whole number")
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1: {text!r}")
    return n


def rate(text: str) -> float:
    """An output rate in Hz the monitor can use: the rig file's bounds (`rate_problem`)."""
    from monitor.rig.load import rate_problem  # the rig's rule, one place for both

    v = _number(text, float, "invalid float value")
    problem = rate_problem(v)
    if problem is not None:
        raise argparse.ArgumentTypeError(f"the rate {problem}")
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
