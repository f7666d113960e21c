"""Which logs a `replay PATH...` names, and where each log's outputs go.

A PATH is a file (taken as given: a missing or unsupported one becomes a failed row of the
summary, with `read_log`'s reason), a directory (every log below it of a format we read,
`monitor.bus.logfile.LOG_FORMATS`, recursively, in name order) or a glob pattern (`*`, `?`,
`[...]`, `**` for any depth; its matching logs, and the logs below matching directories). A
directory or pattern that holds no log is a failed row too. The same file named twice is
replayed once.

Output names mirror the logs' paths below the deepest directory they all share, the log's
suffix kept (`rigA/day1/run.log` -> `rigA/day1/run.log.events.jsonl`), so logs with the
same name in different directories, or the same stem in different formats, never collide.
"""

from __future__ import annotations

import glob
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from monitor.bus.logfile import log_format, suffix_list

__all__ = ["EVENTS_SUFFIX", "RRD_SUFFIX", "LogInput", "find_logs"]

EVENTS_SUFFIX = ".events.jsonl"
RRD_SUFFIX = ".rrd"


@dataclass(frozen=True)
class LogInput:
    """One log to replay: its path as found, the absolute path the workers open, its output
    name below the output directory, and, when it is known before reading, why it cannot
    be replayed."""

    log: str
    path: Path
    name: str
    problem: str | None = None

    def events_path(self, out: Path) -> Path:
        return out / (self.name + EVENTS_SUFFIX)

    def rrd_path(self, out: Path) -> Path:
        return out / (self.name + RRD_SUFFIX)


def _is_log(path: str) -> bool:
    return log_format(path) is not None


def _logs_below(directory: str) -> Iterator[str]:
    for root, dirs, files in os.walk(directory):
        dirs.sort()
        for f in sorted(files):
            if _is_log(f):
                yield os.path.join(root, f)


def _expand(arg: str) -> tuple[list[str], str | None]:
    """The log files an argument names, or why it names none."""
    if glob.has_magic(arg):
        found: list[str] = []
        for match in sorted(glob.glob(arg, recursive=True)):
            if os.path.isdir(match):
                found += _logs_below(match)
            elif _is_log(match):
                found.append(match)
        return found, None if found else f"{arg}: no log matches this pattern"
    if os.path.isdir(arg):
        found = list(_logs_below(arg))
        return found, None if found else (f"{arg}: directory holds no "
                                          f"{suffix_list()} file")
    return [arg], None


def find_logs(args: Sequence[str]) -> list[LogInput]:
    """Every log the arguments name, in their order, each once, with its output name."""
    named: list[tuple[str, str]] = []  # (as found, absolute)
    problems: list[tuple[int, str, str]] = []  # (position, argument, reason)
    seen: set[str] = set()
    for arg in args:
        found, problem = _expand(arg)
        if problem is not None:
            problems.append((len(named), arg, problem))
        for f in found:
            key = os.path.realpath(f)
            if key not in seen:
                seen.add(key)
                named.append((f, os.path.abspath(f)))
    dirs = [os.path.dirname(a) for _, a in named if os.path.exists(a)]  # a missing file
    common = os.path.commonpath(dirs) if dirs else os.getcwd()  # has no outputs
    inputs = [LogInput(log=f, path=Path(a), name=os.path.relpath(a, common)) for f, a in named]
    for position, arg, problem in reversed(problems):
        inputs.insert(position, LogInput(log=arg, path=Path(os.path.abspath(arg)), name="",
                                         problem=problem))
    return inputs
