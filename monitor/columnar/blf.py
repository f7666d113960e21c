"""Vector BLF logs read into `FrameChunk`s by a compiled object scanner.

python-can's `can.io.BLFReader` builds one `can.Message` per frame (about 80,000-210,000
frames/s), which caps a columnar replay of a BLF archive -- the daemon's own raw record
format -- far below the rest of the engine. This reader keeps python-can's rules and its
file-header parsing (`BLFReader` opens the file and gives the start time) and does the
rest in bulk: each log container is inflated by zlib, the inflated bytes are gathered into
blocks of some megabytes, and `_scan_objects` walks a block's objects in compiled code,
writing frames straight into the arrays. Rule for rule as `BLFReader._parse_data`:

* objects are found at "LOBJ" within the 8 bytes after the previous one (padding), an
  object that continues in the next container waits for it (the block's tail);
* header versions 1 and 2; flags 1: timestamps in 10 us, else in ns, converted with one
  correctly rounded division (python-can's exact decimal product, rounded once);
* CAN_MESSAGE / CAN_MESSAGE2, CAN_ERROR_EXT, CAN_FD_MESSAGE, CAN_FD_MESSAGE_64 (its data
  field cut at the extended-data offset and zero-padded to its valid bytes, python-can
  issue 1905) become frames; every other object is skipped;
* anything else -- an unknown header version or compression method, no "LOBJ" where one
  must be, a timestamp past 2^53 units, a payload over 64 bytes -- hands the rest of the
  file to python-can's own reader (from the first frame not yet delivered), so the frames
  and any error are exactly python-can's.

A file cut short is found as the per-frame path finds it (`monitor.bus.logfile.blf_damage`,
from the file's objects and the unfinished object the scanner is left with): the frames
before the cut come out, then `LogDamaged`.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Generator, Iterator
from pathlib import Path

import can
import numpy as np
from numpy.typing import NDArray

from monitor.bus.logfile import READ_ERRORS, blf_damage, damaged, malformed, open_reader
from monitor.columnar.chunk import (
    CLASSIC_WIDTH,
    FD_WIDTH,
    FrameChunk,
    empty_chunk,
    reader_chunks,
)
from monitor.jit import njit

__all__ = ["blf_chunks", "read"]

_OBJ_HEADER = struct.Struct("<4sHHLL")  # signature, header size, version, size, type
_CONTAINER = struct.Struct("<H6xL4x")  # compression method, uncompressed size
_LOG_CONTAINER = 10
_NO_COMPRESSION = 0
_ZLIB_DEFLATE = 2
_BLOCK_BYTES = 1 << 23  # inflated bytes scanned per call (about 170,000 classic frames)


class _Fallback(Exception):
    """Something the scanner leaves to python-can's reader."""


def blf_chunks(path: Path, chunk_frames: int) -> Iterator[FrameChunk]:
    """The frames of the BLF file at `path` in chunks (`read_chunks` for ``.blf``). Opens
    the file now: a missing file or a damaged header raises here, before any output."""
    reader = open_reader(path)
    assert isinstance(reader, can.io.BLFReader)
    return _chunks(path, reader, chunk_frames)


read = blf_chunks


def _chunks(path: Path, reader: can.io.BLFReader, chunk_frames: int) -> Iterator[FrameChunk]:
    delivered = 0
    tail: bytes | None = None  # None: the scanner left the rest of the file to python-can
    try:
        scan = _scan_file(reader, chunk_frames)
        try:
            while True:
                try:
                    chunk = next(scan)
                except StopIteration as done:
                    tail = done.value
                    break
                delivered += len(chunk)
                yield chunk
        except _Fallback:
            pass
        finally:
            reader.stop()
    except READ_ERRORS as exc:
        raise malformed(path, exc, frames=delivered) from None
    if tail is None:  # python-can's frames after those delivered, and its damage
        yield from reader_chunks(path, chunk_frames, skip=delivered)
        return
    found = blf_damage(path, tail)
    if found is not None:
        raise damaged(path, "truncated", frames=delivered, where=found[0], detail=found[1])


