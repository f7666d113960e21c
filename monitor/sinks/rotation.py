"""A recording in several ``.rrd`` files: `RerunSink` splits a long one into parts by size
(a replay), `RotatingRerunSink` writes week-long ones into a directory of files rotated by
size and age, with retention by count and total size. Both go on into the next file with
`RecordingSink.switch_file` (`_switch`: every file complete, of the same recording)."""

from __future__ import annotations

import glob
import logging
import time
import uuid
from contextlib import suppress
from pathlib import Path
from typing import Any, Final, Unpack

import rerun as rr

from monitor.files import FileSeries
from monitor.sinks.compact import Compactor, sweep
from monitor.sinks.outlet import RecordingOutlet
from monitor.sinks.recording import RecordingOptions, RecordingSink

__all__ = ["RerunSink", "RotatingRerunSink", "recording_parts"]

_log = logging.getLogger(__name__)

_RETRY_MAX_S: Final = 60.0


def recording_parts(rrd_path: Path) -> list[Path]:
    """`rrd_path` (if it exists) and the parts beside it that a ``part_bytes`` split wrote
    (``<stem>-partNNNN.rrd``), in order."""
    pattern = f"{glob.escape(rrd_path.stem)}-part[0-9][0-9][0-9][0-9]{glob.escape(rrd_path.suffix)}"
    parts = sorted(rrd_path.parent.glob(pattern))
    return ([rrd_path] if rrd_path.exists() else []) + parts


def _switch(sink: RecordingSink, path: Path) -> Exception | None:
    """Go on recording into `path` (`RecordingSink.switch_file`); the error that kept the
    sink in its current file, if any."""
    try:
        sink.switch_file(path)
    except (RuntimeError, OSError) as exc:
        return exc
    return None


class RerunSink(RecordingSink):
    """`RecordingSink` (the keyword arguments are its own) whose file may be split into parts.

    ``part_bytes`` (a file without ``connect_url``) splits the recording into parts: once the
    current file has reached that size (checked after each full batch), `switch_file` goes on
    into ``<stem>-part0002.rrd``, ``-part0003``... beside ``rrd_path``, every part complete
    (footer, styles, blueprint) and of the same recording, so the viewer opens one part or
    all of them as one recording (`parts` lists them). Parts of an earlier recording to the
    same path are deleted at start: they would merge into this one.
    """

    def __init__(self, *, part_bytes: int | None = None, **options: Any) -> None:
        rrd_path = options.get("rrd_path")
        if part_bytes is not None and (rrd_path is None or options.get("connect_url")
                                       is not None or part_bytes < 1):
            raise ValueError("part_bytes needs rrd_path, no connect_url, and a size >= 1")
        self._part_bytes = part_bytes
        self._part_due = False
        if part_bytes is not None and rrd_path is not None:
            for stale in recording_parts(Path(rrd_path)):
                if stale != Path(rrd_path):
                    stale.unlink(missing_ok=True)
        super().__init__(**options)
        self._parts: list[Path] = [] if self.rrd_path is None else [self.rrd_path]

    @property
    def parts(self) -> tuple[Path, ...]:
        """The files recorded so far, in order (one unless ``part_bytes`` split them)."""
        return tuple(self._parts)

    def _after_full(self) -> None:
        """After a full batch: whether the current file has reached ``part_bytes``. The next
        part is opened by the next row added (`_before_rows`), so none is left empty."""
        if self._part_bytes is None or self.rrd_path is None:
            return
        with suppress(OSError):
            self._part_due = self.rrd_path.stat().st_size >= self._part_bytes

    def _before_rows(self) -> None:
        if not self._part_due:
            return
        self._part_due = False
        first = self._parts[0]
        path = first.with_name(f"{first.stem}-part{len(self._parts) + 1:04d}{first.suffix}")
        exc = _switch(self, path)
        if exc is not None:
            _log.warning("rerun: cannot start the recording's next part %s (%s); recording "
                         "goes on into %s", path, exc, self.rrd_path)
            self._part_bytes = None
            return
        self._parts.append(path)


