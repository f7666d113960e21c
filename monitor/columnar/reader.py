"""Bus logs read in large chunks into arrays: `read_chunks(path)` yields `FrameChunk`s.

Every reader gives exactly the frames python-can's `can.LogReader` gives for the same file
(the per-frame path reads through it), as arrays:

* candump ``.log``: parsed by a compiled byte scanner (`_scan_candump`), about ten times
  python-can's speed. It follows `can.io.canutils.CanutilsLogReader` rule for rule: an ID
  longer than 3 digits is extended, an ID with the error flag *and* the bus-error bit is an
  error frame (ID 0, no data), any other error-flagged ID is an extended data frame, ``#R``
  remote, ``##`` CAN FD. Timestamps are converted exactly (Clinger's fast path: a decimal
  mantissa of at most 2^53 and at most 22 decimals, one correctly rounded division, which
  is what Python's ``float`` gives); a line the scanner does not take as plain (odd hex digits,
  exponents, more digits, anything unexpected) sends its whole chunk through python-can's
  own reader instead, so the result never differs, and a malformed file raises the same
  error.
* ``.blf``: a compiled object scanner over the inflated log containers
  (`monitor.columnar.blf`), python-can's rules and its file-header parsing; anything it
  does not take hands the rest of the file to python-can's reader.
* ``.asc``: a compiled line scanner (`monitor.columnar.asc`) after python-can has read the
  header, python-can's rules; a block of lines it does not take goes through python-can's
  reader.

Under NUMBA_DISABLE_JIT (the hardened unit) BLF and ASC are read by python-can.

Damage is found as `monitor.bus.logfile` finds it for the per-frame path, with the same
line: the frames before it come out, then `LogDamaged` (a line python-can cannot read, or
that is no text in the locale's encoding, at its line number; a last line without its line
end; an ASC without its End TriggerBlock; a BLF cut short). Lines are numbered as a file
read in text mode numbers them (universal newlines).

A frame's payload is ``data[i, :length[i]]``. `data` is 8 bytes wide, or 64 when the chunk
holds a CAN FD frame longer than 8 bytes, so no payload is ever cut short; `fd`,
`bitrate_switch` and `error_state_indicator` carry the CAN FD flags (candump ``##<flags>``,
BLF's FD objects), so an FD frame gets the same outcome (``fd_frame`` on a classic message,
decoded on an FD one) in both replay paths.
"""

from __future__ import annotations

import io
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO, cast

import can
import numpy as np
from numpy.typing import NDArray

from monitor.bus.logfile import (
    LOG_SUFFIXES,
    READ_ERRORS,
    LogError,
    NumberedLines,
    check_log_path,
    damaged,
    log_encoding,
    malformed,
    read_log,
    text_lines,
)
from monitor.errors import one_line
from monitor.estimation.jit import JIT_DISABLED, njit

__all__ = ["LOG_SUFFIXES", "FrameChunk", "LogReadError", "chunk_from_messages", "count_lines",
           "empty_chunk", "messages_to_chunks", "needs_python", "python_can_block",
           "read_chunks", "split_cut_line"]

DEFAULT_CHUNK_FRAMES = 1 << 18
CLASSIC_WIDTH = 8
FD_WIDTH = 64  # the longest CAN FD payload
_READ_BYTES = 1 << 24  # candump text read per call (about 330,000 lines)


LogReadError = LogError
"""A bus log that cannot be read: the one error both replay paths raise for it."""


