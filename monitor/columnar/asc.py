"""Vector ASC logs (``.asc``, ``.asc.gz``) read into `FrameChunk`s by a compiled line scanner.

python-can's `can.io.ASCReader` matches regular expressions and builds one `can.Message` per
line (about 70,000 frames/s), which caps a columnar replay of an ASC archive far below the
rest of the engine. This reader keeps python-can's rules: the header is read by python-can
itself (`ASCReader._extract_header`: ``date``, ``base hex|dec``, comments, up to and including
the first other line, which python-can drops), and `_scan_asc` walks the following lines in
blocks of some megabytes, rule for rule as `ASCReader.__iter__` with its default relative
time stamps (the line's time, no start time added):

* a line that does not start with ``<digits>.<digits><space>`` is skipped (comments, trigger
  blocks, ``End TriggerBlock``); so is ``Start of measurement``, a channel that is neither
  digits nor exactly ``CANFD``, a classic line whose ID is not a word or whose direction does
  not start with Tx/Rx (statistics, J1939 lines), and a ``CANFD`` with nothing after it;
* a classic data frame ``<t> <ch> <id>[x] Tx|Rx d <dlc> <bytes>``: the ID in the header's
  base (``x``: extended), ``min(8, dlc2len(dlc))`` data bytes, fewer if the line ends first,
  anything after them ignored (``Length = ...``);
* a CAN FD frame ``<t> CANFD <ch> Tx|Rx <id> [<name>] <brs> <esi> <dlc> <length> <bytes>``:
  BRS and ESI where the field is exactly ``1``, ``length`` (decimal) bytes, a remote frame
  for length 0.

Anything else -- an error frame, a classic remote frame, a DLC that does not match an FD
frame's length (python-can warns), a field python's ``int`` would read another way (signs,
``0x``, underscores, more digits), a time stamp of more than 17 significant digits, a line
python-can would fail on, and any byte a text file read by python-can would see otherwise
(non-ASCII, a lone carriage return, the separators that Python's ``str.split`` counts as
space) -- sends its whole block through python-can's own reader, so the frames and any
error are exactly python-can's. Damage (a line python-can cannot read or that is no text, a
last line without its line end, a gzip stream cut short or damaged, no End TriggerBlock)
is said as the per-frame path says it (`monitor.bus.logfile`), at the same line. A
gzip-compressed log is scanned as it is decompressed.
"""

from __future__ import annotations

import io
from collections.abc import Iterator
from functools import partial
from pathlib import Path
from typing import IO, TextIO, cast

import can
import numpy as np
from numpy.typing import NDArray

from monitor.bus.logfile import (
    LogError,
    asc_unfinished,
    damaged,
    log_encoding,
    open_binary,
)
from monitor.columnar.chunk import (
    CLASSIC_WIDTH,
    FD_WIDTH,
    FrameChunk,
    empty_chunk,
    reader_chunks,
)
from monitor.columnar.text import (
    count_lines,
    exact_decimal,
    hexval,
    is_space,
    needs_python,
    python_can_block,
    read_block,
    stripped_line,
    text_block,
    text_chunks,
)
from monitor.errors import one_line
from monitor.jit import njit

__all__ = ["asc_chunks", "read"]

_HEAD_BYTES = 1 << 20  # the header must end within this much of the file's start
_FD_LENGTHS = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64], np.int64)


def read(path: Path, chunk_frames: int) -> Iterator[FrameChunk]:
    """The frames of the ASC file at `path` in chunks (`read_chunks` for ``.asc``,
    ``.asc.gz``). Opens the file now: a file that cannot be opened raises here."""
    try:
        fh = open_binary(path)
    except OSError as exc:
        raise LogError(f"{path}: cannot read log ({one_line(exc)})") from None
    return _chunks(path, fh, chunk_frames)


asc_chunks = read


def _chunks(path: Path, fh: IO[bytes], chunk_frames: int) -> Iterator[FrameChunk]:
    encoding = log_encoding()  # what python-can opens the file with
    with fh:
        head, broken = read_block(fh, _HEAD_BYTES)
        header = None if broken is not None else _header(head)
        if header is None:  # python-can reads the file (and says where a gzip broke)
            fh.close()
            yield from reader_chunks(path, chunk_frames)
            return
        base_name, offset = header
        base = 10 if base_name == "dec" else 16
        line = count_lines(head[:offset])  # lines before the block
        fh.seek(offset)
        frames = yield from text_chunks(
            path, fh, partial(_block, path, base, base_name, encoding), line=line)
    end = asc_unfinished(path)
    if end is not None:
        raise damaged(path, "truncated", frames=frames, where=f"byte {end}",
                      detail="no End TriggerBlock")


