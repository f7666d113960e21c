"""Which input value goes with which output sample: the one rule of the per-frame engine
(`monitor.pipeline.core`), the columnar engine (`monitor.columnar.replay`) and `identify`.

1. The held input. For each output sample, every input of the node holds the value of its
   latest frame received before the output's frame, or in it (an ECU holds its command
   between its input frames), but for a frame received less than w periods before the
   output's, w = the rig's `[model] input_window` (0 by default: none): that one is held
   from the next output sample on, as if it had come after it, and the input holds the
   value before it. An ECU that sends its input and output frames at one instant has them
   reach the bus in either order (frames queued together go out by ID, a logger stamps
   them microseconds apart): without a window a change is paired with one sample or the
   next as the bus ordered them, which no input delay fits. `identify` sees where the
   input frames fall in the output period and, where they straddle the output frame,
   places the window's edge where no input frame comes (`input_window_of`). `HeldInputs`
   keeps a node's held values frame by frame, `held_columns` does the same for a whole
   chunk of frames at once; both read the held value at an output through `held_at`.
2. The input delay. The estimator's step for output sample k applies, over the interval
   that ends at the sample (Liu et al. 2020, (35)), the held input of output sample k - d,
   d = the rig's `[model] input_delay` (whole samples, `MAX_INPUT_DELAY` at most). d = 0:
   the output already reflects the input held at it (our own bus: the ECU sends the
   output measured at t(k) before the command it applies from t(k)). A larger d is a dead
   time, or an ECU that sends its command before the output it affects. `delayed` applies
   it; the samples are those the estimator steps, so a sample lost on the bus (the engine
   predicts through k > 1 periods) is skipped in the count, as in the estimator's own
   indexing. Before d held inputs exist -- at a node's first samples, and after an
   estimator restart for a gap (the old inputs say nothing about the new record) -- the
   step takes the first held input of the run.
3. `fit_rows`: the same rule from the side of a fitted model x(j+1) = A x(j) + B v(j),
   y(j) = C x(j). The filter's step k applies v(k-1), so v(j) is the held input of row
   j + 1 - d.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

__all__ = ["MAX_INPUT_DELAY", "HeldInputs", "delayed", "fit_rows", "held_at", "held_column",
           "held_columns", "input_delay_problem", "input_window_of", "input_window_problem",
           "no_past"]

MAX_INPUT_DELAY = 50
"""The largest input delay a rig may give (samples): a dead time longer than this is a
record the model cannot describe at this rate."""


EDGE_SHARE = 0.05
"""`input_window_of`: the input frames straddle the output frame when at least this share of
them (and two) fall in the first and in the last `EDGE` of the output period each."""
EDGE = 0.1
"""Of a period: how close to an output frame an input frame is sent "with" it."""


def input_window_problem(w: object) -> str | None:
    """What is wrong with `w` as an input window (None: nothing), the one rule of the rig
    file and of `MonitorConfig`."""
    if isinstance(w, bool) or not isinstance(w, (int, float)) or not 0.0 <= w < 1.0:
        return f"must be a share of the period from 0 to below 1, got {w!r}"
    return None


def input_window_of(t_out: Array, t_in: Array, T: float) -> float:
    """The input window (rule 1) for input frames at times `t_in` around output frames at
    `t_out` (sorted), period T: 0 unless the input frames straddle the output frames (at
    least `EDGE_SHARE` of them, and two, within `EDGE` of a period after an output frame
    and as many within `EDGE` before one); then the edge goes in the middle of the widest
    stretch of the period in which no input frame comes, so that jitter never carries a
    frame across it. Input frames in an output's own frame are the caller's to leave out."""
    k = np.searchsorted(t_out, t_in, side="right") - 1  # the output frame before each
    ok = (k >= 0) & (k + 1 < t_out.size)
    if not ok.any():
        return 0.0
    phase = (t_in[ok] - t_out[k[ok]]) / T  # since the output before, in periods
    phase = phase[(phase >= 0.0) & (phase < 1.0)]
    n = phase.size
    after = int(np.count_nonzero(phase < EDGE))
    before = int(np.count_nonzero(phase > 1.0 - EDGE))
    need = max(2.0, EDGE_SHARE * n)
    if after < need or before < need:
        return 0.0
    p = np.sort(phase)
    gaps = np.diff(np.concatenate([p, [p[0] + 1.0]]))  # circular: the last to the first
    i = int(np.argmax(gaps))
    edge = (p[i] + 0.5 * gaps[i]) % 1.0  # a phase: frames after it belong to the next output
    return float(round(1.0 - edge, 3)) if edge > 0.0 else 0.0


def input_delay_problem(d: object) -> str | None:
    """What is wrong with `d` as an input delay (None: nothing), the one rule of the rig
    file and of `MonitorConfig`."""
    if isinstance(d, bool) or not isinstance(d, int) or not 0 <= d <= MAX_INPUT_DELAY:
        return f"must be a whole number of samples from 0 to {MAX_INPUT_DELAY}, got {d!r}"
    return None


def held_at(latest: Array, seen: NDArray[np.bool_], before: Array,
            seen_before: NDArray[np.bool_], t_latest: Array, own: NDArray[np.bool_],
            t: float | Array, window: float) -> tuple[Array, NDArray[np.bool_]]:
    """Rule 1 at output frames: per input, the `latest` value unless its frame came less than
    `window` before the output's frame at `t` (a frame stamped after it, where the clock went
    back, is the latest) and is not the output's own (`own`): then the value `before` it.
    Works on one output (arrays (m,), `t` a float) or on rows ((n, m), `t` (n, 1)). Returns
    the values and whether each was seen."""
    recent = (t_latest > t - window) & (t_latest <= t) & ~own
    return np.where(recent, before, latest), np.where(recent, seen_before, seen)


class HeldInputs:
    """A node's inputs frame by frame (rule 1): per input the latest value, the time of its
    frame and the value before it, each with whether there was one."""

    __slots__ = ("before", "latest", "newest", "seen", "seen_before", "t")

    def __init__(self, m: int) -> None:
        self.latest = np.zeros(m)
        self.seen = np.zeros(m, np.bool_)
        self.before = np.zeros(m)
        self.seen_before = np.zeros(m, np.bool_)
        self.t = np.full(m, -np.inf)
        self.newest = -math.inf  # the latest frame's time, of any input

    def take(self, t: float, inputs: Iterable[tuple[int, float]]) -> None:
        """One frame's (index, value) inputs, received at `t`."""
        for i, v in inputs:
            self.before[i] = self.latest[i]
            self.seen_before[i] = self.seen[i]
            self.latest[i] = v
            self.seen[i] = True
            self.t[i] = t
        self.newest = max(self.newest, t)

    def at(self, t: float, own: Iterable[tuple[int, float]], window: float
           ) -> tuple[Array, bool]:
        """The inputs an output frame received at `t` holds (its own inputs `own`, the
        frame's (index, value) pairs, taken first), and whether every one has a value."""
        if self.newest <= t - window:  # no frame within the window: `held_at` gives latest
            return self.latest, bool(self.seen.all())
        mine = np.zeros(self.latest.shape[0], np.bool_)
        for i, _ in own:
            mine[i] = True
        values, seen = held_at(self.latest, self.seen, self.before, self.seen_before, self.t,
                               mine, t, window)
        return values, bool(seen.all())