@dataclass
class FrameChunk:
    """Consecutive frames of a log as columns (row i is the i-th frame of the chunk)."""

    t: NDArray[np.float64]
    arbitration_id: NDArray[np.int64]
    extended: NDArray[np.bool_]
    remote: NDArray[np.bool_]
    error: NDArray[np.bool_]
    length: NDArray[np.int64]
    data: NDArray[np.uint8]  # (n, 8) or (n, 64) with long FD frames; zero beyond the length
    fd: NDArray[np.bool_] | None = None  # None: no CAN FD frame in the chunk
    bitrate_switch: NDArray[np.bool_] | None = None
    error_state_indicator: NDArray[np.bool_] | None = None

    def __post_init__(self) -> None:
        n = len(self)
        if self.fd is None:
            self.fd = np.zeros(n, np.bool_)
        if self.bitrate_switch is None:
            self.bitrate_switch = np.zeros(n, np.bool_)
        if self.error_state_indicator is None:
            self.error_state_indicator = np.zeros(n, np.bool_)

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def is_fd(self) -> NDArray[np.bool_]:
        """The CAN FD flag of every row."""
        assert self.fd is not None  # __post_init__
        return self.fd

    @property
    def is_esi(self) -> NDArray[np.bool_]:
        """The CAN FD error state indicator of every row (the sender is error passive)."""
        assert self.error_state_indicator is not None  # __post_init__
        return self.error_state_indicator

    def head(self, n: int, width: int | None = None) -> FrameChunk:
        """The first `n` rows (views, no copy), the data cut to `width` bytes if given (then
        copied contiguous): a scanner fills a chunk of capacity and keeps what it read."""
        assert self.bitrate_switch is not None and self.error_state_indicator is not None
        data = self.data[:n] if width is None else np.ascontiguousarray(self.data[:n, :width])
        return FrameChunk(self.t[:n], self.arbitration_id[:n], self.extended[:n],
                          self.remote[:n], self.error[:n], self.length[:n], data,
                          self.is_fd[:n], self.bitrate_switch[:n],
                          self.error_state_indicator[:n])

    def message(self, i: int) -> can.Message:
        """Row i as a python-can message (for the rare frames handled one by one)."""
        n = min(int(self.length[i]), self.data.shape[1])
        assert self.bitrate_switch is not None and self.error_state_indicator is not None
        return can.Message(timestamp=float(self.t[i]), arbitration_id=int(self.arbitration_id[i]),
                           is_extended_id=bool(self.extended[i]),
                           is_remote_frame=bool(self.remote[i]),
                           is_error_frame=bool(self.error[i]),
                           is_fd=bool(self.is_fd[i]),
                           bitrate_switch=bool(self.bitrate_switch[i]),
                           error_state_indicator=bool(self.error_state_indicator[i]),
                           data=bytes(self.data[i, :n]), check=False)


def empty_chunk(n: int, width: int = CLASSIC_WIDTH) -> FrameChunk:
    """A chunk of `n` zeroed rows (filled in place by the scanners)."""
    return FrameChunk(np.zeros(n), np.zeros(n, np.int64), np.zeros(n, np.bool_),
                      np.zeros(n, np.bool_), np.zeros(n, np.bool_), np.zeros(n, np.int64),
                      np.zeros((n, width), np.uint8), np.zeros(n, np.bool_),
                      np.zeros(n, np.bool_), np.zeros(n, np.bool_))


def chunk_from_messages(msgs: Iterable[can.Message]) -> FrameChunk:
    """Columns of python-can messages (exactly what the per-frame path would feed)."""
    rows = list(msgs)
    long_fd = any(len(m.data or b"") > CLASSIC_WIDTH for m in rows)
    c = empty_chunk(len(rows), FD_WIDTH if long_fd else CLASSIC_WIDTH)
    assert c.bitrate_switch is not None and c.error_state_indicator is not None
    for i, m in enumerate(rows):
        c.t[i] = m.timestamp
        c.arbitration_id[i] = m.arbitration_id
        c.extended[i] = m.is_extended_id
        c.remote[i] = m.is_remote_frame
        c.error[i] = m.is_error_frame
        c.is_fd[i] = m.is_fd
        c.bitrate_switch[i] = m.bitrate_switch
        c.error_state_indicator[i] = m.error_state_indicator
        d = bytes(m.data or b"")
        c.length[i] = len(d)
        if d:
            k = min(len(d), c.data.shape[1])
            c.data[i, :k] = np.frombuffer(d[:k], np.uint8)
    return c