def _header(head: bytes) -> tuple[str, int] | None:
    """python-can's reading of the header: (base, byte offset of the first line after it),
    or None when this reader leaves the file to python-can (the header does not end within
    `head`, or holds bytes that are not plain ASCII lines)."""
    cut = head.rfind(b"\n") + 1
    text_bytes = head[:cut]
    if not text_bytes or needs_python(np.frombuffer(text_bytes, np.uint8)):
        return None
    reader = can.io.ASCReader(io.StringIO(text_bytes.decode("ascii")))
    extract = getattr(reader, "_extract_header", None)
    if extract is None:  # a python-can that reads its header otherwise
        return None
    extract()
    consumed = reader.file.tell()
    if consumed >= len(text_bytes):
        return None  # the header may go on past what was read
    return reader.base, consumed  # ASCII, "\r\n" kept as it is: characters are bytes


def _block(path: Path, base: int, base_name: str, encoding: str, text: bytes, line: int,
           frames: int) -> Iterator[FrameChunk]:
    """The frames of whole lines `text`, after `line` lines and `frames` frames."""
    buf = np.frombuffer(text, np.uint8)
    if not needs_python(buf):
        c = empty_chunk(text.count(b"\n") + 1,
                        FD_WIDTH if b"CANFD" in text else CLASSIC_WIDTH)
        assert c.bitrate_switch is not None and c.error_state_indicator is not None
        n = _scan_asc(buf, base, c.t, c.arbitration_id, c.extended, c.remote, c.error,
                      c.length, c.data, c.is_fd, c.bitrate_switch, c.error_state_indicator)
        if n >= 0:
            if n:
                yield c.head(n)
            return
    # python-can reads this block: its text as the file's text mode gives it (universal
    # newlines), after an empty line for the header python-can looks for first
    lines = text_block(text, encoding, line, prefix="\n")
    reader = can.io.ASCReader(cast(TextIO, lines), base=base_name)
    yield from python_can_block(path, reader, lines, frames)


@njit
def _digit(ch: int, base: int) -> int:
    """The value of an ASCII digit in `base` (10 or 16), else -1."""
    d = hexval(ch)
    return d if d < base else -1


@njit
def _word(ch: int) -> bool:
    """A regular expression's ``\\w`` under ``re.ASCII``."""
    return 48 <= ch <= 57 or 65 <= ch <= 90 or 97 <= ch <= 122 or ch == 95


@njit
def _lower(ch: int) -> int:
    return ch + 32 if 65 <= ch <= 90 else ch


@njit
def _next_token(buf: NDArray[np.uint8], j: int, e: int) -> tuple[int, int]:
    """The token at or after `j` (skipping space) up to `e`: (start, end); start == e if
    none."""
    while j < e and is_space(buf[j]):
        j += 1
    k = j
    while k < e and not is_space(buf[k]):
        k += 1
    return j, k


@njit
def _time_stamp(buf: NDArray[np.uint8], j: int, e: int) -> tuple[float, int]:
    """``<digits>.<digits>`` and a space at `j` (python-can's pattern): (seconds, end); end
    -1 if the line does not match, -2 if it has more digits than one correctly rounded
    division converts exactly (more than 17 significant, or 22 after the point)."""
    t, k, dot = exact_decimal(buf, j, e)
    if dot <= j or k == dot + 1 or k >= e or not is_space(buf[k]):
        return 0.0, -1
    if np.isnan(t):
        return 0.0, -2
    return t, k


@njit
def _all_digits(buf: NDArray[np.uint8], a: int, b: int) -> bool:
    """Whether [a, b) is one or more ASCII digits (``str.isdigit`` on ASCII)."""
    if b <= a:
        return False
    for q in range(a, b):  # noqa: SIM110 (numba compiles no generator expression)
        if not 48 <= buf[q] <= 57:
            return False
    return True


@njit
def _number(buf: NDArray[np.uint8], a: int, b: int, base: int, max_digits: int) -> int:
    """The token [a, b) as a number in `base`, -1 unless it is 1..max_digits plain digits."""
    if b <= a or b - a > max_digits:
        return -1
    v = 0
    for q in range(a, b):
        d = _digit(buf[q], base)
        if d < 0:
            return -1
        v = v * base + d
    return v


@njit
def _starts_ci(buf: NDArray[np.uint8], a: int, e: int, word: bytes) -> bool:
    """Whether [a, e) starts with the lower-case ASCII `word`, in any case."""
    if e - a < len(word):
        return False
    for q in range(len(word)):  # noqa: SIM110 (numba compiles no generator expression)
        if _lower(buf[a + q]) != word[q]:
            return False
    return True


@njit
def _can_id(buf: NDArray[np.uint8], a: int, b: int, base: int) -> tuple[int, bool]:
    """python-can's ``_extract_can_id``: (ID, extended), ID -1 if ``int`` might read the
    token otherwise."""
    extended = b > a and (buf[b - 1] == 120 or buf[b - 1] == 88)  # x, X
    if extended:
        b -= 1
    return _number(buf, a, b, base, 8 if base == 16 else 10), extended


@njit
def _data_bytes(buf: NDArray[np.uint8], j: int, e: int, count: int, base: int,
                row: NDArray[np.uint8]) -> int:
    """Up to `count` byte tokens from `j` into `row`: how many, -1 for one ``int`` might
    read otherwise or that is over 255."""
    got = 0
    while got < count:
        a, b = _next_token(buf, j, e)
        if a >= e:
            break
        v = _number(buf, a, b, base, 2 if base == 16 else 3)
        if v < 0 or v > 255:
            return -1
        row[got] = v
        got += 1
        j = b
    return got