def held_column(has: NDArray[np.bool_], values: Array, carried: float, seen: bool
                ) -> tuple[Array, NDArray[np.bool_]]:
    """`hold` over a chunk of frames for one input: at every frame the latest value (this
    frame's if it has one, else `carried` from before the chunk), and whether there is one."""
    idx = np.where(has, np.arange(len(has)), -1)
    np.maximum.accumulate(idx, out=idx)
    got = idx >= 0
    val = np.where(got, values[np.maximum(idx, 0)], carried)
    return val, got | seen


def held_columns(has: NDArray[np.bool_], values: Array, t: Array, held: HeldInputs,
                 window: float) -> tuple[Array, NDArray[np.bool_], Array]:
    """`HeldInputs.take` and `HeldInputs.at` over a chunk of a node's frames at once: `has`
    (n, m) which inputs each frame carries, `values` (n, m) their values, `t` (n,) the frames'
    times, `held` the node's held inputs before the chunk (left as after it). Returns per
    frame the inputs an output in that frame holds (`held_at`) and whether all have a
    value, and the latest values (what `HeldInputs.latest` is after each frame)."""
    n, m = has.shape
    rows = np.arange(n)
    idx = np.maximum.accumulate(np.where(has, rows[:, None], -1), axis=0)  # latest frame <= i
    got = idx >= 0
    # the frame before the latest: the latest strictly before it
    prev = np.vstack([np.full((1, m), -1, np.int64), idx[:-1]]) if n else idx
    cols = np.arange(m)[None, :]
    j = np.maximum(idx, 0)
    k = prev[j, cols]
    k_got = got & (k >= 0)
    latest = np.where(got, values[j, cols], held.latest)
    seen = got | held.seen
    t_latest = np.where(got, t[j], held.t)
    before = np.where(k_got, values[np.maximum(k, 0), cols],
                      np.where(got, held.latest, held.before))
    seen_before = k_got | np.where(got, held.seen, held.seen_before)
    at, at_seen = held_at(latest, seen, before, seen_before, t_latest, has, t[:, None], window)
    if n:
        held.latest, held.seen = latest[-1].copy(), seen[-1].copy()
        held.before, held.seen_before = before[-1].copy(), seen_before[-1].copy()
        held.t = t_latest[-1].copy()
        held.newest = max(held.newest, float(np.max(t_latest[-1])))
    return at, np.asarray(at_seen.all(axis=1), np.bool_), latest


