"""Compiled loops of the columnar replay: the per-frame pipeline's sequential rules, run
over whole columns; tests/columnar/test_columnar.py holds the two engines to the same results on
every test log.

* `ticks`: where `feed_log` calls ``pipe.tick`` (every `TICK_S` of bus time).
* `alive` and `admit`: the alive-counter verdicts and the admission of output samples to
  the estimator, over columns (`monitor.pipeline.admission`, whose steps the per-frame
  pipeline calls frame by frame).
* `classify`: per node, samples and ticks in order through the diagnosis rules'
  steps (`monitor.diagnosis.rules.run`), the very steps `MonitorPipeline` calls for each
  sample and tick: eq (76) with hysteresis and dwell, the model-mismatch flag, the
  reported state, the flag's and the health state's changes and the due `Diagnosis`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from monitor.diagnosis import rules
from monitor.jit import njit
from monitor.pipeline import admission
from monitor.pipeline.feed import TICK_S

__all__ = ["TICK_S", "admit", "alive", "classify", "ticks", "warm_up"]

F8 = NDArray[np.float64]
I8 = NDArray[np.int64]
B1 = NDArray[np.bool_]

classify = rules.run
"""Per node, its samples and ticks in bus order through the diagnosis rules
(`monitor.diagnosis.rules.run`: the steps the per-frame pipeline calls one at a time)."""


# The period is an argument, not the module-level TICK_S: numba would compile that in as a
# constant, and its on-disk cache is keyed on this file alone, so a new period in
# `monitor.pipeline.feed` would leave a stale kernel behind.
@njit
def ticks(t: F8, last: F8, out_idx: I8, period: float) -> int:
    """Frames after which `feed_log` ticks: ``t - last_tick >= period`` (`TICK_S`).
    `last[0]` carries the last tick's time between chunks; returns how many indices were
    written."""
    k = 0
    lt = last[0]
    for i in range(t.shape[0]):
        if t[i] - lt >= period:
            lt = t[i]
            out_idx[k] = i
            k += 1
    last[0] = lt
    return k


alive = admission.alive_columns
admit = admission.admit_columns


def warm_up() -> None:
    """Load (or compile) `ticks` (the column forms of the admission and the diagnosis
    rules are warmed by their own modules' `warm_up`)."""
    ticks(np.zeros(1), np.full(1, -np.inf), np.zeros(1, np.int64), TICK_S)