@njit
def _scan_asc(buf: NDArray[np.uint8], base: int, t: NDArray[np.float64],
              ids: NDArray[np.int64], ext: NDArray[np.bool_], remote: NDArray[np.bool_],
              err: NDArray[np.bool_], length: NDArray[np.int64], data: NDArray[np.uint8],
              fd: NDArray[np.bool_], brs: NDArray[np.bool_], esi: NDArray[np.bool_]) -> int:
    """Frames of ASC lines (after the header) into the arrays; returns the count, -1 for a
    line python-can must read (see the module docstring). `data` is 8 or 64 bytes wide."""
    width = data.shape[1]
    size = buf.shape[0]
    n = 0
    i = 0
    while i < size:
        line, e, i = stripped_line(buf, i)
        if line == e or _digit(buf[line], 10) < 0:
            continue  # comments, trigger blocks: no message there
        # the time stamp: <digits>.<digits> and space, else no message on this line
        ts, j = _time_stamp(buf, line, e)
        if j == -1:
            continue
        if j == -2:
            return -1  # a number this scanner does not convert exactly
        a2, b2 = _next_token(buf, j, e)
        if a2 >= e:
            continue
        is_fd = (b2 - a2 == 5 and buf[a2] == 67 and buf[a2 + 1] == 65 and buf[a2 + 2] == 78
                 and buf[a2 + 3] == 70 and buf[a2 + 4] == 68)  # CANFD
        if not is_fd:
            if not _all_digits(buf, a2, b2):
                continue  # neither a channel nor CANFD: "Start of measurement", events
            a3, b3 = _next_token(buf, b2, e)
            if a3 >= e:
                continue
            if _starts_ci(buf, a3, e, b"errorframe"):
                return -1  # an error frame
            word = True
            for q in range(a3, b3):
                if not _word(buf[q]):
                    word = False
            a4, b4 = _next_token(buf, b3, e)
            if not word or a4 >= e or not (_starts_ci(buf, a4, e, b"tx")
                                           or _starts_ci(buf, a4, e, b"rx")):
                continue  # statistics, J1939: not a frame
            a5, b5 = _next_token(buf, b4, e)
            if a5 >= e or _lower(buf[a5]) == 114:
                return -1  # no frame type (python-can fails), or a remote frame
            a6, b6 = _next_token(buf, b5, e)
            if a6 >= e:
                return -1  # no DLC: python-can fails
            cid, extended = _can_id(buf, a3, b3, base)
            dlc = _number(buf, a6, b6, base, 2)
            if cid < 0 or dlc < 0:
                return -1
            count = min(8, _FD_LENGTHS[dlc] if dlc <= 15 else 64)
            got = _data_bytes(buf, b6, e, count, base, data[n])
            if got < 0:
                return -1
            bitrate_switch = False
            error_state = False
            is_remote = False
        else:
            a3, b3 = _next_token(buf, b2, e)  # channel
            if a3 >= e:
                continue  # "<t> CANFD" alone: python-can skips it
            a4, b4 = _next_token(buf, b3, e)  # direction
            a5, b5 = _next_token(buf, b4, e)  # ID
            if a5 >= e or _number(buf, a3, b3, 10, 9) < 0:
                return -1
            if _starts_ci(buf, a5, e, b"errorframe"):
                return -1
            a6, b6 = _next_token(buf, b5, e)  # symbolic name, or BRS
            if a6 >= e:
                return -1
            named = not _all_digits(buf, a6, b6)
            if named:
                a6, b6 = _next_token(buf, b6, e)
            a7, b7 = _next_token(buf, b6, e)  # ESI
            a8, b8 = _next_token(buf, b7, e)  # DLC
            a9, b9 = _next_token(buf, b8, e)  # data length
            a10, _ = _next_token(buf, b9, e)  # data: python-can needs something there
            if a10 >= e:
                return -1
            cid, extended = _can_id(buf, a5, b5, base)
            dlc = _number(buf, a8, b8, base, 2)
            dl = _number(buf, a9, b9, 10, 2)
            if cid < 0 or dlc < 0 or dl < 0:
                return -1
            bitrate_switch = b6 - a6 == 1 and buf[a6] == 49
            error_state = b7 - a7 == 1 and buf[a7] == 49
            is_remote = dl == 0
            if not is_remote and (dl > width or (_FD_LENGTHS[dlc] if dlc <= 15 else 64) != dl):
                return -1  # python-can warns of the mismatch
            got = _data_bytes(buf, b9, e, dl, base, data[n])
            if got < 0:
                return -1
        for q in range(got, width):
            data[n, q] = 0
        t[n] = ts
        ids[n] = cid
        ext[n] = extended
        remote[n] = is_remote
        err[n] = False
        length[n] = got
        fd[n] = is_fd
        brs[n] = bitrate_switch
        esi[n] = error_state
        n += 1
    return n
