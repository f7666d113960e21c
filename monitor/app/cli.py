"""`motor-monitor` command line: run, replay, calibrate, identify, check, and the commands of
installed extensions (`demo`, `reproduce` from the `experiments` package, found through the
`motor_monitor.commands` entry-point group: the daemon never imports them).

Every configuration or usage mistake ends in one line `motor-monitor: error: ...` on
stderr and exit status 2, never a traceback: each stage raises a subclass of
`monitor.errors.MonitorError`, caught here once.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from importlib.metadata import entry_points

from monitor.app import calibrate, check, identify, replay, run, status
from monitor.app.options import OneLineParser
from monitor.errors import ERROR_LINE_LIMIT, MonitorError, one_line

__all__ = ["build_parser", "main"]

COMMANDS_GROUP = "motor_monitor.commands"


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog="motor-monitor",
        description="CAN-bus monitor: fuzzy UKF actuator-fault estimation and diagnosis",
    )
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    run.add_command(sub)
    replay.add_command(sub)
    calibrate.add_command(sub)
    identify.add_command(sub)
    check.add_command(sub)
    status.add_command(sub)
    for ep in sorted(entry_points(group=COMMANDS_GROUP), key=lambda e: e.name):
        ep.load()(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(args.func(args))
    except (MonitorError, OSError) as exc:
        print(f"motor-monitor: error: {one_line(exc, limit=ERROR_LINE_LIMIT)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