def read_chunks(path: Path, chunk_frames: int = DEFAULT_CHUNK_FRAMES) -> Iterator[FrameChunk]:
    """The frames of a candump .log, Vector .asc or .blf file, `chunk_frames` at a time.

    Not a generator itself: a bad path raises `LogReadError` here, before the caller opens
    outputs.
    """
    path = Path(path)
    check_log_path(path)
    if path.suffix.lower() == ".log":
        try:
            fh = path.open("rb")
        except OSError as exc:
            raise LogError(f"{path}: cannot read log ({one_line(exc)})") from None
        return _candump_chunks(path, fh)
    if path.suffix.lower() == ".blf" and not JIT_DISABLED:
        from monitor.columnar.blf import blf_chunks

        return blf_chunks(path, chunk_frames)
    if path.suffix.lower() == ".asc" and not JIT_DISABLED:
        from monitor.columnar.asc import asc_chunks

        return asc_chunks(path, chunk_frames)
    return reader_chunks(path, chunk_frames)


def messages_to_chunks(msgs: Iterable[can.Message], chunk_frames: int) -> Iterator[FrameChunk]:
    """python-can messages in chunks of `chunk_frames` (the last one shorter). If reading
    fails, the frames read before the failure still come out (as the per-frame path feeds
    them), then the error."""
    batch: list[can.Message] = []
    try:
        for msg in msgs:
            batch.append(msg)
            if len(batch) >= chunk_frames:
                yield chunk_from_messages(batch)
                batch = []
    except Exception:
        if batch:
            yield chunk_from_messages(batch)
        raise
    if batch:
        yield chunk_from_messages(batch)


def reader_chunks(path: Path, chunk_frames: int, skip: int = 0) -> Iterator[FrameChunk]:
    """python-can's frames of `path` (`read_log`: damage found alike) after the first
    `skip`, in chunks. Opens the file now: a bad path raises here."""
    return messages_to_chunks(read_log(path, skip), chunk_frames)


def count_lines(text: bytes) -> int:
    """The lines ended in `text` as a file read in text mode counts them (universal
    newlines: ``\n``, ``\r\n`` and a lone ``\r``)."""
    return text.count(b"\n") + text.count(b"\r") - text.count(b"\r\n")


_BLANK = b" \t\r\n\v\f"


def split_cut_line(text: bytes) -> tuple[bytes, bool]:
    """`text` (the end of a file) without a last line that has no line end, and whether
    there was one that is not blank: its writer stopped in the middle of it."""
    end = max(text.rfind(b"\n"), text.rfind(b"\r")) + 1
    if end == len(text):
        return text, False
    return text[:end], bool(text[end:].strip(_BLANK))


def cut_line_error(path: Path, frames: int, line: int) -> LogError:
    """The error for a last line (number `line`) that has no line end."""
    return damaged(path, "truncated", frames=frames, where=f"line {line}",
                   detail="the last line has no line end")


def needs_python(buf: NDArray[np.uint8]) -> bool:
    """Bytes a text reader would see otherwise than the compiled scanners: non-ASCII, the
    separators ``str.split`` counts as space (0x1c-0x1f), a carriage return not before a
    line feed (a line end to a file read in text mode)."""
    if bool((buf >= 0x80).any()) or bool(((buf >= 0x1C) & (buf <= 0x1F)).any()):
        return True
    cr = np.flatnonzero(buf == 13)
    if not len(cr):
        return False
    follows = cr + 1
    return bool((follows >= len(buf)).any() or (buf[follows[follows < len(buf)]] != 10).any())


def python_can_block(path: Path, reader: can.io.generic.MessageReader, lines: NumberedLines,
                     frames: int) -> Iterator[FrameChunk]:
    """python-can's frames of one block of a text log (`reader` reading `lines`) as one
    chunk, then the damage that stopped it, if any. `frames`: the file's frames before the
    block."""
    msgs: list[can.Message] = []
    failure: LogError | None = None
    try:
        msgs.extend(reader)
    except READ_ERRORS as exc:
        failure = malformed(path, exc, frames=frames + len(msgs), where=f"line {lines.line}")
    if failure is None:
        failure = lines.error(path, frames + len(msgs))
    if msgs:
        yield chunk_from_messages(msgs)
    if failure is not None:
        raise failure


