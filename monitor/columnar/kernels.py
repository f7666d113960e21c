"""Compiled loops of the columnar replay: the per-frame pipeline's sequential rules, run
over whole columns; tests/test_columnar.py holds the two engines to the same results on
every test log.

* `ticks`: where `feed_log` calls ``pipe.tick`` (every `TICK_S` of bus time).
* `admit`: `MonitorPipeline._check_counter`'s judgement of a repeated counter and
  `MonitorPipeline._on_output` up to the estimator step, statement by statement: no input
  yet, non-monotonic time, a gap that restarts the estimator, the sample periods k
  (`MonitorPipeline._periods`, `monitor.pipeline.periods`) and late samples.
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
from monitor.pipeline import periods
from monitor.pipeline.feed import TICK_S

__all__ = ["TICK_S", "admit", "classify", "ticks"]

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


_counter_periods = njit(periods.counter_periods)
_wrapped = njit(periods.wrapped)


@njit
def admit(t: F8, lost: I8, wrap: B1, seen: B1, last: F8, rate: float, max_gap: float,
          silence: float, jitter_fraction: float, status: I8, k_out: I8, restart: B1,
          jitter: B1) -> None:
    """Per output sample: status 0 admitted, 1 no input yet, 2 time does not advance,
    3 a repeated counter (`wrap`: one that may be 16 m - 1 lost samples) that is a repeat;
    k sample periods since the previous one; restart after a gap over max_gap; jitter (late
    sample without a counter). last[0]: the node's last admitted time (NaN: none)."""
    lt = last[0]
    for i in range(t.shape[0]):
        restart[i] = False
        jitter[i] = False
        k_out[i] = 1
        if wrap[i] and (lt != lt or not _wrapped(t[i] - lt, rate, silence)):
            status[i] = 3
            continue
        if not seen[i]:
            status[i] = 1
            continue
        if lt != lt:
            k = 1
        else:
            dt = t[i] - lt
            if not dt > 0.0:
                status[i] = 2
                continue
            if dt > max_gap:
                restart[i] = True
                k = 1
            else:
                k_time = dt * rate
                if lost[i] < 0:
                    k = max(1, int(np.rint(k_time)))
                    if abs(k_time - k) > jitter_fraction:
                        jitter[i] = True
                else:
                    k = _counter_periods(k_time, lost[i] + 1)
        status[i] = 0
        k_out[i] = k
        lt = t[i]
    last[0] = lt
