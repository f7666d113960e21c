"""Compiled loops of the columnar replay: the per-frame pipeline's sequential rules, run
over whole columns. Each mirrors a piece of `monitor.pipeline.core.MonitorPipeline` (and the
classes it calls) statement by statement; tests/test_columnar.py holds them to the same
results on every test log.

* `ticks`: where `feed_log` calls ``pipe.tick`` (every `TICK_S` of bus time).
* `admit`: `MonitorPipeline._check_counter`'s judgement of a repeated counter and
  `MonitorPipeline._on_output` up to the estimator step: no input yet, non-monotonic
  time, a gap that restarts the estimator, the sample periods k
  (`MonitorPipeline._periods`, `monitor.pipeline.periods`) and late samples.
* `classify`: per node, samples and ticks in order: `OnlineClassifier.update` and
  `mark_no_data` (eq (76) with hysteresis and dwell), `MismatchDetector.update` and
  `reset`, the reported state (`reported_state`), the model-mismatch flag's and the health
  state's changes and the due `Diagnosis` of `MonitorPipeline._report` and `tick`.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from monitor.diagnosis.classifier import reported_state
from monitor.estimation.jit import njit
from monitor.pipeline import periods
from monitor.pipeline.feed import TICK_S

__all__ = ["CLS_PARAMS", "CLS_STATE", "TICK_S", "admit", "classify", "ticks"]

F8 = NDArray[np.float64]
I8 = NDArray[np.int64]
B1 = NDArray[np.bool_]

# classify state vector (floats; NaN stands for None)
CLS_STATE = ("state", "cand", "cand_since", "away_since", "cls_last_t", "avg", "out_since",
             "in_since", "flagged", "last_publish", "last_t", "reported")
CLS_PARAMS = ("f1", "f2", "f1_up", "f1_down", "f2_up", "f2_down", "dwell", "mm_a", "mm_lo",
              "mm_hi", "mm_dwell", "p", "publish_period", "silence_timeout", "withhold")


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


_reported_state = njit(reported_state)


@njit
def _enter(s: F8, state: int) -> bool:
    s[1] = -1.0
    s[3] = math.nan
    if state == int(s[0]):
        return False
    s[0] = float(state)
    return True


@njit
def _cls_update(s: F8, prm: F8, t: float, value: float) -> None:
    """`OnlineClassifier.update` (eq (76), hysteresis, dwell) on the state vector."""
    if value != value:
        return
    if not t >= s[4]:
        return
    s[4] = t
    st = int(s[0])
    if ((st == 0 and value < prm[2]) or (st == 1 and prm[3] <= value <= prm[4])
            or (st == 2 and value > prm[5])):
        s[1] = -1.0
        s[3] = math.nan
        return
    c = 0 if value < prm[0] else (1 if value <= prm[1] else 2)
    if st == 3:
        _enter(s, c)
        return
    if s[3] != s[3]:
        s[3] = t
    if c != int(s[1]):
        s[1] = float(c)
        s[2] = t
    slack = 1e-9 + abs(t) * 1e-15
    if t - s[2] >= prm[6] - slack:
        _enter(s, c)
        return
    if t - s[3] >= prm[6] - slack:
        _enter(s, 1 if st != 1 else c)


@njit
def _mm_reset(s: F8, prm: F8) -> None:
    s[5] = prm[11]
    s[6] = math.nan
    s[7] = math.nan
    s[8] = 0.0


@njit
def _mm_update(s: F8, prm: F8, t: float, nis: float) -> int:
    """`MismatchDetector.update`: 1 when the flag rises, -1 when it falls, else 0."""
    if nis != nis:
        return 0
    s[5] += prm[7] * (nis - s[5])
    if prm[8] <= s[5] <= prm[9]:
        s[6] = math.nan
        if s[7] != s[7]:
            s[7] = t
        if s[8] != 0.0 and t - s[7] >= prm[10]:
            s[8] = 0.0
            return -1
    else:
        s[7] = math.nan
        if s[6] != s[6]:
            s[6] = t
        if s[8] == 0.0 and t - s[6] >= prm[10]:
            s[8] = 1.0
            return 1
    return 0


@njit
def _report(s: F8, prm: F8, i: int, ti: float, was: bool, fcause: int, hcause: int, due: bool,
            state_out: I8, ev: I8, prev_out: I8, cause: I8, fev: I8, flag_out: B1) -> None:
    """`MonitorPipeline._report`: the reported state after item i, the flag's change (fev:
    its cause + 1), the state's (cause; -1: "model" for an alarm the flag held until now,
    else "estimate") and the due Diagnosis."""
    prev = int(s[11])
    flagged = s[8] != 0.0
    c = int(s[0])
    w = prm[14] != 0.0
    new = _reported_state(c, prev, flagged, w)
    s[11] = float(new)
    changed = flagged != was
    fev[i] = fcause + 1 if changed else 0
    if new != prev:
        if hcause < 0:
            held = was and not flagged and _reported_state(c, prev, True, w) != c
            hcause = 1 if held else 0
        cause[i] = hcause
        changed = True
    prev_out[i] = prev
    if changed:
        ev[i] = 1
        s[9] = ti
    elif due and ti - s[9] >= prm[12]:
        ev[i] = 2
        s[9] = ti
    state_out[i] = new
    flag_out[i] = flagged


@njit
def classify(is_tick: B1, t: F8, g: F8, nis: F8, reset_before: B1, nan: B1, s: F8,
             prm: F8, state_out: I8, ev: I8, prev_out: I8, cause: I8, fev: I8, flag_out: B1,
             counts: I8) -> None:
    """One node's samples and ticks in bus order (see the module docstring).

    Per item: state_out the reported state after it, flag_out the model-mismatch flag after
    it; ev 0 nothing, 1 a change (and its Diagnosis), 2 a Diagnosis only; prev_out the state
    before it; a health transition where ev is 1 and prev_out differs from state_out, its
    cause 0 estimate, 1 model, 2 silence; fev 0 no flag change, else the flag's cause + 1
    (0 nis, 1 restart, 2 silence). counts += [nodes/model_mismatch, nodes/silent].
    """
    for i in range(t.shape[0]):
        ev[i] = 0
        fev[i] = 0
        ti = t[i]
        was = s[8] != 0.0
        if is_tick[i]:
            lt = s[10]
            silent = lt != lt or ti - lt >= prm[13]
            if silent and int(s[0]) != 3:
                if ti > s[4]:
                    s[4] = ti
                _enter(s, 3)
                _mm_reset(s, prm)
                counts[1] += 1
                _report(s, prm, i, ti, was, 2, 2, False, state_out, ev, prev_out, cause, fev,
                        flag_out)
                continue
            if silent and ti - s[9] >= prm[12]:
                ev[i] = 2
                s[9] = ti
            prev_out[i] = int(s[11])
            state_out[i] = int(s[11])
            flag_out[i] = was
            continue
        s[10] = ti
        fc = 0
        if reset_before[i]:
            _mm_reset(s, prm)
            fc = 1
        if nan[i]:
            _mm_reset(s, prm)
            _report(s, prm, i, ti, was, 1, -1, False, state_out, ev, prev_out, cause, fev,
                    flag_out)
            continue
        _cls_update(s, prm, ti, g[i])
        if _mm_update(s, prm, ti, nis[i]) == 1:
            counts[0] += 1
        _report(s, prm, i, ti, was, fc, -1, True, state_out, ev, prev_out, cause, fev,
                flag_out)
