"""Recorded buses read through python-can's readers, with every way a damaged file fails
turned into one `LogError` line naming it.

`LOG_FORMATS` is the one table of the formats read (suffix -> `LogFormat`: python-can's
reader of the per-frame path, the columnar engine's module): candump ``.log``, Vector
``.asc`` and ``.blf``, PEAK ``.trc`` (every version python-can reads: 1.0, 1.1, 1.3, 2.0,
2.1), ASAM MDF4 ``.mf4`` (python-can's `MF4Reader`, on asammdf) and the text logs
gzip-compressed (``.log.gz``, ``.asc.gz``, ``.trc.gz``: python-can's reader on
``gzip.open``, as its own `can.LogReader` does). Everything that names or checks a
log's format (`log_format`, the archive's file search, the command line's messages) uses it.

Both replay paths read through here (`monitor.app.replay` frame by frame,
`monitor.columnar.reader` in chunks), so a file fails the same way in either.

Damage is never silent. python-can's readers stop quietly at the end of a file that was cut
short (a BLF whose last log container runs past the end of the file, a text log whose last
line has lost its end), so this module checks for it: a log that is empty, cut short or
damaged raises `LogDamaged`, one line naming the file, what is wrong, where it starts (a
line number in a text log, a byte offset in a BLF) and how many frames were read before
it. It is raised *after* those frames were delivered: a replay keeps what they gave (its
events, its recording) and reports the log as failed. The rules, the same in both paths:

* a file of 0 bytes: no frames (raised at open, before any output is opened);
* text logs (.log, .asc, .trc, gzip-compressed or not) are read as python-can reads them
  (the locale's encoding, universal newlines), numbered line by line: a line that is not
  text in that encoding is damage at that line; a last line without its line end was cut
  short (it is not read); a line python-can cannot read is damage at that line;
* an .asc whose trigger block began (``Begin Triggerblock``) but that does not end with
  ``End TriggerBlock`` was cut short;
* a gzip-compressed text log whose compressed stream ends before its end marker was cut
  short, one that is no gzip or whose compressed data or checksum is wrong is damaged, at
  the line the decompressed text was at;
* a .trc line python-can cannot read is damage at that line, a line with fewer columns
  than its version has too (python-can skips it with a warning: a frame lost unsaid);
* an .mf4 asammdf cannot open (a block that is no block, runs past the end of the file, a
  file cut short: its block tree is written last) has no frames; a data block it cannot
  read (a checksum, a block of the wrong kind) is damage at the frame python-can's reader
  was at;
* a .blf: an object at the file's top level that runs past the end of the file, a header
  that gives a larger file size than there is, or an object cut at the end of the last log
  container (it continues in a container the file does not have) was cut short; an object
  python-can cannot read is damage in the log container that holds it.
"""

from __future__ import annotations

import gc
import gzip
import importlib.util
import io
import locale
import logging
import re
import struct
import sys
import zlib
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from struct import error as StructError
from typing import IO, Any, TextIO, cast

import can
from can.io.blf import BLFParseError

from monitor.errors import MonitorError, one_line

__all__ = ["GZIP_ERRORS", "LOG_FORMATS", "LOG_SUFFIXES", "READ_ERRORS", "LogDamaged",
           "LogError", "LogFormat", "NumberedLines", "asc_unfinished", "blf_damage",
           "blf_object_at", "check_log_path", "damaged", "gzip_damage", "log_encoding",
           "log_format", "malformed", "open_binary", "open_mdf", "open_reader", "read_log",
           "suffix_list", "text_lines"]


class StrictTRCReader(can.TRCReader):
    """python-can's `TRCReader`, but a line with fewer columns than its version has is an
    error (damage at that line) rather than a warning and a frame lost."""

    def _parse_line(self, line: str) -> can.Message | None:
        cols = tuple(line.split(maxsplit=self._num_columns))
        try:
            return self._parse_cols(cols)
        except IndexError:
            raise ValueError(f"{len(cols)} columns, fewer than a frame of TRC "
                             f"{self.file_version.name} has") from None