def _scan_file(reader: can.io.BLFReader,
               chunk_frames: int) -> Generator[FrameChunk, None, bytes]:
    """The frames of the file's log containers; returns what is left of them at the end
    (an object the file does not finish, or padding)."""
    fh = reader.file
    start = float(reader.start_timestamp)
    pending: list[bytes] = []
    size = 0
    tail = b""
    target = min(_BLOCK_BYTES, max(1 << 16, chunk_frames * 48))
    while True:
        head = fh.read(_OBJ_HEADER.size)
        if not head:
            break
        if len(head) < _OBJ_HEADER.size:
            raise _Fallback  # python-can raises struct.error here
        signature, _, _, obj_size, obj_type = _OBJ_HEADER.unpack(head)
        if signature != b"LOBJ" or obj_size < _OBJ_HEADER.size:
            raise _Fallback
        body = fh.read(obj_size - _OBJ_HEADER.size)
        fh.read(obj_size % 4)
        if obj_type != _LOG_CONTAINER:
            continue
        if len(body) < _CONTAINER.size:
            raise _Fallback
        method = _CONTAINER.unpack_from(body)[0]
        if method == _NO_COMPRESSION:
            pending.append(body[_CONTAINER.size:])
        elif method == _ZLIB_DEFLATE:
            try:
                pending.append(zlib.decompressobj().decompress(body[_CONTAINER.size:]))
            except zlib.error:  # python-can delivers the frames before it, then raises
                raise _Fallback from None
        else:
            raise _Fallback  # python-can warns and skips the container
        size += len(pending[-1])
        if size >= target:
            chunk, tail = _scan_block(tail + b"".join(pending), start)
            pending, size = [], 0
            if len(chunk):
                yield chunk
    chunk, tail = _scan_block(tail + b"".join(pending), start)
    if len(chunk):
        yield chunk
    return tail


def _scan_block(block: bytes, start: float) -> tuple[FrameChunk, bytes]:
    """The frames of the whole objects in `block`, and the bytes of an unfinished one."""
    buf = np.frombuffer(block, np.uint8)
    cap = len(block) // 32 + 1  # an object is at least 32 bytes
    c = empty_chunk(cap, FD_WIDTH)
    assert c.bitrate_switch is not None and c.error_state_indicator is not None
    n, consumed = _scan_objects(buf, start, c.t, c.arbitration_id, c.extended, c.remote,
                                c.error, c.length, c.data, c.is_fd, c.bitrate_switch,
                                c.error_state_indicator)
    if n < 0:
        raise _Fallback
    width = FD_WIDTH if n and int(c.length[:n].max()) > CLASSIC_WIDTH else CLASSIC_WIDTH
    return c.head(n, width), block[consumed:]


@njit
def _u16(b: NDArray[np.uint8], i: int) -> int:
    return int(b[i]) | (int(b[i + 1]) << 8)


@njit
def _u32(b: NDArray[np.uint8], i: int) -> int:
    return _u16(b, i) | (_u16(b, i + 2) << 16)


