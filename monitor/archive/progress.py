"""The progress bar of an archive replay, on standard error when it is a terminal (tqdm,
from the `archive` extra): logs done, frames, frames per second and the time left.

The bar advances by the logs' sizes in bytes (known before any is read), so the time left
weighs a long log more than a short one; while a log replays in this process its frames
move the bar by an estimate of their bytes, corrected when the log is done.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
from typing import Any

__all__ = ["EXTRA_HINT", "ProgressBar", "progress_bar"]

EXTRA_HINT = "pip install 'motor-monitor[archive]'"

# bytes per frame before any log is done: candump text, Vector ASCII, compressed BLF
_BYTES_PER_FRAME = {".log": 38.0, ".asc": 60.0, ".blf": 12.0}


class ProgressBar:
    """Logs and frames done; quiet (every method does nothing) when `enabled` is False."""

    def __init__(self, logs: int, total_bytes: int, *, enabled: bool | None = None) -> None:
        self.logs = logs
        self.done = 0
        self.frames = 0
        self.done_bytes = 0
        self.done_frames = 0
        self.t0 = time.perf_counter()
        self._current: tuple[int, float] | None = None  # (size, bytes per frame) in flight
        self._current_frames = 0
        self._bar: Any = None
        if enabled is None:
            enabled = sys.stderr.isatty()
        if not enabled:
            return
        try:
            from tqdm import tqdm
        except ImportError:
            print(f"motor-monitor: no progress bar without the archive extra ({EXTRA_HINT})",
                  file=sys.stderr)
            return
        self._bar = tqdm(total=max(total_bytes, 1), file=sys.stderr, unit="B", unit_scale=True,
                         dynamic_ncols=True, leave=True, desc="replay",
                         bar_format="{desc} {percentage:3.0f}%|{bar}| "
                                    "[{elapsed}<{remaining}{postfix}]")
        self._show()

    @property
    def enabled(self) -> bool:
        return self._bar is not None

    def _show(self) -> None:
        el = max(time.perf_counter() - self.t0, 1e-9)
        self._bar.set_postfix_str(f"{self.done}/{self.logs} logs, {self.frames:,} frames, "
                                  f"{self.frames / el:,.0f} frames/s", refresh=False)
        self._bar.refresh()

    def start_log(self, size: int, suffix: str) -> None:
        """A log of `size` bytes starts replaying in this process."""
        bpf = (self.done_bytes / self.done_frames if self.done_frames
               else _BYTES_PER_FRAME.get(suffix.lower(), 40.0))
        self._current = (size, bpf)
        self._current_frames = 0

    def add_frames(self, n: int) -> None:
        """`n` more frames of the log in flight (`start_log`)."""
        self.frames += n
        self._current_frames += n
        if self._bar is None or self._current is None:
            return
        size, bpf = self._current
        guess = min(self._current_frames * bpf, 0.99 * size)
        self._bar.n = self.done_bytes + int(guess)
        self._show()

    def log_done(self, size: int, frames: int, *, counted: bool = False) -> None:
        """A log of `size` bytes is done after `frames` frames (already given to
        `add_frames` if `counted`)."""
        self.done += 1
        self.done_bytes += size
        self.done_frames += frames
        if not counted:
            self.frames += frames
        self._current = None
        if self._bar is not None:
            self._bar.n = self.done_bytes
            self._show()

    def logging(self) -> AbstractContextManager[Any]:
        """A context in which log lines go above the bar instead of through it."""
        if self._bar is None:
            return nullcontext()
        from tqdm.contrib.logging import logging_redirect_tqdm

        return logging_redirect_tqdm(loggers=[logging.getLogger()])

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


@contextmanager
def progress_bar(logs: int, total_bytes: int, *, enabled: bool | None = None
                 ) -> Iterator[ProgressBar]:
    bar = ProgressBar(logs, total_bytes, enabled=enabled)
    try:
        with bar.logging():
            yield bar
    finally:
        bar.close()
