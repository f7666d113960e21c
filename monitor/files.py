"""Files shared by every stage: the one way a file a user hands over is read
(`read_user_file`, `read_user_text`, `read_user_toml`: a regular file, opened without
blocking, read up to a limit that fits its kind), durable state files (thresholds, SecOC
freshness) and series of rotated files with retention (recordings, raw bus logs)."""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import numbers
import os
import re
import stat
import tempfile
import time
import tomllib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from monitor.errors import FailureBurst, MonitorError, one_line

__all__ = ["KIB", "MIB", "FileSeries", "PeriodicWrite", "UserFileError", "atomic_replace",
           "atomic_write_text", "file_kind", "read_user_file", "read_user_text",
           "read_user_toml", "shown_path", "user_file_problem"]

KIB = 1024
MIB = 1024 * KIB

_log = logging.getLogger(__name__)


class UserFileError(MonitorError, ValueError):
    """A file the user named that cannot be read as what it should be (one line).

    `errno` is the operating system's error number when the file could not be found or
    opened (e.g. `errno.ENOENT`: a caller for which a missing file is no error tells it
    apart this way), else None.
    """

    def __init__(self, message: str, errno: int | None = None) -> None:
        super().__init__(message)
        self.errno = errno


def shown_path(path: str | os.PathLike[str], limit: int = 120) -> str:
    """`path` as an error message shows it: at most `limit` characters, its start and end."""
    text = os.fspath(path)
    text = text if isinstance(text, str) else os.fsdecode(text)
    if len(text) <= limit:
        return text
    keep = (limit - 3) // 2
    return f"{text[:keep]}...{text[-keep:]}"


def file_kind(mode: int) -> str:
    """What a non-regular file is, in words ("a directory", "a FIFO (named pipe)", ...)."""
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def _os_problem(exc: OSError) -> str:
    if exc.errno == errno.ENOENT:
        return "no such file"
    if exc.errno == errno.ELOOP:
        return "a loop of symbolic links"
    if exc.errno == errno.ENAMETOOLONG:
        return "the path is too long for the file system"
    if exc.errno == errno.ENOTDIR:
        return "a part of the path is not a directory"
    return f"cannot read ({exc.strerror or exc})"


def _kind_problem(mode: int) -> str:
    return f"is {file_kind(mode)}, not a regular file"


def _size_words(n: int, exact: bool = False) -> str:
    if exact or n < KIB:
        return f"{n} bytes"
    return f"{n / MIB:.3g} MiB" if n >= MIB else f"{n / KIB:.3g} KiB"


class _Refused(Exception):
    """Why a user's file is not read, in words (`problem`), and the OS error number if any."""

    def __init__(self, problem: str, errno: int | None = None) -> None:
        super().__init__(problem)
        self.problem = problem
        self.errno = errno

    @classmethod
    def of(cls, exc: OSError) -> _Refused:
        return cls(_os_problem(exc), exc.errno)


def _regular_status(path: str | os.PathLike[str]) -> os.stat_result:
    """The status of `path` (symbolic links followed) if it is a regular file, else
    `_Refused`; opens nothing."""
    try:
        st = os.stat(path)
    except OSError as exc:
        raise _Refused.of(exc) from None
    except ValueError as exc:  # an embedded NUL byte
        raise _Refused(f"not a usable path ({exc})") from None
    if not stat.S_ISREG(st.st_mode):
        raise _Refused(_kind_problem(st.st_mode))
    return st


def _read_regular(path: str | os.PathLike[str], limit: int,
                  check: Callable[[os.stat_result], None] | None) -> bytes:
    def too_big(size: int | None) -> _Refused:
        # in bytes where rounding would say "is 4 KiB, more than the 4 KiB"
        exact = size is not None and _size_words(size) == _size_words(limit)
        return _Refused(("is more" if size is None else f"is {_size_words(size, exact)}, more")
                        + f" than the {_size_words(limit, exact)} such a file may have")

    found = _regular_status(path).st_size
    if found > limit:
        raise too_big(found)
    flags = os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NOCTTY", 0)
    try:
        fd = os.open(path, flags)
    except OSError as exc:
        raise _Refused.of(exc) from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise _Refused(_kind_problem(st.st_mode))
        if check is not None:
            check(st)
        chunks: list[bytes] = []
        size = 0
        while size <= limit and (chunk := os.read(fd, limit + 1 - size)):
            chunks.append(chunk)
            size += len(chunk)
    except OSError as exc:
        raise _Refused.of(exc) from None
    finally:
        os.close(fd)
    if size > limit:  # grew since the check
        raise too_big(None)
    return b"".join(chunks)


def user_file_problem(path: str | os.PathLike[str]) -> str | None:
    """Why `path` cannot be read as a user's file ("no such file", "is a FIFO (named pipe),
    not a regular file", ...), or None if it is a regular file. Opens nothing, so it
    neither blocks nor reads: for checking a file a configuration names before the file is
    read (`read_user_file` checks again then)."""
    try:
        _regular_status(path)
    except _Refused as exc:
        return exc.problem
    return None


