"""Piecewise-constant series recorded as their runs: the rows that draw the line.

Of each batch of a series in `RUNS` (the thresholds, the rule count, the health state, the
model-mismatch flag, a simulator's true gamma) only the rows that draw the line are sent
(`run_ends`: the first and the last row of every run of equal values) and the batch's last
row, which extends the line to the end of the data -- while a run goes on, at most once a
second (`RUN_TAIL_S`; `RunThinner.held` gives the one held back, sent when a file closes,
and a row that changes the value is never held; after a SIGKILL such a line may stop up to
that much before the others, on a value that had not changed). The line through them,
stepped or straight, is the line through every sample, the latest value at any time is the
same, and the viewer draws them without its per-pixel averaging, which would slant a run's
line between two changes (`EXACT_LINE`).

Slowly varying series (the estimator's noise factors, ``<Output>/noise`` and
``process_noise``, which move over its noise window, 2 s by default) keep the first row of
every `SLOW_ROW_S` of bus time (`bin_starts`), sent at most once a second (`RUN_TAIL_S`, as
the runs' tails): ten rows a second draw them, where every sample would grow a compacted
recording by about a fifth per series, and a chunk per flush the live one by as much.
"""

from __future__ import annotations

import math
from typing import Any, Final

import numpy as np
import rerun as rr
from numpy.typing import NDArray

Array = NDArray[np.float64]

__all__ = ["EXACT_LINE", "RUNS", "RUN_TAIL_S", "SLOW_ROW_S", "RunThinner", "bin_starts",
           "run_ends"]

RUNS: Final = ("gamma/true", "gamma/F1", "gamma/F2", "rules", "health", "model_mismatch")
"""Series that are piecewise constant by nature (the truth a simulator sends, the thresholds,
the estimator's rule count, the health state and the model-mismatch flag): recorded as their
runs (`run_ends`), drawn without the viewer's zoom-dependent aggregation (`EXACT_LINE`)."""

SLOW_ROW_S: Final = 0.1
"""A slowly varying series keeps one row per this much bus time (`bin_starts`)."""

RUN_TAIL_S: Final = 1.0
"""A `RUNS` series sends a row that only continues its run at most this often."""

EXACT_LINE: Final = rr.SeriesLines.from_fields(
    aggregation_policy=rr.components.AggregationPolicy.Off)
"""The viewer averages the points that fall into one pixel (its default for a dense series,
where that keeps the line's shape). The two rows either side of a change, one sample apart,
would be averaged into one point half-way, and the line from it to the run's far end would
slant: the runs are drawn as they are, which is the line the samples draw."""


def run_ends(v: Array, previous: float = math.nan) -> NDArray[np.bool_]:
    """Which rows of `v` to keep so that the line through them, stepped or straight, is the
    line through all of them: every row but those inside a run of equal values (equal to the
    row before, ``previous`` for the first, and to the row after). The last row is kept, so
    the line reaches the end of the data; the latest value at any time is unchanged."""
    n = len(v)
    same_before = np.empty(n, dtype=np.bool_)
    same_after = np.zeros(n, dtype=np.bool_)
    if n:
        same_before[0] = v[0] == previous
        same_before[1:] = v[1:] == v[:-1]
        same_after[:-1] = same_before[1:]
    return ~(same_before & same_after)


def bin_starts(t: NDArray[np.floating[Any]], previous: float, width: float
               ) -> NDArray[np.bool_]:
    """Which rows of times `t` (ascending) open a new bin of `width` seconds of the time
    axis (bins aligned on its zero), ``previous`` the time of the row before the first
    (-inf: none, so the first row is kept): one row per bin, whatever the batches."""
    b = np.floor(np.asarray(t, dtype=np.float64) / width)
    before = np.empty_like(b)
    if len(b):
        before[0] = math.floor(previous / width) if math.isfinite(previous) else -math.inf
        before[1:] = b[:-1]
    return np.asarray(b != before)


class RunThinner:
    """The run thinning of one node's `RUNS` series, batch after batch."""

    __slots__ = ("last", "pending", "sent_t")

    def __init__(self) -> None:
        self.last: dict[str, float] = {}
        """The value of the last row of each series so far (none yet: NaN)."""
        self.pending: dict[str, tuple[float, float]] = {}
        """A series' last row (time, value), held back: it only continued its run."""
        self.sent_t: dict[str, float] = {}
        """The time of the last row sent of each series."""

    def rows(self, series: str, t: Array, v: Array) -> tuple[Array, Array] | None:
        """The rows of a batch (t, v) of `series` to send (None: none): the first and the
        last row of every run of equal values (`run_ends`), and the batch's last row. That
        last row, when it only continues a run, is held back until the next batch unless
        `RUN_TAIL_S` has passed since the series' last row was sent: small batches (0.1 s)
        then cost one row a second, not ten; the line's tail in a live view lags by up to
        that much (`held` gives it when a file closes)."""
        previous = self.last.get(series, math.nan)
        held = self.pending.pop(series, None)
        if held is not None:  # it may end its run: it goes first, to be judged with the rest
            t = np.concatenate(([held[0]], t))
            v = np.concatenate(([held[1]], v))
        keep = run_ends(v, previous)
        self.last[series] = float(v[-1])
        before = v[-2] if len(v) > 1 else previous
        kept = t[:-1][keep[:-1]]
        last_sent = kept[-1] if len(kept) else self.sent_t.get(series, -math.inf)
        if v[-1] == before and t[-1] - last_sent < RUN_TAIL_S:
            keep[-1] = False
            self.pending[series] = (float(t[-1]), float(v[-1]))
        if not keep.any():
            return None
        self.sent_t[series] = float(t[keep][-1])
        return t[keep], v[keep]

    def held(self) -> list[tuple[str, Array, Array]]:
        """The rows held back (one per series), to send so that the lines reach the end of
        the data; they count as sent."""
        rows = [(s, np.array([t]), np.array([v])) for s, (t, v) in self.pending.items()]
        for s, (t, _) in self.pending.items():
            self.sent_t[s] = t
        self.pending.clear()
        return rows

    def restart(self) -> None:
        """A new file starts its runs anew."""
        self.last.clear()
        self.sent_t.clear()