@dataclass(frozen=True)
class LogFormat:
    """A log format we read: its suffix, what it is (for messages and docs), python-can's
    reader (`reader`: of a text log's lines for a text format, of the path otherwise),
    whether it is text, gzip-compressed, and the columnar engine's module that reads it
    (``monitor.columnar.<columnar>.read``)."""

    suffix: str
    what: str
    reader: Callable[[Any], can.io.generic.MessageReader]
    text: bool
    gzip: bool
    columnar: str


def _mf4_reader(path: Path) -> can.io.generic.MessageReader:
    return can.io.MF4Reader(str(path))


LOG_FORMATS: dict[str, LogFormat] = {f.suffix: f for f in (
    LogFormat(".log", "candump -L text", can.CanutilsLogReader, True, False, "candump"),
    LogFormat(".log.gz", "candump -L text, gzip", can.CanutilsLogReader, True, True,
              "candump"),
    LogFormat(".asc", "Vector ASC", can.ASCReader, True, False, "asc"),
    LogFormat(".asc.gz", "Vector ASC, gzip", can.ASCReader, True, True, "asc"),
    LogFormat(".trc", "PEAK TRC", StrictTRCReader, True, False, "trc"),
    LogFormat(".trc.gz", "PEAK TRC, gzip", StrictTRCReader, True, True, "trc"),
    LogFormat(".blf", "Vector BLF", lambda p: can.BLFReader(str(p)), False, False, "blf"),
    LogFormat(".mf4", "ASAM MDF4 bus logging", _mf4_reader, False, False, "mf4"),
)}
"""The one table of the log formats read, by suffix (lower case)."""

LOG_SUFFIXES = tuple(LOG_FORMATS)


def suffix_list() -> str:
    """The suffixes read, for a message: ".log, .log.gz, ..."."""
    return ", ".join(LOG_SUFFIXES)


def log_format(path: Path | str) -> LogFormat | None:
    """The format of the log at `path` by its suffix (any case; the longest that matches:
    ``run.log.gz`` is gzip-compressed candump), None if it is no format we read."""
    name = Path(path).name.lower()
    found = [f for s, f in LOG_FORMATS.items() if name.endswith(s) and len(name) > len(s)]
    return max(found, key=lambda f: len(f.suffix)) if found else None


GZIP_ERRORS = (EOFError, gzip.BadGzipFile, zlib.error)
"""What reading a damaged gzip stream raises: cut short, no gzip or a wrong checksum,
damaged compressed data."""

READ_ERRORS = (ValueError, IndexError, OSError, StructError, zlib.error, BLFParseError,
               EOFError)
"""What python-can's readers raise on a damaged file: bad text or numbers, short records,
a BLF that is no BLF or whose compressed objects are broken, a gzip stream cut short."""

_CONTENT_ERRORS = (ValueError, IndexError, StructError, zlib.error, BLFParseError)
"""READ_ERRORS but the system's (OSError): what says the file's content is damaged."""


class LogError(MonitorError):
    """A bus log that cannot be read (one line naming the file)."""


class LogDamaged(LogError):
    """A bus log whose content is damaged, cut short or empty (one line naming the file,
    what is wrong, where it starts and the frames read before it). Raised once the frames
    before the damage have been delivered; `frames` counts them."""

    def __init__(self, message: str, *, frames: int = 0) -> None:
        super().__init__(message)
        self.frames = frames


def damaged(path: Path, what: str, *, frames: int, where: str | None = None,
            detail: str | None = None) -> LogDamaged:
    """The error for damage in `path`: "<path>: <what> at <where> (<detail>); <frames>
    frames read before it"."""
    at = f" at {where}" if where else ""
    why = f" ({detail})" if detail else ""
    read = f"{frames} frames read before it" if frames else "no frame read before it"
    return LogDamaged(f"{path}: {what}{at}{why}; {read}", frames=frames)