def text_block(text: bytes, encoding: str, first: int, prefix: str = "") -> NumberedLines:
    """The lines of a block of a text log as python-can would read them from the file
    (decoded, universal newlines), numbered from `first`, after `prefix`."""
    return NumberedLines(io.StringIO(prefix + text_lines(text.decode(encoding,
                                                                     "surrogateescape"))),
                         encoding, first)


def line_blocks(fh: io.BufferedReader, size: int = _READ_BYTES) -> Iterator[bytes]:
    """The rest of the file in blocks of about `size` bytes, each cut after a line end (the
    last one as the file ends)."""
    tail = b""
    while True:
        block = fh.read(size)
        if not block:
            break
        buf = tail + block
        cut = buf.rfind(b"\n") + 1
        if cut == 0:
            tail = buf
            continue
        tail = buf[cut:]
        yield buf[:cut]
    if tail:
        yield tail


def _candump_chunks(path: Path, fh: io.BufferedReader) -> Iterator[FrameChunk]:
    encoding = log_encoding()
    line = 0  # lines before the block
    frames = 0
    try:
        for block in line_blocks(fh):
            text, cut = split_cut_line(block)
            if text:
                for chunk in _parse_candump(path, text, encoding, line, frames):
                    frames += len(chunk)
                    yield chunk
                line += count_lines(text)
            if cut:
                raise cut_line_error(path, frames, line + 1)
    finally:
        fh.close()


def _parse_candump(path: Path, text: bytes, encoding: str, line: int,
                   frames: int) -> Iterator[FrameChunk]:
    """The frames of whole lines `text`, after `line` lines and `frames` frames."""
    buf = np.frombuffer(text, np.uint8)
    if not needs_python(buf):
        c = empty_chunk(text.count(b"\n") + 1, FD_WIDTH if b"##" in text else CLASSIC_WIDTH)
        assert c.bitrate_switch is not None and c.error_state_indicator is not None
        n = _scan_candump(buf, c.t, c.arbitration_id, c.extended, c.remote, c.error, c.length,
                          c.data, c.is_fd, c.bitrate_switch, c.error_state_indicator)
        if n >= 0:
            if n:
                yield c.head(n)
            return
    # a line the scanner does not take: python-can reads this block
    lines = text_block(text, encoding, line + 1)
    reader = can.io.canutils.CanutilsLogReader(cast(TextIO, lines))
    yield from python_can_block(path, reader, lines, frames)


POW10 = np.array([10.0 ** k for k in range(23)])
"""Exact powers of ten up to 10^22: a decimal of at most 2^53 over one of them is one
correctly rounded division (Clinger's fast path), what Python's ``float`` gives."""
_CAN_ERR_FLAG = 0x20000000
_CAN_ERR_BUSERROR = 0x80


@njit
def _hexval(ch: int) -> int:
    if 48 <= ch <= 57:
        return ch - 48
    if 65 <= ch <= 70:
        return ch - 55
    if 97 <= ch <= 102:
        return ch - 87
    return -1


@njit
def is_space(ch: int) -> bool:
    """ASCII white space: what ``bytes.split`` splits at and ``str.strip`` strips (of ASCII,
    but 0x1c-0x1f, which a text scanner's caller rules out)."""
    return ch == 32 or ch == 9 or ch == 10 or ch == 13 or ch == 11 or ch == 12


@njit
def stripped_line(buf: NDArray[np.uint8], i: int) -> tuple[int, int, int]:
    """The line that starts at `i`, without its leading and trailing white space:
    (start, end, start of the next line)."""
    size = buf.shape[0]
    e = i
    while e < size and buf[e] != 10:
        e += 1
    nxt = e + 1
    while i < e and is_space(buf[i]):
        i += 1
    while e > i and is_space(buf[e - 1]):
        e -= 1
    return i, e, nxt


