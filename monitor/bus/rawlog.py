"""The raw bus as the lossless record: every frame the monitor receives -- valid, rejected
and error frames, with their kernel timestamps -- written to rotating log files through
python-can's own writers (Vector .blf by default, candump .log on request), so that
a diagnosis can be re-run later with a better model or thresholds (`motor-monitor replay`
reproduces the live run's events from these files).

`RotatingBusLog` is a python-can `BaseRotatingLogger` (a `can.Listener`): it rotates by
size and age like the recordings, into one directory, with the same retention
(`monitor.files.FileSeries`). `flush` (called every `flush_interval_s` by the daemon) pushes
what the writer buffers to the operating system, so a SIGKILL loses at most that interval:
for BLF it closes the open compressed container and rewrites the file header (start time,
object count), which python-can's `BLFWriter` otherwise does only in `stop`, so that a file
cut short by a kill still reads back with absolute timestamps. The BLF writer has no public
call for either; the two private ones used are pinned with python-can in constraints.txt
and tested (tests/bus/test_rawlog.py).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, ClassVar

import can
from can.io.generic import MessageWriter

from monitor.files import FileSeries

__all__ = ["RAW_FORMATS", "RotatingBusLog"]

log = logging.getLogger(__name__)

RAW_FORMATS = (".blf", ".log")  # both keep absolute kernel timestamps through a kill


class RotatingBusLog(can.io.BaseRotatingLogger):
    """Every frame into ``<directory>/<prefix>-YYYYmmddTHHMMSS-NNNN<suffix>``, rotated when
    a file reaches `max_bytes` or `max_age_s`, the oldest deleted beyond `keep` files or
    `max_total_bytes`."""

    _supported_formats: ClassVar[set[str]] = set(RAW_FORMATS)

    def __init__(self, directory: str | Path, *, suffix: str = ".blf", prefix: str = "bus",
                 max_bytes: int | None = 64 * 2**20, max_age_s: float | None = 3600.0,
                 keep: int | None = None, max_total_bytes: int | None = None,
                 flush_interval_s: float = 0.1, **writer_kwargs: Any) -> None:
        if suffix not in RAW_FORMATS:
            raise ValueError(f"raw log format must be one of {', '.join(RAW_FORMATS)}, "
                             f"got {suffix!r}")
        super().__init__(**writer_kwargs)
        self.series = FileSeries(directory, prefix, suffix, keep=keep,
                                 max_total_bytes=max_total_bytes, max_bytes=max_bytes,
                                 label="raw bus log")
        self.max_bytes = max_bytes
        self.max_age_s = max_age_s
        self.flush_interval_s = flush_interval_s
        self.frames = 0
        self.path = self.series.next_path()
        self._writer: MessageWriter = self._get_new_writer(self.path)
        self._opened = time.monotonic()
        self._last_flush = self._opened
        self.series.prune(self.path)

    @property
    def writer(self) -> MessageWriter:
        return self._writer

    def on_message_received(self, msg: can.Message) -> None:
        self.frames += 1
        super().on_message_received(msg)

    def should_rollover(self, msg: can.Message) -> bool:
        if self.max_age_s is not None and time.monotonic() - self._opened >= self.max_age_s:
            return True
        if self.max_bytes is None:
            return False
        size = getattr(self._writer, "file_size", None)
        return size is not None and size() >= self.max_bytes

    def do_rollover(self) -> None:
        self._writer.stop()
        log.info("raw bus log: closed %s (%s bytes)", self.path, FileSeries.size(self.path))
        self.path = self.series.next_path()
        self._writer = self._get_new_writer(self.path)
        self._opened = time.monotonic()
        self.series.prune(self.path)

    def maybe_flush(self, now_monotonic: float) -> None:
        if now_monotonic - self._last_flush >= self.flush_interval_s:
            self.flush()

    def flush(self) -> None:
        """Everything received so far to the operating system (survives a SIGKILL)."""
        self._last_flush = time.monotonic()
        w = self._writer
        if isinstance(w, can.BLFWriter):
            if w.file.closed:
                return
            w._flush()  # the open container (private: python-can has no public flush)
            end = w.file.tell()
            if w.object_count:  # the header with start time and counts, as stop() writes it
                w.stop_timestamp = w.stop_timestamp or w.start_timestamp
                w.file.seek(0)
                w._write_header(end)
                w.file.seek(end)
        file = getattr(w, "file", None)
        if file is not None and not file.closed:
            file.flush()

    def files(self) -> list[Path]:
        return self.series.files()
