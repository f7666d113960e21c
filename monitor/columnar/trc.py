"""PEAK TRC logs (``.trc``, ``.trc.gz``, every version python-can reads) in `FrameChunk`s:
python-can's `TRCReader` (`monitor.bus.logfile.StrictTRCReader`, a line with fewer
columns than its version has is damage), its frames gathered into chunks. The per-frame
path reads the same reader, so the frames and any damage are the same by construction."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from monitor.columnar.chunk import FrameChunk, reader_chunks

__all__ = ["read"]


def read(path: Path, chunk_frames: int) -> Iterator[FrameChunk]:
    """The frames of the TRC file at `path` in chunks (`read_chunks` for ``.trc``,
    ``.trc.gz``). Opens the file now: a bad path raises here."""
    return reader_chunks(path, chunk_frames)