def read_user_file(path: str | os.PathLike[str], *, what: str, limit: int,
                   check: Callable[[os.stat_result], None] | None = None) -> bytes:
    """The bytes of the regular file a user named as `what` (e.g. "rig file",
    "--thresholds"), at most `limit` bytes.

    Every file a user hands over is read this way, so that none can block or exhaust the
    monitor: the path is checked before it is opened (a directory, FIFO, device or socket is
    refused, so a FIFO never blocks the open), opened with O_NONBLOCK and checked again on
    the descriptor (the path may have changed in between), and a file over `limit` is
    refused before it is read. `check`, if given, is called with the status of the opened
    file before any byte is read and raises to refuse it (e.g. a secret readable by
    others); its exception passes unchanged. Otherwise raises `UserFileError`, one line
    naming `what`, the path and the problem (its `errno` set when the file could not be
    found or opened).
    """
    try:
        return _read_regular(path, limit, check)
    except _Refused as exc:
        raise UserFileError(f"{what} {shown_path(path)}: {exc.problem}", exc.errno) from None


def read_user_text(path: str | os.PathLike[str], *, what: str, limit: int) -> str:
    """`read_user_file` decoded as UTF-8 text (a BOM is dropped); binary content is one
    `UserFileError` line saying where it stops being text."""
    data = read_user_file(path, what=what, limit=limit)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise UserFileError(f"{what} {shown_path(path)}: not UTF-8 text (byte "
                            f"0x{data[exc.start]:02x} at offset {exc.start})") from None
    if "\x00" in text:
        raise UserFileError(f"{what} {shown_path(path)}: not text (a NUL byte at offset "
                            f"{text.index(chr(0))})")
    return text


def read_user_toml(path: str | os.PathLike[str], *, what: str, limit: int) -> dict[str, Any]:
    """`read_user_text` parsed as TOML. Besides a syntax error, a document tomllib cannot
    take (an integer of thousands of digits, tables nested thousands deep) is the same one
    `UserFileError` line "<what> <path>: not valid TOML: ..." and no traceback."""
    text = read_user_text(path, what=what, limit=limit)
    try:
        return tomllib.loads(text)
    except RecursionError:
        problem = "nested too deeply"
    except ValueError as exc:  # TOMLDecodeError, or int()'s limit on digits
        problem = one_line(exc)
    raise UserFileError(f"{what} {shown_path(path)}: not valid TOML: {problem}")


def finite_number(value: object) -> float | None:
    """`value` as a float if it is a finite number (an int or a float, not a bool), else
    None. What a number in a user's TOML file must be: tomllib gives integers of any size
    and `inf`/`nan`, and `math.isfinite` of an integer of hundreds of digits raises."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return None
    try:
        out = float(value)
    except OverflowError:
        return None
    return out if math.isfinite(out) else None


def atomic_write_text(path: str | os.PathLike[str], text: str, *, mode: int | None = None,
                      encoding: str = "utf-8") -> None:
    """Write `text` to `path` so that a reader (or a crash) sees the old or the new file,
    never half of one: a temporary file beside it, fsync, rename, fsync of the directory.

    `mode` sets the new file's permissions before any byte is written (e.g. 0o600 for
    secrets). Raises OSError; the previous file then stays intact and no temporary file
    is left behind.
    """
    with (_replacing(Path(path), ".tmp") as (fd, _),
          os.fdopen(fd, "w", encoding=encoding, newline="\n") as fh):
        if mode is not None:
            os.fchmod(fh.fileno(), mode)
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())


@contextlib.contextmanager
def _replacing(path: Path, suffix: str) -> Iterator[tuple[int, str]]:
    """A new temporary file beside `path` (open descriptor, name; permissions 0600), renamed
    over `path` when the block ends, then the rename made durable; deleted if the block
    raises. The block writes, fsyncs and closes it."""
    directory = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=directory)
    try:
        yield fd, tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    _fsync_directory(directory)


def _fsync_path(path: str | os.PathLike[str]) -> None:
    """fsync the file or directory at `path` (raises OSError)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_directory(directory: Path) -> None:
    """Make a rename in `directory` durable (best effort: some file systems refuse)."""
    with contextlib.suppress(OSError):
        _fsync_path(directory)


@contextlib.contextmanager
def atomic_replace(path: str | os.PathLike[str]) -> Iterator[Path]:
    """A temporary path beside `path` (same directory, same suffix, so a writer that goes
    by the suffix picks the right format) for a writer that wants a file name, not text:
    when the block ends, that file is fsynced and renamed over `path`, as
    `atomic_write_text` does; if the block raises, it is deleted and `path` stays as it
    was. The new file keeps the permissions of the one it replaces, else gets those the
    umask gives a new file. Raises OSError (naming the temporary file: callers name `path`
    in their message).
    """
    p = Path(path)
    try:
        mode = stat.S_IMODE(os.stat(p).st_mode)
    except OSError:
        mask = os.umask(0o077)  # reading the umask means setting it (to the strict side)
        os.umask(mask)
        mode = 0o666 & ~mask
    with _replacing(p, f".tmp{p.suffix}") as (fd, tmp):
        try:
            os.fchmod(fd, mode)  # mkstemp's is 0600
        finally:
            os.close(fd)
        yield Path(tmp)
        _fsync_path(tmp)