def check_log_path(path: Path) -> LogFormat:
    """The format of the log at `path`; `LogError` for a file that is not there or not of a
    format we read, `LogDamaged` for an empty one."""
    fmt = log_format(path)
    if fmt is None:
        raise LogError(f"{path}: unsupported log format (use {suffix_list()})")
    if not path.is_file():
        raise LogError(f"{path}: no such file")
    with suppress(OSError):  # unreadable: said when it is opened
        if path.stat().st_size == 0:
            raise LogDamaged(f"{path}: empty file (0 bytes): no frames")
    return fmt


def malformed(path: Path, exc: BaseException, *, frames: int = 0,
              where: str | None = None) -> LogDamaged:
    """The error for a file that opened but broke while being read."""
    return damaged(path, "malformed log", frames=frames, where=where, detail=one_line(exc))


def gzip_damage(path: Path, exc: BaseException, *, frames: int, line: int) -> LogDamaged:
    """The error for a gzip stream that broke (`exc`, one of `GZIP_ERRORS`) while line
    `line` of its text was being decompressed."""
    if isinstance(exc, EOFError):
        return damaged(path, "truncated", frames=frames, where=f"line {line}",
                       detail="the gzip stream ends before its end marker")
    return damaged(path, "malformed log", frames=frames, where=f"line {line}",
                   detail=f"damaged gzip: {one_line(exc)}")


def open_binary(path: Path) -> IO[bytes]:
    """The bytes of the log at `path`, decompressed if it is gzip-compressed."""
    fmt = log_format(path)
    if fmt is not None and fmt.gzip:
        return cast(IO[bytes], gzip.open(path, "rb"))
    return path.open("rb")


def log_encoding() -> str:
    """The encoding python-can opens text logs with."""
    return locale.getpreferredencoding(False)


# -- text logs ----------------------------------------------------------------------------

_NOT_TEXT = re.compile("[\udc80-\udcff]")  # bytes the encoding did not take (surrogateescape)
_BLANK = " \t\r\n\v\f"


class NumberedLines:
    """The lines of a text log as python-can's readers would read them, numbered.

    python-can's text readers iterate over their file; given this instead, they see the same
    lines (the caller opens or decodes the text as python-can does), and `line` says which
    line they are at when they fail. A line the encoding did not take (decoded with
    ``surrogateescape``) and a last line without its line end (cut short) end the lines
    there; `damage` then says why and `line` is that line. `first` is the number of the
    first line (a block of a file)."""

    def __init__(self, lines: Iterable[str], encoding: str, first: int = 1) -> None:
        self.lines = lines
        self.encoding = encoding
        self.line = first - 1
        self.damage: str | None = None
        self.broken: BaseException | None = None  # the gzip stream's failure

    def __iter__(self) -> Iterator[str]:
        if self.damage is not None:  # a reader that iterates again (ASC: after its header)
            return
        lines = iter(self.lines)
        while True:
            try:
                text = next(lines)
            except StopIteration:
                return
            except GZIP_ERRORS as exc:  # the decompressor: the next line is not there
                self.line += 1
                self.damage = "gzip"
                self.broken = exc
                return
            self.line += 1
            if not text.endswith("\n") and text.strip(_BLANK):
                self.damage = "truncated"  # the writer stopped in the middle of the line
                return
            if _NOT_TEXT.search(text):
                self.damage = f"not {self.encoding} text"
                return
            yield text

    def close(self) -> None:
        close = getattr(self.lines, "close", None)
        if close is not None:
            close()

    def error(self, path: Path, frames: int) -> LogDamaged | None:
        """The damage that ended the lines, if any."""
        if self.damage is None:
            return None
        if self.broken is not None:
            return gzip_damage(path, self.broken, frames=frames, line=self.line)
        if self.damage == "truncated":
            return damaged(path, "truncated", frames=frames, where=f"line {self.line}",
                           detail="the last line has no line end")
        return damaged(path, "malformed log", frames=frames, where=f"line {self.line}",
                       detail=self.damage)


