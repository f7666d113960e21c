"""Compacting finished ``.rrd`` files with Rerun's own optimiser, in place and atomically.

A recording written live is made of small chunks: the sink hands its column buffers to
Rerun every ``flush_interval_s``, and each hand-over is one chunk per entity, each with its
own Arrow schema, row ids and footer-manifest entry. ``rerun rrd optimize`` merges the chunks
of each entity into large ones (the same rows, the same recording and blueprint), which
takes several times less space. `compact_rrd` runs it on a closed file:

1. ``rerun rrd optimize FILE -o .FILE.compacting.rrd --max-rows R --max-size S``, the CLI
   that ships with rerun-sdk, in its own process at a lower CPU priority, with a time limit.
   (SDK 0.41 can do the same in this process, ``RrdReader(FILE).stream().collect(optimize=
   ...).write_rrd(...)``, but one store at a time -- the blueprint would need a pass of its
   own -- and holding the whole file in the daemon's memory);
2. ``rerun rrd verify`` on the result;
3. fsync, then ``os.replace`` over the original (readers see the old or the new file, never
   a part of one), but only if the original is still the file that was compacted (retention
   may have deleted it meanwhile).

Any failure (no CLI, an error, the time limit, a result that does not verify, a full disk) is
logged, the temporary file removed, and the original left as it was. A process killed while
compacting leaves the original intact and a hidden ``.<name>.compacting.rrd`` beside it,
which `sweep` removes.

`Compactor` does this on a background thread, one file at a time, so that the daemon's loop
never waits for it: `RotatingRerunSink` hands it every file it closes.

Cost (``python -m tests.bench.recording_size``, one 100 Hz node, an hour in one file, on a
2-core machine): 347 MB flushed every 0.1 s become 45 MB, 88 MB flushed every 2 s 45 MB
too, in 27 s and 2.4 s on an idle machine (ten times that beside other work); the
optimiser's peak resident memory was 0.69-0.78 GB.
"""

from __future__ import annotations

import contextlib
import logging
import os
import subprocess
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Final

__all__ = [
    "COMPACT_MAX_BYTES",
    "COMPACT_MAX_ROWS",
    "CompactionError",
    "Compactor",
    "CompactorStats",
    "compact_rrd",
    "rerun_cli",
    "sweep",
]

_log = logging.getLogger(__name__)

COMPACT_MAX_ROWS: Final = 65_536
"""Rows of a compacted chunk at most (``--max-rows``; Rerun's "object-store" profile)."""

COMPACT_MAX_BYTES: Final = 2 * 2**20
"""Bytes of a compacted chunk at most (``--max-size``; the same profile): ~58,000 rows of a
scalar series, ten minutes of a 100 Hz one; a chunk's own cost (~1 kB) is then nothing."""

DEFAULT_TIMEOUT_S: Final = 600.0

_TMP_SUFFIX: Final = ".compacting.rrd"
_NICE: Final = 10


class CompactionError(RuntimeError):
    """Why a file was not compacted (the original is untouched)."""


def rerun_cli() -> Path | None:
    """The ``rerun`` executable of the installed rerun-sdk: the binary inside the ``rerun_cli``
    package (no Python wrapper process in between), else the ``rerun`` script next to
    ``sys.executable``, else None."""
    with contextlib.suppress(ImportError):
        import rerun_cli

        if rerun_cli.__file__ is not None:
            binary = Path(rerun_cli.__file__).with_name("rerun")
            if os.access(binary, os.X_OK):
                return binary
    script = Path(sys.executable).with_name("rerun")
    return script if os.access(script, os.X_OK) else None


def _temp_path(path: Path) -> Path:
    return path.with_name(f".{path.name}{_TMP_SUFFIX}")


def sweep(directory: str | Path) -> int:
    """Remove the temporary files of compactions a killed process left in `directory`;
    return how many."""
    n = 0
    with contextlib.suppress(OSError):
        for entry in os.scandir(directory):
            if entry.name.startswith(".") and entry.name.endswith(_TMP_SUFFIX):
                with contextlib.suppress(OSError):
                    os.unlink(entry.path)
                    n += 1
                    _log.info("rerun compaction: removed the leftover %s", entry.path)
    return n


