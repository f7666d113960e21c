"""The chunk every columnar log reader yields: `FrameChunk`, a run of consecutive frames as
columns, and the ways to build one (`empty_chunk` to fill, `chunk_from_messages` and
`reader_chunks` from python-can's messages, what a compiled scanner leaves to python-can).

A frame's payload is ``data[i, :length[i]]``. `data` is 8 bytes wide, or 64 when the chunk
holds a CAN FD frame longer than 8 bytes, so no payload is ever cut short; `fd`,
`bitrate_switch` and `error_state_indicator` carry the CAN FD flags, so an FD frame gets the
same outcome (``fd_frame`` on a classic message, decoded on an FD one) in both replay paths.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import can
import numpy as np
from numpy.typing import NDArray

from monitor.bus.logfile import LogError, read_log

__all__ = ["CLASSIC_WIDTH", "DEFAULT_CHUNK_FRAMES", "FD_WIDTH", "FrameChunk", "LogReadError",
           "chunk_from_messages", "empty_chunk", "messages_to_chunks", "reader_chunks"]

DEFAULT_CHUNK_FRAMES = 1 << 18
CLASSIC_WIDTH = 8
FD_WIDTH = 64  # the longest CAN FD payload


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