def text_lines(text: str) -> str:
    """`text` with universal newlines, as a file opened in text mode reads it."""
    return text.replace("\r\n", "\n").replace("\r", "\n")


def asc_unfinished(path: Path) -> int | None:
    """The size of the ASC log at `path` (decompressed) if it began a trigger block (``Begin
    Triggerblock`` among its first lines) and does not end with ``End TriggerBlock`` (its
    writer stopped before closing it: Vector's tools and python-can's writer always close
    it), else None."""
    with open_binary(path) as fh:
        head = fh.read(1 << 16)
        if isinstance(fh, gzip.GzipFile):  # no seek from the end: read on to it
            tail = head[-4096:]
            while block := fh.read(1 << 20):
                tail = (tail + block)[-4096:]
            size = fh.tell()
        else:
            size = fh.seek(0, io.SEEK_END)
            fh.seek(max(0, size - 4096))
            tail = fh.read()
    began = any(ln.strip().lower().startswith(b"begin triggerblock")
                for ln in head.replace(b"\r", b"\n").split(b"\n"))
    last = [ln.strip() for ln in tail.replace(b"\r", b"\n").split(b"\n") if ln.strip()]
    if not began or (last and last[-1].lower().startswith(b"end triggerblock")):
        return None
    return size


# -- BLF ----------------------------------------------------------------------------------

_BLF_FILE_HEADER = struct.Struct("<4sL8xQ")  # signature, header size, ..., file size
_BLF_FILE_HEADER_SIZE = 144  # what python-can's reader reads before the header's own size
_BLF_OBJECT = struct.Struct("<4sHHLL")  # signature, header size, version, size, type


_CUT = -1  # `_blf_objects`: a header cut short by the end of the file
_NO_OBJECT = -2  # `_blf_objects`: no object's signature where one must be


def _blf_objects(fh: IO[bytes], size: int) -> Iterator[tuple[int, int]]:
    """(offset, size) of each object at the top level of a BLF file, stepping as
    python-can's reader does (the object, then ``size % 4`` bytes of padding); size `_CUT`
    for a header cut short, `_NO_OBJECT` where there is no object (python-can fails at
    both), the file's rest for an object whose size is less than its header (python-can
    reads the rest of the file)."""
    fh.seek(0)
    head = fh.read(_BLF_FILE_HEADER.size)
    if len(head) < _BLF_FILE_HEADER.size:
        return
    header_size = _BLF_FILE_HEADER.unpack(head)[1]
    pos = header_size if header_size >= _BLF_FILE_HEADER_SIZE else size
    while pos < size:
        fh.seek(pos)
        obj = fh.read(_BLF_OBJECT.size)
        if len(obj) < _BLF_OBJECT.size or obj[:4] != b"LOBJ":
            yield pos, _CUT if len(obj) < _BLF_OBJECT.size else _NO_OBJECT
            return
        obj_size = _BLF_OBJECT.unpack(obj)[3]
        if obj_size < _BLF_OBJECT.size:
            yield pos, size - pos
            return
        yield pos, obj_size
        pos += obj_size + obj_size % 4


def _cut_short(pos: int, obj_size: int, size: int) -> str | None:
    """Why the top-level object at `pos` was cut short by the end of the file, or None."""
    if obj_size == _CUT:
        return f"an object header cut short at {size - pos} bytes"
    if obj_size >= 0 and pos + obj_size > size:
        return f"an object of {obj_size} bytes, {size - pos} of them in the file"
    return None


def blf_object_at(path: Path, offset: int) -> tuple[int, str | None]:
    """The top-level object of the BLF file at `path` that python-can's reader was reading
    when its file position was `offset`: its offset, and why it was cut short (None if it
    was not)."""
    with path.open("rb") as fh:
        size = fh.seek(0, io.SEEK_END)
        start = _BLF_FILE_HEADER_SIZE
        for pos, obj_size in _blf_objects(fh, size):
            start = pos
            if obj_size < 0 or offset <= pos + obj_size + obj_size % 4:
                return pos, _cut_short(pos, obj_size, size)
    return start, None


