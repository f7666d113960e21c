"""Bus logs read in large chunks into arrays: `read_chunks(path)` yields `FrameChunk`s.

Laid out as python-can's ``can/io``: one chunk type (`FrameChunk`, `monitor.columnar.chunk`),
the text scanning the text formats share written once (`monitor.columnar.text`), one module
per format, each with ``read(path, chunk_frames)``, found through the one suffix table
(`monitor.bus.logfile.LOG_FORMATS`, its ``columnar`` field):

* `candump` (``.log``, ``.log.gz``): a compiled byte scanner, about ten times python-can's
  speed;
* `asc` (``.asc``, ``.asc.gz``): a compiled line scanner after python-can has read the
  header;
* `blf`: a compiled object scanner over the inflated log containers, python-can's
  file-header parsing;
* `mf4`: asammdf's columns of the CAN_DataFrame (error, remote) channel groups, whole
  arrays, no message built;
* `trc` (``.trc``, ``.trc.gz``): python-can's reader, in chunks.

Every reader gives exactly the frames python-can's reader of the per-frame path gives for
the same file (`monitor.bus.logfile.read_log`); what a compiled scanner does not take goes
through python-can's reader, so the result never differs. Under NUMBA_DISABLE_JIT (the
hardened unit) every format but candump is read by python-can.

Damage is found as `monitor.bus.logfile` finds it for the per-frame path, with the same
line: the frames before it come out, then `LogDamaged` (a line python-can cannot read, or
that is no text in the locale's encoding, at its line number; a last line without its line
end; a gzip stream cut short or damaged; an ASC without its End TriggerBlock; a BLF cut
short; an MF4 data block asammdf cannot read). Lines are numbered as a file read in text
mode numbers them (universal newlines).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Final

from monitor.bus.logfile import LOG_FORMATS, check_log_path
from monitor.columnar import asc, blf, candump, mf4, trc
from monitor.columnar.chunk import DEFAULT_CHUNK_FRAMES, FrameChunk, LogReadError, reader_chunks
from monitor.jit import JIT_DISABLED

__all__ = ["DEFAULT_CHUNK_FRAMES", "FrameChunk", "LogReadError", "read_chunks"]

_READERS: Final[dict[str, Callable[[Path, int], Iterator[FrameChunk]]]] = {
    "candump": candump.read, "asc": asc.read, "blf": blf.read, "mf4": mf4.read, "trc": trc.read}
"""Each format module's reader, by `LogFormat.columnar` (every one `LOG_FORMATS` names)."""
assert {f.columnar for f in LOG_FORMATS.values()} <= _READERS.keys()


def read_chunks(path: Path, chunk_frames: int = DEFAULT_CHUNK_FRAMES) -> Iterator[FrameChunk]:
    """The frames of a log of any format we read (`LOG_FORMATS`), `chunk_frames` at a time.

    Not a generator itself: a bad path raises `LogReadError` here, before the caller opens
    outputs.
    """
    path = Path(path)
    fmt = check_log_path(path)
    if JIT_DISABLED and fmt.columnar != "candump":
        return reader_chunks(path, chunk_frames)
    return _READERS[fmt.columnar](path, chunk_frames)
