"""Shared by the log reader tests: logs written by python-can's writers (`write_log`), a
frame's fields as python-can's reader (the per-frame path) and the columnar reader give them,
random frames of every kind, and MF4 files written by asammdf itself (column by column, as a
logger's software would)."""

from __future__ import annotations

import random
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import can
import numpy as np
from numpy.typing import NDArray

from monitor.bus.logfile import LogError, read_log
from monitor.columnar import read_chunks

Frame = tuple[float, int, bool, bool, bool, bool, bool, bool, bytes, int]

WRITERS: dict[str, Callable[[Path], Any]] = {
    ".log": lambda p: can.CanutilsLogWriter(p, channel="vcan0"),
    ".asc": lambda p: can.ASCWriter(p),
    ".blf": lambda p: can.BLFWriter(p),
}


def write_log(path: Path, frames: Sequence[can.Message]) -> Path:
    """`frames` to `path` with the writer of its suffix."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with WRITERS[path.suffix](path) as writer:
        for m in frames:
            writer.on_message_received(m)
    return path


def row(m: can.Message, length: int | None = None) -> Frame:
    """A frame's fields; `length` the chunk's own (a message's is len(data))."""
    return (m.timestamp, m.arbitration_id, m.is_extended_id, m.is_remote_frame,
            m.is_error_frame, m.is_fd, m.bitrate_switch, m.error_state_indicator, bytes(m.data),
            len(m.data) if length is None else length)


def per_frame(path: Path) -> tuple[list[Frame], str | None]:
    rows: list[Frame] = []
    try:
        for m in read_log(path):
            rows.append(row(m))
    except LogError as exc:
        return rows, str(exc)
    return rows, None


def columnar(path: Path, chunk_frames: int = 1 << 18) -> tuple[list[Frame], str | None]:
    rows: list[Frame] = []
    try:
        for c in read_chunks(path, chunk_frames):
            rows.extend(row(c.message(i), int(c.length[i])) for i in range(len(c)))
    except LogError as exc:
        return rows, str(exc)
    return rows, None


def python_can(path: Path) -> list[Frame]:
    """The frames python-can's own `can.LogReader` reads from `path` (gzip included)."""
    with can.LogReader(str(path)) as reader:
        return [row(m) for m in reader]


def write_mf4(path: Path, t: NDArray[np.floating[Any]], ids: NDArray[np.int64],
              data: NDArray[np.uint8], length: NDArray[np.int64], *,
              fields: tuple[str, ...] = ("IDE", "DLC"),
              compression: Literal[0, 1, 2] = 2) -> Path:
    """A CAN bus-logging MF4 file of one CAN_DataFrame channel group written by asammdf:
    the time stamps `t` (seconds after 2026-01-01 UTC), `ids`, the payloads `data` (n, w)
    of `length` bytes, and the optional `fields` (IDE from ID > 0x7FF, DLC = length, EDL,
    BRS and ESI zero); a field left out is one the reader takes a default for."""
    from asammdf import MDF, Signal
    from asammdf.blocks.v4_blocks import SourceInformation
    from asammdf.blocks.v4_constants import BUS_TYPE_CAN, SOURCE_BUS

    n, width = data.shape
    layout = [("CAN_DataFrame.ID", "<u4"), *((f"CAN_DataFrame.{f}", "u1") for f in fields),
              ("CAN_DataFrame.DataLength", "u1"), ("CAN_DataFrame.DataBytes", f"({width},)u1")]
    samples = np.zeros(n, np.dtype(layout))
    samples["CAN_DataFrame.ID"] = ids
    samples["CAN_DataFrame.DataLength"] = length
    samples["CAN_DataFrame.DataBytes"] = data
    if "IDE" in fields:
        samples["CAN_DataFrame.IDE"] = ids > 0x7FF
    if "DLC" in fields:
        samples["CAN_DataFrame.DLC"] = length
    mdf = MDF(version="4.10")
    mdf.header.start_time = datetime(2026, 1, 1, tzinfo=UTC)
    mdf.append(Signal(name="CAN_DataFrame", samples=samples, timestamps=t,
                      source=SourceInformation(source_type=SOURCE_BUS, bus_type=BUS_TYPE_CAN)))
    mdf.save(str(path), overwrite=True, compression=compression)
    mdf.close()
    return path


def random_frames(n: int, seed: int) -> list[can.Message]:
    rng = random.Random(seed)
    t = 1.7e9 + rng.random()
    out = []
    for _ in range(n):
        t += rng.choice((1e-6, 1e-4, 0.001, 0.0137))
        kind = rng.random()
        ext = rng.random() < 0.3
        fid = rng.getrandbits(29 if ext else 11)
        if kind < 0.05:
            out.append(can.Message(timestamp=t, is_error_frame=True, arbitration_id=fid,
                                   is_extended_id=ext, data=bytes(rng.getrandbits(8)
                                                                  for _ in range(8))))
        elif kind < 0.1:
            out.append(can.Message(timestamp=t, arbitration_id=fid, is_extended_id=ext,
                                   is_remote_frame=True, dlc=rng.randint(0, 8)))
        elif kind < 0.4:
            size = rng.choice((0, 1, 8, 12, 16, 20, 24, 32, 48, 64))
            out.append(can.Message(timestamp=t, arbitration_id=fid, is_extended_id=ext,
                                   is_fd=True, bitrate_switch=rng.random() < 0.5,
                                   error_state_indicator=rng.random() < 0.2,
                                   data=rng.randbytes(size)))
        else:
            out.append(can.Message(timestamp=t, arbitration_id=fid, is_extended_id=ext,
                                   data=rng.randbytes(rng.randint(0, 8))))
    return out
