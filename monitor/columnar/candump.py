"""candump ``-L`` logs (``.log``, ``.log.gz``) read into `FrameChunk`s by a compiled byte
scanner (`_scan_candump`), about ten times python-can's speed.

It follows `can.io.canutils.CanutilsLogReader` rule for rule: an ID longer than 3 digits is
extended, an ID with the error flag *and* the bus-error bit is an error frame (ID 0, no
data), any other error-flagged ID is an extended data frame, ``#R`` remote, ``##`` CAN FD.
Timestamps are converted exactly (Clinger's fast path: a decimal mantissa of at most 2^53
and at most 22 decimals, one correctly rounded division, which is what Python's ``float``
gives); a line the scanner does not take as plain (odd hex digits, exponents, more digits,
anything unexpected) sends its whole block through python-can's own reader instead, so the
result never differs, and a malformed file raises the same error. A gzip-compressed log is
scanned as it is decompressed.
"""

from __future__ import annotations

from collections.abc import Iterator
from functools import partial
from pathlib import Path
from typing import IO, TextIO, cast

import can
import numpy as np
from numpy.typing import NDArray

from monitor.bus.logfile import LogError, log_encoding, open_binary
from monitor.columnar.chunk import CLASSIC_WIDTH, FD_WIDTH, FrameChunk, empty_chunk
from monitor.columnar.text import (
    exact_decimal,
    hexval,
    is_space,
    needs_python,
    python_can_block,
    stripped_line,
    text_block,
    text_chunks,
)
from monitor.errors import one_line
from monitor.jit import njit

__all__ = ["read"]


def read(path: Path, chunk_frames: int) -> Iterator[FrameChunk]:
    """The frames of the candump log at `path` (`read_chunks` for ``.log``, ``.log.gz``).
    Opens the file now: a file that cannot be opened raises here."""
    try:
        fh = open_binary(path)
    except OSError as exc:
        raise LogError(f"{path}: cannot read log ({one_line(exc)})") from None
    return _candump_chunks(path, fh)


def _candump_chunks(path: Path, fh: IO[bytes]) -> Iterator[FrameChunk]:
    encoding = log_encoding()
    with fh:
        yield from text_chunks(path, fh, partial(_parse_candump, path, encoding))


def _parse_candump(path: Path, encoding: str, text: bytes, line: int,
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


@njit
def _scan_candump(buf: NDArray[np.uint8], t: NDArray[np.float64], ids: NDArray[np.int64],
                  ext: NDArray[np.bool_], remote: NDArray[np.bool_], err: NDArray[np.bool_],
                  length: NDArray[np.int64], data: NDArray[np.uint8], fd: NDArray[np.bool_],
                  brs: NDArray[np.bool_], esi: NDArray[np.bool_]) -> int:
    """Frames of candump -L lines into the arrays; returns the count, -1 for a line it does
    not take as plain (the caller then asks python-can). `data` is 8 or 64 bytes wide."""
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
        ts, j, dot = exact_decimal(buf, i + 1, e)
        no_digit = j - (i + 1) == (1 if dot >= 0 else 0)  # "()" or "(.)": python's float fails
        if j >= e or buf[j] != 41 or no_digit or np.isnan(ts):
            return -1
        j += 1  # ')'
        if j >= e or not is_space(buf[j]):
            return -1
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
            v = hexval(buf[h])
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
            if h + 1 >= k or hexval(buf[h + 1]) < 0 or buf[h + 1] > 57:
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
                hi = hexval(buf[h + 2 * b])
                lo = hexval(buf[h + 2 * b + 1])
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
