"""ASAM MDF4 bus logs (``.mf4``) read into `FrameChunk`s as asammdf's columns.

python-can's `can.io.MF4Reader` asks asammdf for 1,000 records at a time and builds one
`can.Message` per record; this reader asks asammdf (`MDF.get`, the same call, ``raw=False``)
for the records of a chunk at once and takes its numpy arrays as the chunk's columns: the
time stamps, ``CAN_DataFrame.ID``, ``.IDE``, ``.DataLength``, ``.DataBytes``, ``.EDL``,
``.BRS``, ``.ESI``. python-can's rules, column by column:

* the channel groups read are those `MF4Reader` reads: bus events (``FLAG_CG_BUS_EVENT``)
  with records, a CAN bus source, holding ``CAN_DataFrame``, else ``CAN_ErrorFrame``, else
  ``CAN_RemoteFrame``;
* the time of a record is its time stamp plus the header's start time; the ID is masked to
  29 bits; a field a group does not have takes `can.Message`'s default (extended ID, no
  FD flags, no data);
* a data frame's payload is its first ``DataLength`` bytes (at most the field's width), an
  error frame's too (if it has both fields), a remote frame has none;
* frames of several groups (error or remote frames beside the data frames) come out in the
  order of python-can's ``heapq.merge`` by time stamp: at each step the earliest head,
  the first group on a tie (`_merge_order`). Such a file is read whole, then cut into
  chunks; a file of one group is read a chunk at a time.

A data block asammdf cannot read hands the rest of the file to python-can's reader (from
the first frame not yet delivered), which says the damage as the per-frame path does
(`monitor.bus.logfile.mf4_damage`); a file asammdf cannot open raises `LogDamaged` before
any output.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from monitor.bus.logfile import open_mdf, quiet_asammdf
from monitor.columnar.chunk import (
    CLASSIC_WIDTH,
    FD_WIDTH,
    FrameChunk,
    empty_chunk,
    reader_chunks,
)
from monitor.jit import njit

__all__ = ["read"]

_KINDS = ("CAN_DataFrame", "CAN_ErrorFrame", "CAN_RemoteFrame")
_STEP = 1000  # python-can's records per asammdf call: a chunk is a whole number of them


def read(path: Path, chunk_frames: int) -> Iterator[FrameChunk]:
    """The frames of the MF4 file at `path` in chunks (`read_chunks` for ``.mf4``). Opens
    the file now: a file asammdf cannot open raises `LogDamaged` here."""
    return _chunks(path, open_mdf(path, _open), chunk_frames)


def _open(path: Path) -> Any:
    from asammdf import MDF  # imported when an .mf4 is read

    # no bus-logging decoding (signals from attached databases, a pass over all the data at
    # open): the raw frames only. MDF passes the option on to MDF4; its hints lack it.
    return MDF(str(path), process_bus_logging=False)  # type: ignore[call-arg]


def can_groups(mdf: Any) -> list[tuple[int, str]]:
    """(group index, kind) of the channel groups python-can's `MF4Reader` reads, in its
    order."""
    from asammdf import Source
    from asammdf.blocks.v4_constants import FLAG_CG_BUS_EVENT

    found = []
    for index, group in enumerate(mdf.groups):
        cg = group.channel_group
        source = cg.acq_source
        if not cg.flags & FLAG_CG_BUS_EVENT or cg.cycles_nr == 0 or source is None:
            continue
        if not source.source_type & Source.SOURCE_BUS or source.bus_type != Source.BUS_TYPE_CAN:
            continue
        names = [channel.name for channel in group.channels]
        kind = next((k for k in _KINDS if k in names), None)
        if kind is not None:
            found.append((index, kind))
    return found


def _chunks(path: Path, mdf: Any, chunk_frames: int) -> Iterator[FrameChunk]:
    delivered = 0
    failed = False
    try:
        start = float(mdf.header.start_time.timestamp())
        groups = can_groups(mdf)
        step = max(_STEP, chunk_frames // _STEP * _STEP)
        if len(groups) == 1:
            index, kind = groups[0]
            for offset in range(0, mdf.groups[index].channel_group.cycles_nr, step):
                try:
                    with quiet_asammdf():
                        signal = mdf.get(kind, index, record_offset=offset,
                                         record_count=step, raw=False)
                    chunk = _columns(signal, kind, start)
                except Exception:  # asammdf's or numpy's on a damaged block: python-can's
                    failed = True  # reader says it
                    break
                delivered += len(chunk)
                yield chunk
        elif groups:
            try:
                with quiet_asammdf():
                    parts = [_columns(mdf.get(kind, index, raw=False), kind, start)
                             for index, kind in groups]
                merged = _merged(parts)
            except Exception:  # as above
                failed = True
            else:
                for first in range(0, len(merged), chunk_frames):
                    rows = np.arange(first, min(len(merged), first + chunk_frames))
                    yield _take(merged, rows)
    finally:
        mdf.close()
    if failed:
        yield from reader_chunks(path, chunk_frames, skip=delivered)


def _field(samples: NDArray[Any], name: str) -> NDArray[Any] | None:
    names = samples.dtype.names or ()
    return samples[name] if name in names else None


def _columns(signal: Any, kind: str, start: float) -> FrameChunk:
    """A group's records as a chunk, by python-can's rules (the module docstring)."""
    samples = signal.samples
    n = len(samples)
    with np.errstate(invalid="ignore"):  # a damaged block's NaN time stamps stay NaN
        t = np.asarray(signal.timestamps, np.float64) + start

    def flag(name: str, default: bool) -> NDArray[np.bool_]:
        column = _field(samples, f"{kind}.{name}")
        if column is None:
            return np.full(n, default, np.bool_)
        return np.asarray(column).astype(np.bool_)

    ids = _field(samples, f"{kind}.ID")
    arbitration_id = (np.zeros(n, np.int64) if ids is None
                      else np.asarray(ids).astype(np.int64) & 0x1FFFFFFF)
    length = np.zeros(n, np.int64)
    data = np.zeros((n, CLASSIC_WIDTH), np.uint8)
    sizes = _field(samples, f"{kind}.DataLength")
    payload = _field(samples, f"{kind}.DataBytes")
    if kind != "CAN_RemoteFrame" and sizes is not None and payload is not None:
        payload = np.asarray(payload, np.uint8).reshape(n, -1)
        length = np.minimum(np.asarray(sizes).astype(np.int64), payload.shape[1])
        width = FD_WIDTH if n and int(length.max()) > CLASSIC_WIDTH else CLASSIC_WIDTH
        data = np.zeros((n, width), np.uint8)
        used = min(width, payload.shape[1])
        keep = np.arange(used)[None, :] < length[:, None]  # zero beyond each length
        data[:, :used] = np.where(keep, payload[:, :used], 0)
    remote = (np.ones(n, np.bool_) if kind == "CAN_RemoteFrame"
              else flag("RTR", False) if kind == "CAN_ErrorFrame" else np.zeros(n, np.bool_))
    fd = flag("EDL", False) if kind != "CAN_RemoteFrame" else np.zeros(n, np.bool_)
    brs = flag("BRS", False) if kind != "CAN_RemoteFrame" else np.zeros(n, np.bool_)
    esi = flag("ESI", False) if kind != "CAN_RemoteFrame" else np.zeros(n, np.bool_)
    return FrameChunk(t, arbitration_id, flag("IDE", True), remote,
                      np.full(n, kind == "CAN_ErrorFrame", np.bool_), length, data, fd, brs,
                      esi)


def _merged(parts: list[FrameChunk]) -> FrameChunk:
    """The groups' frames in python-can's merged order, as one chunk."""
    width = max(p.data.shape[1] for p in parts)
    total = sum(len(p) for p in parts)
    whole = empty_chunk(total, width)
    assert whole.bitrate_switch is not None and whole.error_state_indicator is not None
    bounds = np.zeros(len(parts) + 1, np.int64)
    at = 0
    for i, p in enumerate(parts):
        assert p.bitrate_switch is not None and p.error_state_indicator is not None
        end = at + len(p)
        whole.t[at:end] = p.t
        whole.arbitration_id[at:end] = p.arbitration_id
        whole.extended[at:end] = p.extended
        whole.remote[at:end] = p.remote
        whole.error[at:end] = p.error
        whole.length[at:end] = p.length
        whole.data[at:end, :p.data.shape[1]] = p.data
        whole.is_fd[at:end] = p.is_fd
        whole.bitrate_switch[at:end] = p.bitrate_switch
        whole.error_state_indicator[at:end] = p.error_state_indicator
        bounds[i + 1] = end
        at = end
    return _take(whole, _merge_order(whole.t, bounds))


@njit
def _merge_order(t: NDArray[np.float64], bounds: NDArray[np.int64]) -> NDArray[np.int64]:
    """The rows of the groups (group g: rows bounds[g]..bounds[g + 1]) in ``heapq.merge``'s
    order by time stamp: each step takes the earliest head, the first group on a tie (each
    group's own order kept, sorted or not, as heapq's merge keeps it)."""
    k = bounds.shape[0] - 1
    heads = bounds[:-1].copy()
    out = np.empty(bounds[-1], np.int64)
    for n in range(out.shape[0]):
        best = -1
        for g in range(k):
            if heads[g] < bounds[g + 1] and (best < 0 or t[heads[g]] < t[heads[best]]):
                best = g
        out[n] = heads[best]
        heads[best] += 1
    return out


def _take(c: FrameChunk, rows: NDArray[np.int64]) -> FrameChunk:
    assert c.bitrate_switch is not None and c.error_state_indicator is not None
    return FrameChunk(c.t[rows], c.arbitration_id[rows], c.extended[rows], c.remote[rows],
                      c.error[rows], c.length[rows], c.data[rows], c.is_fd[rows],
                      c.bitrate_switch[rows], c.error_state_indicator[rows])