def _run(cmd: list[str], timeout_s: float, what: str,
         cancel: threading.Event | None = None) -> None:
    env = dict(os.environ, RUST_LOG="warn", RAYON_NUM_THREADS="1", TOKIO_WORKER_THREADS="1")
    try:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE, env=env)
    except OSError as exc:
        raise CompactionError(f"cannot run {cmd[0]}: {exc}") from None
    # Below the daemon's priority; a sandbox without the @resources system calls says EPERM.
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, proc.pid, _NICE)
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            _, err = proc.communicate(timeout=0.2)
            break
        except subprocess.TimeoutExpired:
            cancelled = cancel is not None and cancel.is_set()
            if cancelled or time.monotonic() >= deadline:
                proc.kill()
                proc.communicate()
                raise CompactionError("cancelled" if cancelled else
                                      f"{what} took longer than {timeout_s:.0f} s") from None
    if proc.returncode != 0:
        lines = [ln for ln in err.decode(errors="replace").splitlines() if ln.strip()]
        raise CompactionError(f"{what} failed (exit status {proc.returncode}): "
                              f"{lines[-1] if lines else 'no message'}")


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def compact_rrd(path: str | Path, *, exe: str | Path | None = None,
                max_rows: int = COMPACT_MAX_ROWS, max_bytes: int = COMPACT_MAX_BYTES,
                timeout_s: float = DEFAULT_TIMEOUT_S,
                cancel: threading.Event | None = None) -> int:
    """Compact the finished ``.rrd`` file `path` in place (see the module docstring); return
    the bytes it saved. Raises `CompactionError` (the original untouched) on any failure.

    `timeout_s` bounds the whole (optimise and verify); setting `cancel` stops it early.
    `exe` is the ``rerun`` CLI (default `rerun_cli`).
    """
    p = Path(path)
    cli = Path(exe) if exe is not None else rerun_cli()
    if cli is None:
        raise CompactionError("no rerun CLI found (rerun-sdk's rerun_cli)")
    try:
        before = os.stat(p)
    except OSError as exc:
        raise CompactionError(f"cannot read {p}: {exc}") from None
    tmp = _temp_path(p)
    deadline = time.monotonic() + timeout_s
    try:
        _run([str(cli), "rrd", "optimize", str(p), "-o", str(tmp), "--max-rows", str(max_rows),
              "--max-size", f"{max_bytes}B"], timeout_s, "rerun rrd optimize", cancel)
        _run([str(cli), "rrd", "verify", str(tmp)], deadline - time.monotonic(),
             "rerun rrd verify of the result", cancel)
        try:
            _fsync(tmp)
            after = os.stat(p)
        except OSError as exc:
            raise CompactionError(str(exc)) from None
        if (after.st_ino, after.st_size, after.st_mtime_ns) != (
                before.st_ino, before.st_size, before.st_mtime_ns):
            raise CompactionError("the file changed while it was compacted")
        size = os.stat(tmp).st_size
        try:
            os.replace(tmp, p)
        except OSError as exc:
            raise CompactionError(f"cannot replace the file: {exc}") from None
    finally:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
    with contextlib.suppress(OSError):  # make the rename durable (best effort)
        _fsync(p.parent)
    return before.st_size - size


@dataclass
class CompactorStats:
    """What a `Compactor` did."""

    compacted: int = 0
    failed: int = 0
    abandoned: int = 0
    saved_bytes: int = 0


class Compactor:
    """Compacts files with `compact_rrd` on one background thread, in the order submitted.

    `submit` never blocks. `close` waits up to a time limit for what is queued (a daemon that
    stops compacts its last file too); what is left then is abandoned: the running
    compaction's process is stopped (its original kept) and the rest stay as written. A
    failure is logged as a warning and the file kept uncompacted.
    """

    def __init__(self, *, exe: str | Path | None = None, max_rows: int = COMPACT_MAX_ROWS,
                 max_bytes: int = COMPACT_MAX_BYTES,
                 timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        self.exe = exe
        self.max_rows = max_rows
        self.max_bytes = max_bytes
        self.timeout_s = timeout_s
        self.stats = CompactorStats()
        self._todo: deque[Path] = deque()
        self._busy = False
        self._closing = threading.Event()
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None

    def submit(self, path: str | Path) -> None:
        """Queue `path` (a finished file) for compaction."""
        with self._cond:
            if self._closing.is_set():
                return
            self._todo.append(Path(path))
            if self._thread is None:
                self._thread = threading.Thread(target=self._work, name="rrd-compactor",
                                                daemon=True)
                self._thread.start()
            self._cond.notify_all()

    def pending(self) -> int:
        """Files queued or being compacted."""
        with self._cond:
            return len(self._todo) + self._busy

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait until everything queued is done; False if `timeout_s` passed first."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._todo and not self._busy, timeout_s)

    def close(self, timeout_s: float = 20.0) -> None:
        """Finish what is queued within `timeout_s`, then stop. Idempotent."""
        done = self.wait(timeout_s)
        with self._cond:
            if not done and not self._closing.is_set():
                _log.warning("rerun compaction: stopping with %d file(s) not compacted (kept "
                             "as written)", len(self._todo) + self._busy)
            self._closing.set()  # stops a running compaction; the rest is skipped
            self.stats.abandoned += len(self._todo)
            self._todo.clear()
            self._cond.notify_all()
            thread = self._thread
        if thread is not None:
            thread.join(timeout=10.0)

    def _work(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: bool(self._todo) or self._closing.is_set())
                if not self._todo:
                    return
                path = self._todo.popleft()
                self._busy = True
            try:
                self._one(path)
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    def _one(self, path: Path) -> None:
        if not path.exists():  # deleted by retention before its turn
            _log.debug("rerun compaction: %s is gone", path)
            return
        started = time.monotonic()
        try:
            saved = compact_rrd(path, exe=self.exe, max_rows=self.max_rows,
                                max_bytes=self.max_bytes, timeout_s=self.timeout_s,
                                cancel=self._closing)
        except CompactionError as exc:
            if self._closing.is_set():
                self.stats.abandoned += 1
                return
            if not path.exists():  # retention deleted it meanwhile: nothing was lost
                _log.debug("rerun compaction: %s was deleted meanwhile", path)
                return
            self.stats.failed += 1
            _log.warning("rerun compaction of %s: %s; the file is kept as written", path, exc)
            return
        self.stats.compacted += 1
        self.stats.saved_bytes += saved
        _log.info("rerun compaction: %s %d bytes smaller in %.1f s", path, saved,
                  time.monotonic() - started)
