"""Files shared by every stage that writes them: durable state files (thresholds, SecOC
freshness) and series of rotated files with retention (recordings, raw bus logs)."""

from __future__ import annotations

import contextlib
import logging
import os
import re
import tempfile
import time
from pathlib import Path

__all__ = ["FileSeries", "atomic_write_text"]

_log = logging.getLogger(__name__)


def atomic_write_text(path: str | os.PathLike[str], text: str, *, mode: int | None = None,
                      encoding: str = "utf-8") -> None:
    """Write `text` to `path` so that a reader (or a crash) sees the old or the new file,
    never half of one: a temporary file beside it, fsync, rename, fsync of the directory.

    `mode` sets the new file's permissions before any byte is written (e.g. 0o600 for
    secrets). Raises OSError; the previous file then stays intact and no temporary file
    is left behind.
    """
    p = Path(path)
    directory = p.parent if str(p.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=directory)
    try:
        with os.fdopen(fd, "w", encoding=encoding, newline="\n") as fh:
            if mode is not None:
                os.fchmod(fh.fileno(), mode)
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, p)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    with contextlib.suppress(OSError):  # make the rename durable (best effort)
        dfd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


class FileSeries:
    """A directory of rotated files ``<prefix>-YYYYmmddTHHMMSS-NNNN<suffix>`` and their
    retention, shared by the recordings and the raw bus logs.

    Names sort chronologically: the UTC time the file was opened and a sequence number one
    more than the highest in the directory at start, then +1 per file. Retention (`prune`)
    counts every file of the pattern in the directory (earlier runs too), never deletes the
    one being written, and deletes the oldest while there are more than `keep` files (the
    current one included) or the closed ones total more than ``max_total_bytes -
    max_bytes`` (the room the current file may take).
    """

    def __init__(self, directory: str | os.PathLike[str], prefix: str, suffix: str, *,
                 keep: int | None = None, max_total_bytes: int | None = None,
                 max_bytes: int | None = None, label: str = "files") -> None:
        if not re.fullmatch(r"[A-Za-z0-9_.-]+", prefix):
            raise ValueError(f"prefix must match [A-Za-z0-9_.-]+: {prefix!r}")
        if keep is not None and keep < 1:
            raise ValueError("keep must be >= 1 (or None)")
        if max_total_bytes is not None and (
            max_total_bytes < 1 or (max_bytes is not None and max_total_bytes < max_bytes)
        ):
            raise ValueError("max_total_bytes must be >= max_bytes (or None)")
        self.directory = Path(directory)
        self.prefix = prefix
        self.suffix = suffix
        self.keep = keep
        self.max_total_bytes = max_total_bytes
        self.max_bytes = max_bytes
        self.label = label
        self._pattern = re.compile(re.escape(prefix) + r"-(\d{8}T\d{6})-(\d{4,})"
                                   + re.escape(suffix))
        self.directory.mkdir(parents=True, exist_ok=True)
        self._seq = 1 + max((seq for _, seq, _ in self._scan()), default=-1)

    @staticmethod
    def size(path: Path) -> int | None:
        try:
            return os.stat(path).st_size
        except OSError:
            return None

    def _scan(self) -> list[tuple[str, int, Path]]:
        """(UTC stamp, sequence number, path) of this pattern's files, oldest first."""
        out: list[tuple[str, int, Path]] = []
        try:
            names = os.listdir(self.directory)
        except OSError:
            return out
        for name in names:
            m = self._pattern.fullmatch(name)
            if m is not None:
                out.append((m.group(1), int(m.group(2)), self.directory / name))
        out.sort()
        return out

    def files(self) -> list[Path]:
        """The files of the pattern, oldest first."""
        return [p for _, _, p in self._scan()]

    def next_path(self) -> Path:
        """A new name, after every existing one."""
        with contextlib.suppress(OSError):  # if it fails, creating the file reports it
            self.directory.mkdir(parents=True, exist_ok=True)
        stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime())
        while True:
            path = self.directory / f"{self.prefix}-{stamp}-{self._seq:04d}{self.suffix}"
            self._seq += 1
            if not path.exists():
                return path

    def prune(self, current: Path) -> None:
        """Delete the oldest closed files beyond `keep` and `max_total_bytes`."""
        if self.keep is None and self.max_total_bytes is None:
            return
        closed = [p for p in self.files() if p != current]
        sizes = [self.size(p) or 0 for p in closed]
        count = len(closed) + 1  # with the current file
        total = sum(sizes)
        room = (None if self.max_total_bytes is None
                else self.max_total_bytes - (self.max_bytes or 0))
        for p, size in zip(closed, sizes, strict=True):
            if (self.keep is None or count <= self.keep) and (room is None or total <= room):
                break
            try:
                p.unlink(missing_ok=True)
                _log.info("%s: deleted %s (%d bytes)", self.label, p, size)
            except OSError as exc:
                _log.warning("%s: cannot delete %s: %s", self.label, p, exc)
            count -= 1
            total -= size