@njit
def _scan_objects(buf: NDArray[np.uint8], start: float, t: NDArray[np.float64],
                  ids: NDArray[np.int64], ext: NDArray[np.bool_], remote: NDArray[np.bool_],
                  err: NDArray[np.bool_], length: NDArray[np.int64], data: NDArray[np.uint8],
                  fd: NDArray[np.bool_], brs: NDArray[np.bool_], esi: NDArray[np.bool_]
                  ) -> tuple[int, int]:
    """(frames written, bytes consumed) of the inflated objects in `buf`; (-1, 0) for
    anything left to python-can. An object cut at the end is not consumed."""
    size = buf.shape[0]
    n = 0
    pos = 0
    while True:
        obj = -1
        for k in range(pos, min(pos + 5, size - 3)):  # "LOBJ" within [pos, pos + 8)
            if buf[k] == 76 and buf[k + 1] == 79 and buf[k + 2] == 66 and buf[k + 3] == 74:
                obj = k
                break
        if obj < 0:
            if pos + 8 > size:
                return n, pos
            return -1, 0
        if obj + 16 > size:
            return n, pos
        header_size = _u16(buf, obj + 4)
        version = _u16(buf, obj + 6)
        obj_size = _u32(buf, obj + 8)
        obj_type = _u32(buf, obj + 12)
        nxt = obj + obj_size
        if nxt > size:
            return n, pos
        p = obj + 16
        if version == 1:
            hdr = 16
        elif version == 2:
            hdr = 24
        else:
            return -1, 0
        if p + hdr > size:
            return n, pos
        flags = _u32(buf, p)
        high = _u32(buf, p + 12)
        stamp = _u32(buf, p + 8) + (high << 32)
        p += hdr
        if (obj_type == 1 or obj_type == 86 or obj_type == 73 or obj_type == 100
                or obj_type == 101):
            if high >= 1 << 21:  # 2^53 units or more: not exact in a double
                return -1, 0
            ts = stamp / 1e5 if flags == 1 else stamp / 1e9
            t[n] = ts + start
        # the frame's fields by object type, then one write of them: (ID word, remote,
        # error, length, data bytes copied from `src`, FD/BRS/ESI as bits 0..2)
        if obj_type == 1 or obj_type == 86:  # CAN_MESSAGE(2): <HBBL8s
            if p + 16 > size:
                return n, pos
            is_remote = (buf[p + 2] & 0x80) != 0
            valid = 0 if is_remote else min(int(buf[p + 3]), 8)  # remote: no data (can.Message)
            can_id, is_error, copied, src, fd_bits = _u32(buf, p + 4), False, valid, p + 8, 0
        elif obj_type == 73:  # CAN_ERROR_EXT: <HHLBBBxLLH2x8s
            if p + 32 > size:
                return n, pos
            valid = min(int(buf[p + 10]), 8)
            can_id, is_remote, is_error, copied, src, fd_bits = (_u32(buf, p + 16), False, True,
                                                                 valid, p + 24, 0)
        elif obj_type == 100:  # CAN_FD_MESSAGE: <HBBLLBBB5x64s
            if p + 84 > size:
                return n, pos
            is_remote = (buf[p + 2] & 0x80) != 0
            valid = 0 if is_remote else min(int(buf[p + 14]), 64)
            can_id, is_error, copied, src = _u32(buf, p + 4), False, valid, p + 20
            fd_bits = int(buf[p + 13]) & 0x7
        elif obj_type == 101:  # CAN_FD_MESSAGE_64: <BBBBLLLLLLLHBBL, then the data
            if p + 40 > size:
                return n, pos
            valid = int(buf[p + 2])
            if valid > 64:
                return -1, 0
            fd_flags = _u32(buf, p + 12)
            ext_offset = int(buf[p + 35])
            copied = min(valid, (ext_offset if ext_offset else obj_size) - header_size - 40)
            copied = max(0, min(copied, size - (p + 40)))  # python's slice stops at the end
            is_remote = (fd_flags & 0x0010) != 0
            if is_remote:
                valid = copied = 0
            can_id, is_error, src, fd_bits = _u32(buf, p + 4), False, p + 40, (fd_flags >> 12) & 0x7
        else:
            pos = nxt
            continue
        ids[n] = can_id & 0x1FFFFFFF
        ext[n] = (can_id & 0x80000000) != 0
        remote[n] = is_remote
        err[n] = is_error
        length[n] = valid
        for j in range(copied):
            data[n, j] = buf[src + j]
        fd[n] = (fd_bits & 0x1) != 0
        brs[n] = (fd_bits & 0x2) != 0
        esi[n] = (fd_bits & 0x4) != 0
        n += 1
        pos = nxt
