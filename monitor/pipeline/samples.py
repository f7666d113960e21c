"""Which input value goes with which output sample: the one rule of the per-frame engine
(`monitor.pipeline.core`), the columnar engine (`monitor.columnar.replay`) and `identify`.

1. The held input. For each output sample, every input of the node holds the value of its
   latest frame received before the output's frame, or in it (an ECU holds its command
   between its input frames). `hold` takes one frame into the held values, `held_column`
   does the same for a whole chunk of frames at once.
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

from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

__all__ = ["MAX_INPUT_DELAY", "delayed", "fit_rows", "held_column", "hold", "input_delay_problem",
           "no_past"]

MAX_INPUT_DELAY = 50
"""The largest input delay a rig may give (samples): a dead time longer than this is a
record the model cannot describe at this rate."""


def input_delay_problem(d: object) -> str | None:
    """What is wrong with `d` as an input delay (None: nothing), the one rule of the rig
    file and of `MonitorConfig`."""
    if isinstance(d, bool) or not isinstance(d, int) or not 0 <= d <= MAX_INPUT_DELAY:
        return f"must be a whole number of samples from 0 to {MAX_INPUT_DELAY}, got {d!r}"
    return None


def hold(held: Array, seen: NDArray[np.bool_], inputs: Iterable[tuple[int, float]]) -> None:
    """Take one frame's (index, value) inputs into the held values and mark them seen."""
    for i, v in inputs:
        held[i] = v
        seen[i] = True


def held_column(has: NDArray[np.bool_], values: Array, carried: float, seen: bool
                ) -> tuple[Array, NDArray[np.bool_]]:
    """`hold` over a chunk of frames for one input: at every frame the latest value (this
    frame's if it has one, else `carried` from before the chunk), and whether there is one."""
    idx = np.where(has, np.arange(len(has)), -1)
    np.maximum.accumulate(idx, out=idx)
    got = idx >= 0
    val = np.where(got, values[np.maximum(idx, 0)], carried)
    return val, got | seen


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