def blf_damage(path: Path, tail: bytes) -> tuple[str, str] | None:
    """(where, why) the BLF file at `path` was cut short, or None. `tail` is what the reader
    had left of the inflated log containers at the end (an unfinished object, or padding)."""
    with path.open("rb") as fh:
        size = fh.seek(0, io.SEEK_END)
        last = None
        for pos, obj_size in _blf_objects(fh, size):
            why = _cut_short(pos, obj_size, size)
            if why is not None:
                return f"byte {pos}", why
            last = pos
        fh.seek(0)
        head = fh.read(_BLF_FILE_HEADER.size)
    if len(head) == _BLF_FILE_HEADER.size:
        header_size, file_size = _BLF_FILE_HEADER.unpack(head)[1:]
        if header_size < file_size and file_size > size:  # a header its writer finished
            return f"byte {size}", f"the header gives {file_size} bytes"
    if tail.strip(b"\x00"):
        where = f"byte {last}" if last is not None else f"byte {size}"
        return where, ("the log container ends in the middle of an object that would "
                       "continue in a container the file does not have")
    return None


# -- reading ------------------------------------------------------------------------------

def open_reader(path: Path) -> can.io.generic.MessageReader:
    """python-can's reader of the log at `path` (`LogError` if it cannot open it,
    `LogDamaged` if its header is damaged). A text log's reader reads `NumberedLines`."""
    fmt = check_log_path(path)
    try:
        if not fmt.text:
            if fmt.suffix == ".mf4":
                return open_mdf(path, fmt.reader)
            return fmt.reader(path)
        encoding = log_encoding()
        if fmt.gzip:  # as can.LogReader opens it, in the encoding and newlines of a text log
            fh: IO[str] = gzip.open(  # noqa: SIM115 (the reader closes it)
                path, "rt", encoding=encoding, errors="surrogateescape")
        else:
            fh = path.open("r", encoding=encoding, errors="surrogateescape")
        return fmt.reader(cast(TextIO, NumberedLines(fh, encoding)))
    except OSError as exc:
        raise LogError(f"{path}: cannot read log ({one_line(exc)})") from None
    except _CONTENT_ERRORS as exc:
        raise LogDamaged(f"{path}: cannot read log ({one_line(exc)}): no frames read") \
            from None


# -- MF4 ----------------------------------------------------------------------------------

class _Demote(logging.Filter):
    """asammdf's own log records, to our log at DEBUG, one line each: it logs a block it
    cannot read with a traceback (to its own handler), which this module says once, as
    `LogDamaged`."""

    def filter(self, record: logging.LogRecord) -> bool:
        _log.debug("asammdf: %s", one_line(record.getMessage()))
        return False


_log = logging.getLogger("motor_monitor")
_DEMOTE = _Demote()


@contextmanager
def quiet_asammdf() -> Iterator[None]:
    """asammdf's log records to our DEBUG from now on (see `_Demote`), and, while in
    the context, the "Exception ignored" its half-built MDF object prints when it is
    collected after a failed open dropped."""
    logging.getLogger("asammdf").addFilter(_DEMOTE)  # once: a filter is not added twice
    hook = sys.unraisablehook

    def unraisable(info: Any) -> None:
        if not str(getattr(info.object, "__module__", "")).startswith("asammdf"):
            hook(info)

    sys.unraisablehook = unraisable
    try:
        yield
    finally:
        sys.unraisablehook = hook


