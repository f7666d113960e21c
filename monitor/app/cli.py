"""`motor-monitor` command line: run, replay, calibrate, identify, check, and the commands of
installed extensions (`demo`, `reproduce` from the `experiments` package, found through the
`motor_monitor.commands` entry-point group: the daemon never imports them).

Every configuration or usage mistake ends in one line `motor-monitor: error: ...` on
stderr and exit status 2, never a traceback: each stage raises a subclass of
`monitor.errors.MonitorError`, caught here once.

A command line that names its command imports that command's module alone (as pip does):
the daemon's start-up does not pay for identify's, the archive's or the extensions' imports.
The whole list is built for ``--help`` and for a word that is no command.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence
from importlib.metadata import entry_points

from monitor.errors import ERROR_LINE_LIMIT, MonitorError, one_line
from monitor.runtime.argtypes import OneLineParser
from monitor.runtime.imports import without_mf4

__all__ = ["BUILTIN_COMMANDS", "build_parser", "main", "program"]

COMMANDS_GROUP = "motor_monitor.commands"
#: The built-in commands, each defined by the module `monitor.app.<name>` (its `add_command`),
#: in the order of the help.
BUILTIN_COMMANDS = ("run", "replay", "calibrate", "identify", "check", "status")
#: The commands that read no bus log (`monitor.runtime.imports`).
READS_NO_LOG = frozenset({"run", "status"})


def command_word(argv: Sequence[str]) -> str | None:
    """The command named on a command line (the first word that is no option: the program's
    own options take no value), None if there is none or help comes first."""
    for word in argv:
        if word in ("--", "-h", "--help"):
            return None
        if not word.startswith("-"):
            return word
    return None


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The command line's parser: with the built-in or extension `command`, that command
    alone (only its module imported); else every command."""
    p = OneLineParser(
        prog="motor-monitor",
        description="CAN-bus monitor: fuzzy UKF actuator-fault estimation and diagnosis",
    )
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    builtin: Sequence[str] = BUILTIN_COMMANDS
    extensions = sorted(entry_points(group=COMMANDS_GROUP), key=lambda e: e.name)
    if command in BUILTIN_COMMANDS:
        builtin, extensions = (command,), []
    elif any(ep.name == command for ep in extensions):
        builtin, extensions = (), [ep for ep in extensions if ep.name == command]
    for name in builtin:
        importlib.import_module(f"monitor.app.{name}").add_command(sub)
    for ep in extensions:
        ep.load()(sub)
    return p


def program() -> int:
    """The `motor-monitor` executable: `main` on this process's arguments. A command that
    reads no bus log starts without python-can's MF4 support (`without_mf4`), which only
    the program's own process may leave out."""
    if command_word(sys.argv[1:]) in READS_NO_LOG:
        without_mf4()
    return main()


def main(argv: Sequence[str] | None = None) -> int:
    words = sys.argv[1:] if argv is None else argv
    parser = build_parser(command_word(words))
    args = parser.parse_args(words)
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
    sys.exit(program())