class PeriodicWrite:
    """A file written again every `period_s` while the program runs (SecOC freshness, the
    metrics' textfile): `maybe_write`, called often, runs `write` once the period has passed
    since the last, the first time `period_s` after `start` (a monotonic time; -inf: at the
    first call). A failing `write` (OSError, or a `MonitorError` naming the file) is logged
    once per burst of failures (`FailureBurst`) and retried at the next period: the program
    keeps running on what it has."""

    def __init__(self, write: Callable[[], None], what: str, period_s: float, *,
                 start: float = -math.inf) -> None:
        self.period_s = period_s
        self._write = write
        self._what = what
        self._last = start
        self.burst = FailureBurst(_log, f"{what}: written again")

    def maybe_write(self, now_monotonic: float) -> None:
        if now_monotonic - self._last >= self.period_s:
            self._last = now_monotonic
            self.write()

    def write(self) -> bool:
        """One write now; False where it failed (logged as `maybe_write`'s are)."""
        try:
            self._write()
        except (OSError, MonitorError) as exc:
            self.burst.failed(f"cannot write {self._what}: {one_line(exc)} (retrying every "
                              f"{self.period_s:g} s)")
            return False
        self.burst.worked()
        return True


class FileSeries:
    """A directory of rotated files ``<prefix>-YYYYmmddTHHMMSS-NNNN<suffix>`` and their
    retention, shared by the recordings and the raw bus logs.

    Names sort chronologically: the UTC time the file was opened and a sequence number one
    more than the highest in the directory at start, then +1 per file. Retention (`prune`)
    counts every file of the pattern in the directory (earlier runs too), never deletes the
    one being written, and deletes the oldest while there are more than `keep` files (the
    current one included) or the closed ones total more than ``max_total_bytes -
    max_bytes`` (the room the current file may take).
    """

    def __init__(self, directory: str | os.PathLike[str], prefix: str, suffix: str, *,
                 keep: int | None = None, max_total_bytes: int | None = None,
                 max_bytes: int | None = None, label: str = "files") -> None:
        if not re.fullmatch(r"[A-Za-z0-9_.-]+", prefix):
            raise ValueError(f"prefix must match [A-Za-z0-9_.-]+: {prefix!r}")
        if keep is not None and keep < 1:
            raise ValueError("keep must be >= 1 (or None)")
        if max_total_bytes is not None and (
            max_total_bytes < 1 or (max_bytes is not None and max_total_bytes < max_bytes)
        ):
            raise ValueError("max_total_bytes must be >= max_bytes (or None)")
        self.directory = Path(directory)
        self.prefix = prefix
        self.suffix = suffix
        self.keep = keep
        self.max_total_bytes = max_total_bytes
        self.max_bytes = max_bytes
        self.label = label
        self._pattern = re.compile(re.escape(prefix) + r"-(\d{8}T\d{6})-(\d{4,})"
                                   + re.escape(suffix))
        self.directory.mkdir(parents=True, exist_ok=True)
        self._seq = 1 + max((seq for _, seq, _ in self._scan()), default=-1)

    @staticmethod
    def size(path: Path) -> int | None:
        try:
            return os.stat(path).st_size
        except OSError:
            return None

    def _scan(self) -> list[tuple[str, int, Path]]:
        """(UTC stamp, sequence number, path) of this pattern's files, oldest first."""
        out: list[tuple[str, int, Path]] = []
        try:
            names = os.listdir(self.directory)
        except OSError:
            return out
        for name in names:
            m = self._pattern.fullmatch(name)
            if m is not None:
                out.append((m.group(1), int(m.group(2)), self.directory / name))
        out.sort()
        return out

    def files(self) -> list[Path]:
        """The files of the pattern, oldest first."""
        return [p for _, _, p in self._scan()]

    def next_path(self) -> Path:
        """A new name, after every existing one."""
        with contextlib.suppress(OSError):  # if it fails, creating the file reports it
            self.directory.mkdir(parents=True, exist_ok=True)
        stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime())
        while True:
            path = self.directory / f"{self.prefix}-{stamp}-{self._seq:04d}{self.suffix}"
            self._seq += 1
            if not path.exists():
                return path

    def prune(self, current: Path) -> None:
        """Delete the oldest closed files beyond `keep` and `max_total_bytes`."""
        if self.keep is None and self.max_total_bytes is None:
            return
        closed = [p for p in self.files() if p != current]
        sizes = [self.size(p) or 0 for p in closed]
        count = len(closed) + 1  # with the current file
        total = sum(sizes)
        room = (None if self.max_total_bytes is None
                else self.max_total_bytes - (self.max_bytes or 0))
        for p, size in zip(closed, sizes, strict=True):
            if (self.keep is None or count <= self.keep) and (room is None or total <= room):
                break
            try:
                p.unlink(missing_ok=True)
                _log.info("%s: deleted %s (%d bytes)", self.label, p, size)
            except OSError as exc:
                _log.warning("%s: cannot delete %s: %s", self.label, p, exc)
            count -= 1
            total -= size
