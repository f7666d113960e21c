"""Which frames and output samples of a node reach the estimator: the rules both engines run.

Three steps over plain values that `monitor.pipeline.core` calls per frame (`admit`
compiled, as `monitor.diagnosis.rules`' steps; the others as plain Python, cheaper than a
call into compiled code); the columnar engine applies `not_read` per route, and
`alive_columns` and `admit_columns` run the other two compiled over its columns. The loops
live here, beside the steps, because numba's on-disk cache tracks a kernel's own source
file only. `warm_up` loads the compiled forms before the first frame.

* `not_read`: a decoded frame the estimator does not read, and its counter.
* `alive_verdict`, per frame with an alive counter: the frames lost before it by its
  counter (`monitor.bus.counters.frames_lost`), or a duplicate or replay to drop
  (`DROP`). The same counter again on a frame of output samples only is not dropped here:
  it may be 16 m periods on (a held-up socket's drops, an ECU skipping samples), which
  only the time since the previous sample can tell (`wrap`, judged by `admit`).
* `admit`, per output sample: the sample's status (`ADMITTED`, `NO_INPUT` before the
  node's first input, `NON_MONOTONIC` time, `REPEATED` for a `wrap` that is a repeat), the
  sample periods k since the previous admitted sample (`monitor.pipeline.periods`), an
  estimator restart (a gap over `max_gap`, or the node's drive operational again after
  holding, `RESUME`), whether a sample without a counter was late (`time/jitter`), and
  whether the node's samples come at another rate than the nominal one (`rate_event`:
  a wrong rate in the rig or on the command line makes every step predict over the wrong
  time, and the model-mismatch flag alone would not say why).

A node's admission state is a float vector (`new_state`): its last admitted sample time
(NaN before any) and the pending resumption flag.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from monitor.bus.counters import REPEATED as COUNTER_REPEATED
from monitor.bus.counters import frames_lost
from monitor.jit import njit
from monitor.pipeline import counters as C
from monitor.pipeline.events import BusEvent
from monitor.pipeline.periods import counter_periods, wrapped

__all__ = ["ADMITTED", "DROP", "LAST", "NON_MONOTONIC", "NO_COUNTER", "NO_INPUT", "REFUSED",
           "REPEATED", "RESUME", "admit", "admit_columns", "alive_columns", "alive_verdict",
           "new_state", "not_read", "rate_event", "warm_up"]

F8 = NDArray[np.float64]
I8 = NDArray[np.int64]
B1 = NDArray[np.bool_]

NO_COUNTER = -1
"""The lost count of a frame without an alive counter (its time stamps tell k)."""
DROP = -2
"""`alive_verdict`'s lost count of a frame to drop as a duplicate or replay."""
WRAP_LOST = 15  # a repeated counter 16 m periods on: 16 m - 1 lost, 15 by the counter

ADMITTED, NO_INPUT, NON_MONOTONIC, REPEATED = 0, 1, 2, 3
REFUSED = {NO_INPUT: C.SAMPLES_NO_INPUT, NON_MONOTONIC: C.TIME_NON_MONOTONIC}
"""The counter of each status that keeps a sample from the estimator; `REPEATED` (only ever
a `wrap`) is counted where the wrap is judged, as `e2e/repeated`, with its warning."""

LAST, RESUME, DT_SUM, DT_N, OFF_RATE = range(5)
"""The admission state vector: the last admitted time, the resumption pending, the sum and
number of the current window's sample intervals, and whether the node's samples come at
another rate than the nominal one (`RATE_WINDOW`)."""

RATE_WINDOW = 100
"""Sample intervals averaged to tell a node's actual period (one second at 100 Hz)."""
RATE_TOLERANCE = 1.5
"""A node whose average period is this much longer or shorter than the nominal one comes
at another rate: the rig's rate (or --rate) is wrong, and every step predicts over the
wrong time."""


def new_state() -> NDArray[np.float64]:
    """A node's admission state before its first sample."""
    return np.array([math.nan, 0.0, 0.0, 0.0, 0.0])


def not_read(kind: str, node: int, nodes: tuple[int, ...] | None, secoc: bool) -> str | None:
    """The counter of a decoded frame the estimator does not read, None for one it reads:
    a monitor's own MonitorDiagnosis frames, SecOC sync frames (applied by the codec with a
    key), the frames of nodes not monitored (`nodes`; None: every node)."""
    if kind == "diagnosis":
        return C.IGNORED_DIAGNOSIS
    if kind == "sync":
        return C.SAMPLES_SECOC_SYNC if secoc else C.IGNORED_SECOC_SYNC
    if nodes is not None and node not in nodes:
        return C.IGNORED_NODE
    return None


def alive_verdict(lost: int, output_only: bool) -> tuple[int, bool]:
    """(lost, wrap) of a frame whose alive counter says `lost` frames were lost before it
    (`monitor.bus.counters.frames_lost`: -1 for the same counter again). A repeat on a frame
    of output samples only is `WRAP_LOST` lost with `wrap` set, for `admit` to judge by the
    time since the previous sample; any other repeat is `DROP`."""
    if lost != COUNTER_REPEATED:
        return lost, False
    if output_only:
        return WRAP_LOST, True
    return DROP, False


_wrapped = njit(wrapped)
_counter_periods = njit(counter_periods)