def open_mdf(path: Path, opener: Callable[[Path], Any]) -> Any:
    """`opener(path)` of an MF4 file (asammdf's `MDF`, python-can's `MF4Reader`);
    `LogDamaged` for a file asammdf cannot open, naming what it found (asammdf raises its
    own and numpy's errors on an untrusted file: any of them is damage), `LogError` in an
    install without asammdf."""
    if importlib.util.find_spec("asammdf") is None:  # an install without it
        raise LogError(f"{path}: reading MF4 needs asammdf, which is not installed "
                       "(the mf4 extra: pip install 'motor-monitor[mf4]')")
    problem = None
    with quiet_asammdf():
        try:
            return opener(path)
        except OSError as exc:
            raise LogError(f"{path}: cannot read log ({one_line(exc)})") from None
        except Exception as exc:  # asammdf's MdfException, ValueError, IsalError, ...
            problem = one_line(exc)
        gc.collect()  # the half-built object is in a cycle: collected here, said nowhere
    raise LogDamaged(f"{path}: malformed MF4 ({problem}): no frames read")


def read_log(path: Path, skip: int = 0) -> Iterator[can.Message]:
    """Frames of a candump .log, Vector .asc or .blf file, through python-can's readers
    (after the first `skip`), then `LogDamaged` if the file was damaged or cut short.

    Not a generator itself: a bad path raises `LogError` here, before the caller opens
    any output (--rrd, --events) that an error must not create or overwrite.
    """
    return _frames(path, open_reader(path), skip)


def _frames(path: Path, reader: can.io.generic.MessageReader,
            skip: int) -> Iterator[can.Message]:
    source = getattr(reader, "file", None)
    lines = source if isinstance(source, NumberedLines) else None
    mf4 = isinstance(reader, can.io.MF4Reader)
    n = 0
    try:
        try:
            for msg in reader:
                n += 1
                if n > skip:
                    yield msg
        except READ_ERRORS as exc:
            if mf4:
                raise mf4_damage(path, exc, n) from None
            raise _located(path, source, exc, n) from None
        except Exception as exc:
            if not mf4:
                raise
            raise mf4_damage(path, exc, n) from None
        if lines is not None:
            cut = lines.error(path, n)
            if cut is not None:
                raise cut
            end = asc_unfinished(path) if cast(LogFormat, log_format(path)).columnar == "asc" \
                else None
            if end is not None:
                raise damaged(path, "truncated", frames=n, where=f"byte {end}",
                              detail="no End TriggerBlock")
        elif isinstance(reader, can.BLFReader):
            found = blf_damage(path, bytes(getattr(reader, "_tail", b"")))
            if found is not None:
                raise damaged(path, "truncated", frames=n, where=found[0], detail=found[1])
    finally:
        with suppress(Exception):
            reader.stop()


def mf4_damage(path: Path, exc: BaseException, frames: int) -> LogDamaged:
    """The error for asammdf's failure to read the data of an MF4 file after `frames`
    frames (a block it cannot read: the frames of the records before it came out)."""
    return damaged(path, "malformed MF4", frames=frames, where=f"frame {frames + 1}",
                   detail=f"a data block asammdf cannot read: {one_line(exc)}")


def _located(path: Path, source: object, exc: BaseException, frames: int) -> LogDamaged:
    """python-can's failure after `frames` frames, with where it happened: the line its
    text reader was at (`source` the `NumberedLines` it reads), or the top-level BLF object
    its binary reader was in (`source` its file)."""
    if isinstance(source, NumberedLines):
        return malformed(path, exc, frames=frames, where=f"line {source.line}")
    tell = getattr(source, "tell", None)
    try:
        offset = int(tell()) if tell is not None else -1
    except (OSError, ValueError):  # closed: no position to give
        offset = -1
    if offset < 0:
        return malformed(path, exc, frames=frames)
    pos, cut = blf_object_at(path, offset)
    if cut is not None:
        return damaged(path, "truncated", frames=frames, where=f"byte {pos}", detail=cut)
    return damaged(path, "malformed log", frames=frames, where=f"byte {pos}",
                  detail=f"in the object there: {one_line(exc)}")