def no_past(m: int) -> Array:
    """The carried held inputs of a node before its first sample: none."""
    return np.zeros((0, m))


def delayed(held: Array, d: int, past: Array, restart: NDArray[np.bool_] | None = None
            ) -> tuple[Array, Array]:
    """The inputs the estimator applies at a run of output samples, and what to carry on.

    held: (n, m) held inputs at the samples stepped, in order; past: the held inputs of up
    to d samples stepped before (from the previous call, `no_past` at the start); restart:
    (n,) rows where the estimator starts anew (a gap), None for none. Row i gets the held
    input of row i - d, or the first of its run where that is before the run's start. The
    second array is the new `past`: the last held inputs of the last run, d at most.
    """
    if d == 0:
        return held, past
    n = held.shape[0]
    k = past.shape[0]
    stacked = np.concatenate([past, held]) if k else held
    pos = k + np.arange(n)
    first = np.zeros(n, np.int64)
    if restart is not None and restart.any():
        first = np.maximum.accumulate(np.where(restart, pos, 0))
    applied = stacked[np.maximum(pos - d, first)]
    start = int(first[-1]) if n else 0
    # a copy: `held` may be a view of values the caller changes in place
    return applied, stacked[max(start, stacked.shape[0] - d):].copy()


def fit_rows(held: Array, y: Array, d: int) -> tuple[Array, Array, slice]:
    """The rows of a fit of x(j+1) = A x(j) + B v(j), y(j) = C x(j) that the monitor
    reproduces with input delay d: v(j) = held row j + 1 - d against output row j. The
    output rows the shift leaves without an input are dropped; the slice says which output
    rows remain."""
    N = held.shape[0]
    rows = slice(max(d - 1, 0), min(N, N - 1 + d))
    first = rows.start + 1 - d
    return held[first:first + rows.stop - rows.start], y[rows], rows
