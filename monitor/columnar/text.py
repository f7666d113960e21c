"""The text scanning the columnar readers of text logs share (`candump`, `asc`): a log read
block by block (`text_chunks`, damage said where it stopped) in blocks of
whole lines read from the file (gzip-compressed or not), lines counted and numbered as a
file read in text mode numbers them (universal newlines), the bytes that make a block go
through python-can's own reader instead of a compiled scanner, python-can's reading of such a
block with its damage located, and the compiled primitives of the scanners (white space,
stripped lines, hex digits, exact decimal time stamps)."""

from __future__ import annotations

import gzip
import io
from collections.abc import Callable, Generator, Iterator
from pathlib import Path
from typing import IO

import can
import numpy as np
from numpy.typing import NDArray

from monitor.bus.logfile import (
    GZIP_ERRORS,
    READ_ERRORS,
    LogError,
    NumberedLines,
    damaged,
    gzip_damage,
    malformed,
    text_lines,
)
from monitor.columnar.chunk import FrameChunk, chunk_from_messages
from monitor.jit import njit

__all__ = ["POW10", "count_lines", "exact_decimal", "hexval", "is_space", "needs_python",
           "python_can_block", "read_block", "stripped_line", "text_block", "text_chunks"]

READ_BYTES = 1 << 24  # text read per call (about 330,000 candump lines)


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


class StreamBroken(Exception):
    """A gzip stream that broke (`cause`, one of `GZIP_ERRORS`) after the lines before it
    were given: the caller says it as the per-frame path does (`gzip_damage`, at the next
    line)."""

    def __init__(self, cause: BaseException) -> None:
        super().__init__(str(cause))
        self.cause = cause


_GZIP_STEP = 8192  # what a text file reads of a gzip stream per call (TextIOWrapper)


def read_block(fh: IO[bytes], size: int) -> tuple[bytes, BaseException | None]:
    """About `size` bytes of `fh`, and the gzip stream's failure if it broke: the bytes
    decompressed before it are kept, in steps of the size a text file reads, so that they
    are those python-can's reader sees before the same failure."""
    if not isinstance(fh, gzip.GzipFile):
        return fh.read(size), None
    parts: list[bytes] = []
    got = 0
    while got < size:
        try:
            part = fh.read1(_GZIP_STEP)
        except GZIP_ERRORS as exc:
            return b"".join(parts), exc
        if not part:
            break
        parts.append(part)
        got += len(part)
    return b"".join(parts), None


def line_blocks(fh: IO[bytes], size: int = READ_BYTES) -> Iterator[bytes]:
    """The rest of the file in blocks of about `size` bytes, each cut after a line end (the
    last one as the file ends); `StreamBroken` after the whole lines before a broken gzip
    stream (the line it broke in is not given)."""
    tail = b""
    while True:
        block, broken = read_block(fh, size)
        if broken is not None:
            buf = tail + block
            cut = buf.rfind(b"\n") + 1
            if cut:
                yield buf[:cut]
            raise StreamBroken(broken)
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


def text_chunks(path: Path, fh: IO[bytes],
                parse: Callable[[bytes, int, int], Iterator[FrameChunk]], *, line: int = 0,
                size: int = READ_BYTES) -> Generator[FrameChunk, None, int]:
    """The chunks `parse` makes of the rest of the text log `fh`, one block of whole lines
    at a time (`parse(text, line, frames)`: the lines after `line` lines and `frames`
    frames of the file); returns the file's frames. Damage is said as the per-frame path
    says it: a gzip stream that broke (`gzip_damage`) and a last line without its line end
    (`cut_line_error`), each at the line it stopped in."""
    frames = 0
    blocks = line_blocks(fh, size)
    while True:
        try:
            block = next(blocks, None)
        except StreamBroken as broken:
            raise gzip_damage(path, broken.cause, frames=frames, line=line + 1) from None
        if block is None:
            return frames
        text, cut = split_cut_line(block)
        if text:
            for chunk in parse(text, line, frames):
                frames += len(chunk)
                yield chunk
            line += count_lines(text)
        if cut:
            raise cut_line_error(path, frames, line + 1)


POW10 = np.array([10.0 ** k for k in range(23)])
"""Exact powers of ten up to 10^22: a decimal of at most 2^53 over one of them is one
correctly rounded division (Clinger's fast path), what Python's ``float`` gives."""


@njit
def exact_decimal(buf: NDArray[np.uint8], k: int, e: int) -> tuple[float, int, int]:
    """The decimal ``<digits>[.<digits>]`` at `k` (before `e`): (value, end: the first byte
    that is neither a digit nor the first point, the point's position or -1). The value is
    NaN when the number has more digits than one correctly rounded division converts
    exactly (more than 17 significant, or 22 after the point)."""
    mant = 0
    digits = 0
    frac = 0
    dot = -1
    while k < e:
        ch = buf[k]
        if ch == 46 and dot < 0:
            dot = k
        elif 48 <= ch <= 57:
            if digits > 0 or ch != 48:
                digits += 1
            if digits <= 17:
                mant = mant * 10 + (ch - 48)
            if dot >= 0:
                frac += 1
        else:
            break
        k += 1
    if digits > 17 or mant > 9007199254740992 or frac > 22:
        return np.nan, k, dot
    return float(mant) / POW10[frac], k, dot


@njit
def hexval(ch: int) -> int:
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