@njit
def _watch_rate(state: NDArray[np.float64], dt: float, rate: float) -> int:
    """One interval between consecutive samples into the rate window: +1 when a full window
    says the node's samples come at another rate than `rate` (it did not before), -1 when
    they come at it again, else 0."""
    state[DT_SUM] += dt
    state[DT_N] += 1.0
    if state[DT_N] < RATE_WINDOW:
        return 0
    ratio = state[DT_SUM] / state[DT_N] * rate
    state[DT_SUM] = 0.0
    state[DT_N] = 0.0
    off = ratio > RATE_TOLERANCE or ratio * RATE_TOLERANCE < 1.0
    was = state[OFF_RATE] != 0.0
    state[OFF_RATE] = 1.0 if off else 0.0
    return 1 if off and not was else -1 if was and not off else 0


@njit
def admit(state: NDArray[np.float64], t: float, lost: int, wrap: bool, seen: bool,
          resume: bool, rate: float, max_gap: float, silence: float,
          jitter_fraction: float) -> tuple[int, int, bool, bool, int]:
    """(status, k, restart, jitter, rate_change) of a node's output sample at time `t`.

    lost: frames lost before it by its alive counter (`NO_COUNTER`: the message has none, the
    time stamps tell k: the nearest whole number of periods, and a sample further than
    `jitter_fraction` of a period from that grid is late, `jitter`); wrap: a repeated
    counter (`alive_verdict`) that is 16 m periods on only if `periods.wrapped` says so,
    else `REPEATED`; seen: every input of the node has been received; resume: the node's
    drive became operational again before this sample (or set ``state[RESUME]``). An
    admitted sample becomes the node's last and takes the pending resumption with it.
    rate_change: +1 when the intervals between consecutive samples (no frame lost by the
    counter) say the node's samples come at another rate than `rate`, -1 when they come
    at it again (`_watch_rate`), else 0.
    """
    if resume:
        state[RESUME] = 1.0
    last = state[LAST]
    if wrap and (last != last or not _wrapped(t - last, rate, silence)):
        return REPEATED, 1, False, False, 0
    if last == last and not t - last > 0.0:  # before the inputs: a clock gone back says more
        return NON_MONOTONIC, 1, False, False, 0
    if not seen:
        return NO_INPUT, 1, False, False, 0
    restart = False
    jitter = False
    k = 1
    rate_change = 0
    if last == last:
        dt = t - last
        if dt > max_gap or state[RESUME] != 0.0:
            restart = True
        else:
            if lost <= 0:  # consecutive samples (or no counter to say otherwise)
                rate_change = _watch_rate(state, dt, rate)
            k_time = dt * rate
            if lost == NO_COUNTER:
                k = max(1, round(k_time))
                jitter = abs(k_time - k) > jitter_fraction
            else:
                k = _counter_periods(k_time, lost + 1)
    state[LAST] = t
    state[RESUME] = 0.0
    return ADMITTED, k, restart, jitter, rate_change


def rate_event(t: float, node: int, change: int, rate: float) -> tuple[str | None, BusEvent]:
    """The counter (None: none) and the event of a node's rate change (`admit`), the one
    form both engines give."""
    if change > 0:
        return C.TIME_OFF_RATE, BusEvent(
            t, f"node {node}: output samples do not come at the nominal {rate:g} Hz (the "
               f"average of {RATE_WINDOW} intervals is off by more than {RATE_TOLERANCE:g}x):"
               " check the rig's [bus] rate or --rate; every step predicts over the wrong "
               "time", "WARN")
    return None, BusEvent(t, f"node {node}: output samples come at the nominal {rate:g} Hz "
                             "again", "INFO")


_frames_lost = njit(frames_lost)
_alive_verdict = njit(alive_verdict)


@njit
def alive_columns(stream: I8, counter: I8, output_only: B1, last: I8, lost: I8,
                  wrap: B1) -> None:
    """`alive_verdict` of each frame with an alive counter, in bus order, against the
    previous counter of its stream (`last`, indexed by stream, -1 before any: carried
    between chunks)."""
    for i in range(stream.shape[0]):
        s = stream[i]
        lost[i], wrap[i] = _alive_verdict(_frames_lost(last[s], counter[i]), output_only[i])
        last[s] = counter[i]


@njit
def admit_columns(t: F8, lost: I8, wrap: B1, seen: B1, resume: B1, state: F8, rate: float,
                  max_gap: float, silence: float, jitter_fraction: float, status: I8,
                  k_out: I8, restart: B1, jitter: B1, rate_change: I8) -> None:
    """`admit` of each output sample of a node, in order; `state` is the node's admission
    state (`new_state`), carried between chunks."""
    for i in range(t.shape[0]):
        status[i], k_out[i], restart[i], jitter[i], rate_change[i] = admit(
            state, t[i], lost[i], wrap[i], seen[i], resume[i], rate, max_gap, silence,
            jitter_fraction)


def warm_up() -> None:
    """Load (or compile) what both engines call (`admit`, and its column forms the live
    daemon runs on a backlog), on a scratch state: a JIT compile on the first frame of a
    live bus would stall the daemon."""
    admit(new_state(), 0.0, NO_COUNTER, False, True, False, 100.0, 5.0, 0.5, 0.25)
    one_i, one_b, one_f = np.zeros(1, np.int64), np.zeros(1, np.bool_), np.zeros(1)
    alive_columns(one_i, one_i, one_b, np.full(1, -1, np.int64), np.zeros(1, np.int64),
                  np.zeros(1, np.bool_))
    admit_columns(one_f, np.full(1, NO_COUNTER, np.int64), one_b, np.ones(1, np.bool_), one_b,
                  new_state(), 100.0, 5.0, 0.5, 0.25, np.zeros(1, np.int64),
                  np.zeros(1, np.int64), np.zeros(1, np.bool_), np.zeros(1, np.bool_),
                  np.zeros(1, np.int64))