class RotatingRerunSink(RecordingOutlet):
    """A `Sink` that records into a directory of ``.rrd`` files, rotated by size and age.

    Files are named ``<prefix>-YYYYmmddTHHMMSS-NNNN.rrd``: the UTC time the file was opened and
    a sequence number (one more than the highest in the directory at start, then +1 per file),
    so names sort chronologically. After every flush (`flush`, or `maybe_flush` once
    ``flush_interval_s`` has passed) the current file is rotated when it has reached
    ``max_bytes`` (one ``os.stat``) or is ``max_age_s`` old: `RerunSink.switch_file` flushes
    the buffers into it, the SDK writes its footer and closes it (``rerun rrd verify`` passes
    on every rotated file) and recording goes on into the next file. Every sample goes to
    exactly one file (no gap, no duplicate at a boundary). Each file is self-contained: store
    info, recording start time, blueprint (every node seen so far), static series styles, and
    the current thresholds with its first gamma batch.

    Retention, applied whenever a file is opened, counts every file of this pattern in the
    directory (earlier runs too) and never deletes the one being written: the oldest are
    deleted while there are more than ``keep`` files (the current one included), and while the
    closed ones total more than ``max_total_bytes - max_bytes`` (the room the current file may
    take), so the directory stays within ``max_total_bytes``. A file ends up larger than
    ``max_bytes`` by what was sent after the size check saw it reached (one flush, plus what the
    SDK's writer thread had not written yet) and its footer (~50-100 kB plus ~35 bytes a chunk).
    The defaults (64 MiB, 1 h, 48 files) bound the directory to ~3 GiB.

    Sizing (one 100 Hz node, ``python -m tests.bench.recording_size``): a flush every 0.1 s
    makes ~74 chunks/s, ~0.35 GB/h; every 2 s ~12 chunks/s, ~88 MB/h; a compacted file ~45 MB
    an hour. The SDK keeps ~0.3-0.45 kB of footer manifest in memory per chunk of the open
    file (measured), which without rotation would grow by ~18 GB per node and week at 0.1 s.

    Memory: one `RecordingStream` serves the whole run (the Python SDK never frees a
    `RecordingStream`'s threads, so a new one per file would leak them); only its `FileSink` is
    replaced at each rotation, and with it the footer's chunk manifest that the SDK keeps while
    a file is open. So memory is bounded by ``max_bytes``/``max_age_s`` however long the run.

    All files of a run share its recording id (``recording_id``, or a random one): opened
    together (``rerun DIR/*.rrd``) they form one continuous recording. ``connect_url`` streams
    to a viewer/gRPC proxy through a second `RerunSink` that lives for the whole run and is
    never rotated (one connection; a gRPC sink keeps no manifest), with the same recording id
    -- so do not load the files into the viewer that received the live stream: the rows would
    show twice.

    If the next file cannot be created (disk full, directory removed), the error is logged and
    recording goes on into the current file; the rotation is retried after 1 s, then with
    doubling back-off up to a minute. One sink per directory: retention deletes files that
    another writer might be using.

    Compaction (``compactor``, e.g. ``Compactor()``): every file closed by a rotation is handed
    to the `monitor.sinks.compact.Compactor`, which rewrites it with ``rerun rrd optimize`` on a
    background thread (the loop never waits; a failure is logged and the file kept as
    written; the result replaces it atomically and passes ``rerun rrd verify``); `close`
    compacts the last file too, waiting at most ``compact_wait_s`` for all of them. Leftover
    temporary files of a killed run are removed at start.

    Flush interval: ``flush_interval_s`` bounds the data a SIGKILL loses from the files (and
    how far the live stream lags); when another record carries that bound (the raw bus log,
    ``run --raw-dir``), a longer interval writes larger chunks (a few times smaller files
    before compaction).

    The recording's settings (``nodes``, ``f1``/``f2``, ``batch_size``, ``flush_interval_s``,
    ``signals``, ...) are `RecordingOptions`, passed on to every file's `RecordingSink` and to
    the live stream's, with their defaults there.
    """

    def __init__(
        self,
        directory: str | Path,
        *,
        max_bytes: int | None = 64 * 2**20,
        max_age_s: float | None = 3600.0,
        keep: int | None = 48,
        max_total_bytes: int | None = None,
        prefix: str = "monitor",
        connect_url: str | None = None,
        compactor: Compactor | None = None,
        compact_wait_s: float = 20.0,
        **recording: Unpack[RecordingOptions],
    ) -> None:
        if max_bytes is not None and max_bytes < 1:
            raise ValueError("max_bytes must be >= 1 (or None)")
        if max_age_s is not None and not max_age_s > 0:
            raise ValueError("max_age_s must be > 0 (or None)")
        self.directory = Path(directory)
        self.max_bytes = max_bytes
        self.max_age_s = None if max_age_s is None else float(max_age_s)
        self.keep = keep
        self.max_total_bytes = max_total_bytes
        self.prefix = prefix
        recording_id = recording.get("recording_id")
        self.recording_id = recording_id if recording_id is not None else uuid.uuid4().hex
        self.rotations = 0
        """Files closed by rotation so far."""
        self._closed = False
        self._last_flush = time.monotonic()
        self._retry_at = 0.0
        self._retry_s = 1.0
        self._compact_wait_s = float(compact_wait_s)
        self.compactor = compactor
        """Compacts the closed files (None: they stay as written)."""

        self._series = FileSeries(directory, prefix, ".rrd", keep=keep,
                                  max_total_bytes=max_total_bytes, max_bytes=max_bytes,
                                  label="rerun sink")
        path = self._series.next_path()
        common: RecordingOptions = {**recording, "recording_id": self.recording_id}
        self._file = RecordingSink(rrd_path=path, **common)
        self._flush_interval_s = self._file.flush_interval_s
        self._path = path
        self._opened = time.monotonic()
        # RERUN=off in the environment: no file is written, nothing to rotate
        self._enabled = rr.is_enabled(self._file.recording)
        self._live: RecordingSink | None = None
        try:
            self._series.prune(self._path)
            if self.compactor is not None:
                sweep(self.directory)
            if connect_url is not None:
                self._live = RecordingSink(connect_url=connect_url, **common)
        except BaseException:
            self.close()
            raise

    # -- the column API (`RecordingOutlet`): forwarded to the file sink and the live stream ---

    def outlets(self) -> tuple[RecordingSink, ...]:
        return self._sinks()

    def set_thresholds(self, f1: float, f2: float) -> None:
        """Change the thresholds (buffered samples keep the old ones; later files start with
        the new ones)."""
        for sink in self._sinks():
            sink.set_thresholds(f1, f2)

    def flush(self) -> None:
        """Send all buffered data, then rotate if the current file is too big or too old."""
        now = time.monotonic()
        self._last_flush = now
        if self._closed:
            return
        for sink in self._sinks():
            sink.flush()
        if now >= self._retry_at and self._due(now):
            self.rotate()

    def rotate(self) -> Path:
        """Close the current file (footer written), start the next one and apply retention;
        return the path being written (the old one if the new one could not be created)."""
        if self._closed:
            return self._path
        path = self._series.next_path()
        started = time.monotonic()
        old = self._path
        exc = _switch(self._file, path)
        if exc is not None:
            _log.error(
                "rerun sink: cannot start %s: %s; still recording to %s (retry in %.0f s)",
                path,
                exc,
                old,
                self._retry_s,
            )
            self._retry_at = started + self._retry_s
            self._retry_s = min(2.0 * self._retry_s, _RETRY_MAX_S)
            return old
        self._retry_s = 1.0
        self._path = path
        self._opened = time.monotonic()
        self.rotations += 1
        if self.compactor is not None:
            self.compactor.submit(old)
        _log.info(
            "rerun sink: closed %s (%s bytes) in %.3f s, recording to %s",
            old,
            FileSeries.size(old),
            self._opened - started,
            path,
        )
        self._series.prune(self._path)
        return path

    def close(self, timeout_s: float = 10.0) -> None:
        """Flush and close the current file (footer written) and the live stream, then wait up
        to ``compact_wait_s`` for the compaction of the closed files, the last one included.
        Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._file.close(timeout_s)
        finally:
            try:
                if self._live is not None:
                    self._live.close(timeout_s)
            finally:
                if self.compactor is not None:
                    if self._enabled:
                        self.compactor.submit(self._path)
                    self.compactor.close(self._compact_wait_s)

    # -- introspection ------------------------------------------------------------------------

    @property
    def path(self) -> Path:
        """The file being written (after `close`: the last one written)."""
        return self._path

    @property
    def nodes(self) -> tuple[int, ...]:
        return self._file.nodes

    @property
    def recording(self) -> rr.RecordingStream:
        """The `RecordingStream` of the files (one for the whole run)."""
        return self._file.recording

    def files(self) -> list[Path]:
        """The files of this pattern in the directory, oldest first (the current one last)."""
        return self._series.files()

    # -- internals --------------------------------------------------------------------------

    def _sinks(self) -> tuple[RecordingSink, ...]:
        return (self._file,) if self._live is None else (self._file, self._live)

    def _due(self, now: float) -> bool:
        if not self._enabled:
            return False
        if self.max_age_s is not None and now - self._opened >= self.max_age_s:
            return True
        if self.max_bytes is not None:
            size = FileSeries.size(self._path)
            # removed under us: start a new file rather than write into an unlinked one
            return size is None or size >= self.max_bytes
        return False