@njit
def _scan_candump(buf: NDArray[np.uint8], t: NDArray[np.float64], ids: NDArray[np.int64],
                  ext: NDArray[np.bool_], remote: NDArray[np.bool_], err: NDArray[np.bool_],
                  length: NDArray[np.int64], data: NDArray[np.uint8], fd: NDArray[np.bool_],
                  brs: NDArray[np.bool_], esi: NDArray[np.bool_]) -> int:
    """Frames of candump -L lines into the arrays; returns the count, -1 for a line it does
    not take as plain (the caller then asks python-can). `data` is 8 or 64 bytes wide."""
    pow10 = POW10
    width = data.shape[1]
    size = buf.shape[0]
    n = 0
    i = 0
    while i < size:
        i, e, nxt = stripped_line(buf, i)
        if i == e:
            i = nxt
            continue
        # token 1: (seconds.fraction)
        if buf[i] != 40:
            return -1
        j = i + 1
        mant = 0
        digits = 0
        frac = 0
        dot = False
        while j < e and buf[j] != 41:
            ch = buf[j]
            if ch == 46 and not dot:
                dot = True
            elif 48 <= ch <= 57:
                if digits > 0 or ch != 48:
                    digits += 1
                if digits <= 17:
                    mant = mant * 10 + (ch - 48)
                if dot:
                    frac += 1
            else:
                return -1
            j += 1
        if j >= e or digits > 17 or mant > 9007199254740992 or frac > 22 or j == i + 1:
            return -1
        j += 1  # ')'
        if j >= e or not is_space(buf[j]):
            return -1
        ts = float(mant) / pow10[frac]
        # token 2: channel
        while j < e and is_space(buf[j]):
            j += 1
        while j < e and not is_space(buf[j]):
            j += 1
        while j < e and is_space(buf[j]):
            j += 1
        # token 3: frame, up to the next space
        k = j
        while k < e and not is_space(buf[k]):
            k += 1
        # rest: nothing, or one direction token r/t (any case)
        r = k
        while r < e and is_space(buf[r]):
            r += 1
        if r < e:
            if r + 1 != e or not (buf[r] == 82 or buf[r] == 114 or buf[r] == 84
                                  or buf[r] == 116):
                return -1
        elif k != e:
            return -1
        # id
        h = j
        cid = 0
        while h < k and buf[h] != 35:
            v = _hexval(buf[h])
            if v < 0:
                return -1
            cid = cid * 16 + v
            h += 1
        nid = h - j
        if h >= k or nid == 0 or nid > 8:
            return -1
        h += 1  # '#'
        is_fd = False
        flags = 0
        if h < k and buf[h] == 35:  # CAN FD: '##' and a flags digit
            if h + 1 >= k or _hexval(buf[h + 1]) < 0 or buf[h + 1] > 57:
                return -1
            is_fd = True
            flags = buf[h + 1] - 48
            h += 2
        is_remote = False
        nbytes = 0
        if h < k and (buf[h] == 82 or buf[h] == 114):
            is_remote = True
            for q in range(h + 1, k):
                if not 48 <= buf[q] <= 57:
                    return -1
        else:
            if (k - h) % 2 != 0:
                return -1
            nbytes = (k - h) // 2
            if nbytes > width:  # longer than CAN FD allows: python-can decides
                return -1
            for b in range(nbytes):
                hi = _hexval(buf[h + 2 * b])
                lo = _hexval(buf[h + 2 * b + 1])
                if hi < 0 or lo < 0:
                    return -1
                data[n, b] = hi * 16 + lo
            for b in range(nbytes, width):
                data[n, b] = 0
        t[n] = ts
        if (cid & 0x20000000) != 0 and (cid & 0x80) != 0:
            ids[n] = 0
            err[n] = True
            ext[n] = True  # python-can's Message default
            remote[n] = False
            length[n] = 0
            fd[n] = False
            brs[n] = False
            esi[n] = False
            for b in range(width):
                data[n, b] = 0
        else:
            ids[n] = cid & 0x1FFFFFFF
            err[n] = False
            ext[n] = nid > 3
            remote[n] = is_remote
            length[n] = 0 if is_remote else nbytes
            fd[n] = is_fd
            brs[n] = is_fd and (flags & 1) != 0
            esi[n] = is_fd and (flags & 2) != 0
            if is_remote:
                for b in range(width):
                    data[n, b] = 0
        n += 1
        i = nxt
    return n

