"""Recorded buses: candump .log, Vector .asc and .blf files read through python-can's
readers, with every way a damaged file fails turned into one `LogError` line naming it.

Both replay paths read through here (`monitor.app.replay` frame by frame,
`monitor.columnar.reader` in chunks), so a file fails the same way in either.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterator
from contextlib import suppress
from pathlib import Path
from struct import error as StructError

import can
from can.io.blf import BLFParseError

from monitor.errors import MonitorError, one_line

__all__ = ["LOG_SUFFIXES", "READ_ERRORS", "LogError", "check_log_path", "malformed",
           "open_reader", "read_log"]

LOG_SUFFIXES = (".log", ".asc", ".blf")

READ_ERRORS = (ValueError, IndexError, OSError, StructError, zlib.error, BLFParseError)
"""What python-can's readers raise on a damaged file: bad text or numbers, short records,
a BLF that is no BLF or whose compressed objects are broken."""


class LogError(MonitorError):
    """A bus log that cannot be read (one line naming the file)."""


def check_log_path(path: Path) -> None:
    """`LogError` for a file that is not there or not of a format we read."""
    if path.suffix.lower() not in LOG_SUFFIXES:
        raise LogError(f"{path}: unsupported log format (use {', '.join(LOG_SUFFIXES)})")
    if not path.is_file():
        raise LogError(f"{path}: no such file")


def malformed(path: Path, exc: BaseException) -> LogError:
    """The error for a file that opened but broke while being read."""
    return LogError(f"{path}: malformed log ({one_line(exc)})")


def open_reader(path: Path) -> can.io.generic.MessageReader:
    """python-can's reader of the log at `path` (`LogError` if it cannot open it)."""
    check_log_path(path)
    try:
        return can.LogReader(str(path))
    except READ_ERRORS as exc:
        raise LogError(f"{path}: cannot read log ({one_line(exc)})") from None


def read_log(path: Path) -> Iterator[can.Message]:
    """Frames of a candump .log, Vector .asc or .blf file, through python-can's readers.

    Not a generator itself: a bad path raises `LogError` here, before the caller opens
    any output (--rrd, --events) that an error must not create or overwrite.
    """
    return _frames(path, open_reader(path))


def _frames(path: Path, reader: can.io.generic.MessageReader) -> Iterator[can.Message]:
    try:
        yield from reader
    except READ_ERRORS as exc:
        raise malformed(path, exc) from None
    finally:
        with suppress(Exception):
            reader.stop()
