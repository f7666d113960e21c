"""The diagnosis rules of one node, compiled: a step per output sample and per tick over a
named state vector, the one implementation both engines run.

The per-frame pipeline (`monitor.pipeline.core.MonitorPipeline`) calls `on_sample` for each
estimated sample and `on_tick` for each node at each tick; the columnar replay calls `run`,
the same two steps in a loop over a node's samples and ticks of a chunk
(`monitor.columnar.kernels.classify`). `OnlineClassifier` and `MismatchDetector`
(`monitor.diagnosis.classifier`) are views that call `cls_update`, `cls_no_data`,
`mm_update` and `mm_reset` on a vector of their own.

The rules (Liu, Bao, Xue, Du, Int. J. Fuzzy Syst. 22(1), 2020):

* `cls_update`: eq (76) (`region`: value < F1 fault-free, F1 <= value <= F2 fault,
  value > F2 outage) with hysteresis and a dwell in sample time (see `OnlineClassifier`);
  `cls_no_data` forces NO_DATA (a silent node).
* `mm_update`, `mm_reset`: the model-mismatch flag (the windowed NIS outside its
  chi-square band for a dwell, see `MismatchDetector`).
* `reported_state`: the state a node reports beside the flag (withheld alarms).
* `report`: after a step, what changed -- the flag, the reported state and its cause --
  and whether a `Diagnosis` is due (on a change, or every publication period).

State and parameters are float64 vectors, laid out as `STATE` and `PARAMS` name them
(`new_state`, `params`); NaN stands for "none" in a time field. What a step reports goes
to a small int64 vector laid out as `OUT` (`new_out`). Plain ints and floats throughout,
so numba compiles every function here and a step costs one call from Python; with the JIT
off (`monitor.jit`) the same functions run as plain Python (on lists when called one step at
a time, `step_vectors`). The loop `run` is in this module with the steps because numba's
on-disk cache tracks a kernel's own source file only: a loop elsewhere would keep a cached
copy of steps edited here. `warm_up` loads the steps before the first sample (the daemon,
the install's cache warm-up).
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.special import gammaincinv

from monitor.diagnosis.thresholds import DiagnosisError, DiagnosisSpec, Thresholds
from monitor.jit import JIT_DISABLED, njit

__all__ = ["FLAG_CAUSES", "HEALTH_CAUSES", "NIS_BAND_FLOOR", "NO_DATA", "OUT", "PARAMS", "STATE",
           "FloatVector", "IntVector", "chi2_quantile", "cls_no_data", "cls_update", "mm_reset",
           "mm_update", "new_out", "new_state", "on_sample", "on_tick", "params", "region",
           "report", "reported_state", "run", "step_vectors", "warm_up"]

F8 = NDArray[np.float64]
I8 = NDArray[np.int64]
B1 = NDArray[np.bool_]


class FloatVector(Protocol):
    """A state or parameter vector a step reads and writes: a float64 array, or (the JIT
    off) a list of floats (`step_vectors`)."""

    def __getitem__(self, i: int, /) -> float: ...

    def __setitem__(self, i: int, v: float, /) -> None: ...


class IntVector(Protocol):
    """The vector a step reports into (`OUT`): an int64 array, or a list of ints."""

    def __getitem__(self, i: int, /) -> int: ...

    def __setitem__(self, i: int, v: int, /) -> None: ...


NO_DATA = 3  # `HealthState.NO_DATA`

STATE = ("state", "cand", "cand_since", "away_since", "cls_last_t", "since", "onset",
         "n_nan", "n_time", "avg", "out_since", "in_since", "flagged", "last_publish",
         "last_t", "reported")
"""The state vector: the classifier's state (eq (76), debounced), its candidate (-1: none)
and when it appeared, since when the value is outside the state's region, its last sample
time, when its state was adopted and the onset that supported it, its ignored NaN values
and timestamps; the mismatch detector's average NIS, since when it is outside and inside
its band, the flag (0 or 1); when the last `Diagnosis` was due, the last sample's time
(silence), the reported state."""
(ST, CAND, CAND_SINCE, AWAY_SINCE, CLS_LAST_T, SINCE, ONSET, N_NAN, N_TIME, AVG, OUT_SINCE,
 IN_SINCE, FLAGGED, LAST_PUBLISH, LAST_T, REPORTED) = range(len(STATE))

PARAMS = ("f1", "f2", "f1_up", "f1_down", "f2_up", "f2_down", "dwell", "mm_a", "mm_lo",
          "mm_hi", "mm_dwell", "outputs", "publish_period", "silence_timeout", "withhold",
          "significance")
"""The parameter vector: thresholds F1, F2 and the edges of the regions widened by the
hysteresis, the classifier's dwell; the mismatch detector's averaging coefficient, band
and dwell, the number of outputs (the NIS's mean); the publication period, the silence
timeout, whether alarms are withheld while the flag is up (0 or 1); the standard
deviations of gamma^ by which an alarm's edge is raised (`cls_update`)."""
(F1, F2, F1_UP, F1_DOWN, F2_UP, F2_DOWN, DWELL, MM_A, MM_LO, MM_HI, MM_DWELL, OUTPUTS,
 PUBLISH, SILENCE, WITHHOLD, SIGNIFICANCE) = range(len(PARAMS))

OUT = ("ev", "prev", "cause", "flag", "mismatch", "silent")
"""What a step reports: ev 0 nothing, 1 a change (and its `Diagnosis`), 2 a `Diagnosis`
only; the reported state before the step; the cause of a change of the reported state
(0 estimate, 1 model: an alarm the flag held until now, 2 silence); the flag's change
(0 none, else its cause + 1: 0 nis, 1 restart, 2 silence); whether the flag rose on the
NIS (counted nodes/model_mismatch); whether the node fell silent (nodes/silent)."""
(EV, PREV, CAUSE, FLAG, MISMATCH, SILENT) = range(len(OUT))
N_OUT = len(OUT)
HEALTH_CAUSES = ("estimate", "model", "silence")
"""The cause of a change of the reported state, by its `OUT` cause code."""
FLAG_CAUSES = ("nis", "restart", "silence")
"""The cause of a change of the flag, by its `OUT` flag code - 1."""


NIS_BAND_FLOOR = (1.0 / 1.5, 1.25)
"""The mismatch band always holds [p lo, p hi] (p outputs, the NIS's mean). Its chi-square
quantiles hold for a filter whose noise model is exact, and they narrow with the sample
rate: +-23 % at 100 Hz, +-7 % at 1 kHz (alpha 1e-3, a 2 s window). A model learned from a
capture meets other noise levels at other operating points (its Q carries the fit's error at
the capture's excitation): the rig zoo's seed 5, 1 kHz, fitted at 98.6 %, ran its fresh
healthy runs at a windowed NIS of 0.78 and was flagged 92 % of the time. Above p the
innovations are larger than the filter expects, which is what a model that misses something
gives (an unmodelled load of 5 N m on the paper's motor: 1.35); below p its noise is
overstated and the fit better than it claims, so that side is given more room. An input
paired with the wrong output or a wrong rig file is off by 3 to 20 times."""


def chi2_quantile(q: float, dof: float) -> float:
    """The q-quantile of a chi-square of `dof` degrees of freedom: 2 P^-1(dof / 2, q), the
    regularised lower incomplete gamma function's inverse, which is what scipy.stats.chi2.ppf
    returns (tests hold the two to each other), from scipy.special: importing scipy.stats
    costs the daemon half a second of its start."""
    return float(2.0 * gammaincinv(0.5 * dof, q))


#: The diagnosis's defaults, declared once by `DiagnosisSpec` (a rig's ``[diagnosis]``).
DEFAULTS = DiagnosisSpec()


def params(thresholds: Thresholds, *, dwell_s: float = DEFAULTS.dwell_s,
           hysteresis: float = DEFAULTS.hysteresis, outputs: int = 1, rate: float = 100.0,
           window_s: float = DEFAULTS.mismatch_window_s,
           mismatch_dwell_s: float = DEFAULTS.mismatch_dwell_s, alpha: float = 1e-3,
           publish_period_s: float = 0.1,
           silence_timeout_s: float = DEFAULTS.silence_timeout_s,
           withhold: bool = DEFAULTS.withhold_alarms_on_mismatch,
           significance: float = DEFAULTS.significance) -> F8:
    """The parameter vector (`PARAMS`); raises `DiagnosisError` for a value out of range.

    The mismatch band is that of `MismatchDetector`: the [alpha/2, 1 - alpha/2] quantiles
    of the exponential average (coefficient a = 1 / (window_s rate)) of a chi-square NIS
    with `outputs` degrees of freedom, p / v times a chi-square with v = p (2 - a) / a,
    widened to hold [p, p] times `NIS_BAND_FLOOR`."""
    dwell_s = float(dwell_s)
    hysteresis = float(hysteresis)
    if not (math.isfinite(dwell_s) and dwell_s >= 0.0):
        raise DiagnosisError(f"dwell_s must be a finite number >= 0, got {dwell_s!r}")
    half_gap = 0.5 * (thresholds.f2 - thresholds.f1)
    if not (math.isfinite(hysteresis) and 0.0 <= hysteresis < half_gap):
        raise DiagnosisError(
            f"hysteresis must be in [0, (f2 - f1)/2 = {half_gap:g}), got {hysteresis!r}"
        )
    significance = float(significance)
    if not (math.isfinite(significance) and significance >= 0.0):
        raise DiagnosisError(f"significance must be a finite number >= 0, got {significance!r}")
    if not (window_s > 0 and mismatch_dwell_s > 0 and rate > 0 and 0 < alpha < 1):
        raise DiagnosisError("mismatch window, dwell and rate must be > 0, alpha in (0, 1)")
    a = min(1.0, 1.0 / (window_s * rate))
    dof = outputs * (2.0 - a) / a
    f1, f2 = thresholds.f1, thresholds.f2
    return np.array([f1, f2, f1 + hysteresis, f1 - hysteresis, f2 + hysteresis,
                     f2 - hysteresis, dwell_s, a,
                     min(chi2_quantile(0.5 * alpha, dof) * outputs / dof,
                         outputs * NIS_BAND_FLOOR[0]),
                     max(chi2_quantile(1.0 - 0.5 * alpha, dof) * outputs / dof,
                         outputs * NIS_BAND_FLOOR[1]),
                     float(mismatch_dwell_s), float(outputs), float(publish_period_s),
                     float(silence_timeout_s), float(bool(withhold)), significance])


def new_state(prm: F8) -> F8:
    """A node's state vector before any input: NO_DATA, no candidate, the flag down."""
    s = np.full(len(STATE), math.nan)
    s[ST] = s[REPORTED] = float(NO_DATA)
    s[CAND] = -1.0
    s[CAND_SINCE] = 0.0
    s[CLS_LAST_T] = s[LAST_PUBLISH] = -math.inf
    s[N_NAN] = s[N_TIME] = s[FLAGGED] = 0.0
    s[AVG] = prm[OUTPUTS]
    return s


def new_out() -> I8:
    """The vector a step reports into (`OUT`)."""
    return np.zeros(N_OUT, np.int64)


def step_vectors(prm: F8) -> tuple[FloatVector, FloatVector, IntVector]:
    """A new state vector, the parameters and an `OUT` vector for calling the steps one at
    a time from Python: arrays for the compiled steps; with the JIT off, lists, because
    plain Python reads a list's items as floats but makes a numpy scalar of every array
    item it reads (a step on arrays then costs about four times as much)."""
    s = new_state(prm)
    if JIT_DISABLED:
        return s.tolist(), prm.tolist(), [0] * N_OUT
    return s, prm.copy(), new_out()


def warm_up(prm: F8) -> None:
    """Load (or compile) the steps both engines call (one at a time, and `run` over the
    columns of a backlog), on scratch vectors: a JIT compile on the first sample of a live
    bus would stall the daemon for seconds."""
    s, p, out = step_vectors(prm)
    on_sample(s, p, 0.0, 0.0, 0.0, 1.0, False, False, out)
    on_sample(s, p, 0.01, math.nan, math.nan, math.nan, True, True, out)
    on_tick(s, p, 10.0, out)
    one_b, one_f = np.zeros(1, np.bool_), np.zeros(1)
    run(one_b, one_f, one_f, one_f, one_f, one_b, one_b, new_state(prm), prm.copy(),
        np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros(1, np.int64),
        np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros(1, np.bool_),
        np.zeros(2, np.int64))


def region(value: float, f1: float, f2: float) -> int:
    """Eq (76): value < F1 fault-free (0); F1 <= value <= F2 fault (1); value > F2 outage
    (2); NaN no data (3)."""
    if value < f1:
        return 0
    if value <= f2:
        return 1
    if value > f2:
        return 2
    return NO_DATA  # NaN: every comparison above was False


def reported_state(classified: int, reported: int, flagged: bool, withhold: bool) -> int:
    """The health state a node reports, from the classifier's (eq (76), debounced).

    The classifier's state, except with `withhold` (a rig's `withhold_alarms_on_mismatch`)
    while the model-mismatch flag is up: a change to fault (1) or outage (2) is held -- the
    node keeps reporting `reported`, the state it reported before -- because gamma^ is read
    through a model the innovations reject. Every other change (to fault_free, no_data) goes
    through. When the flag falls the classifier's state is reported again: an alarm still
    there is reported then. Plain ints (`HealthState` values).
    """
    if withhold and flagged and classified != reported and (classified == 1 or classified == 2):
        return reported
    return classified


_region = njit(region)
_reported_state = njit(reported_state)


@njit
def _enter(s: FloatVector, state: int, t: float, onset: float) -> bool:
    """The classifier adopts `state` at t (supported since `onset`); whether it is new."""
    s[CAND] = -1.0
    s[AWAY_SINCE] = math.nan
    if state == int(s[ST]):
        return False
    s[ST] = float(state)
    s[SINCE] = t
    s[ONSET] = onset
    return True


@njit
def cls_update(s: FloatVector, prm: FloatVector, t: float, value: float, sd: float) -> bool:
    """One sample (t, value) through the classifier, `sd` the standard deviation of value
    (NaN or 0: none known); whether its state changed.

    An alarm must be significant: fault-free is left only at value >= F1 + max(hysteresis,
    significance sd), so that where the estimate is uncertain (an input too small or an
    output too noisy to show a loss within the dwell) a noise-sized jump of it raises no
    alarm, while a loss the outputs show, which narrows sd as it moves the value, does.
    Leaving an alarm (recovery, or fault <-> outage) takes the hysteresis alone: the
    diagnosis follows the estimate once it has alarmed.

    Inside the reported state's region widened by the hysteresis nothing changes;
    outside, the (76) candidate becomes the state once it has lasted the dwell, or, when
    the value has been outside that long without one candidate lasting, the state moves a
    step towards them (to fault; from fault, to the latest candidate). From NO_DATA the
    first sample's (76) region is adopted at once. A NaN value and a timestamp that is NaN
    or goes back are ignored and counted."""
    if value != value:
        s[N_NAN] += 1.0
        return False
    if not t >= s[CLS_LAST_T]:  # also a NaN timestamp
        s[N_TIME] += 1.0
        return False
    s[CLS_LAST_T] = t
    st = int(s[ST])
    # an alarm's edge: F1 + max(hysteresis, significance sd)
    edge = prm[F1_UP]
    if sd > 0.0 and prm[F1] + prm[SIGNIFICANCE] * sd > edge:
        edge = prm[F1] + prm[SIGNIFICANCE] * sd
    if ((st == 0 and value < edge) or (st == 1 and prm[F1_DOWN] <= value <= prm[F2_UP])
            or (st == 2 and value > prm[F2_DOWN])):
        s[CAND] = -1.0
        s[AWAY_SINCE] = math.nan
        return False
    c = _region(value, prm[F1], prm[F2])
    if st == NO_DATA:
        return _enter(s, c, t, t)
    if s[AWAY_SINCE] != s[AWAY_SINCE]:
        s[AWAY_SINCE] = t
    if c != int(s[CAND]):
        s[CAND] = float(c)
        s[CAND_SINCE] = t
    slack = 1e-9 + abs(t) * 1e-15  # float round-off in timestamp differences
    if t - s[CAND_SINCE] >= prm[DWELL] - slack:
        return _enter(s, c, t, s[CAND_SINCE])
    if t - s[AWAY_SINCE] >= prm[DWELL] - slack:
        return _enter(s, 1 if st != 1 else c, t, s[AWAY_SINCE])
    return False


@njit
def cls_no_data(s: FloatVector, t: float) -> bool:
    """The classifier to NO_DATA at t (a silent node); whether that is new."""
    if t > s[CLS_LAST_T]:
        s[CLS_LAST_T] = t
    return _enter(s, NO_DATA, t, t)


@njit
def mm_reset(s: FloatVector, prm: FloatVector) -> None:
    """The mismatch detector forgets its history (a restarted estimator): the flag down."""
    s[AVG] = prm[OUTPUTS]
    s[OUT_SINCE] = math.nan
    s[IN_SINCE] = math.nan
    s[FLAGGED] = 0.0


@njit
def mm_update(s: FloatVector, prm: FloatVector, t: float, nis: float) -> int:
    """One NIS at sample time t through the mismatch detector: 1 when the flag rises, -1
    when it falls, else 0. The flag rises when the average has been outside the band for
    the dwell and falls when it has been back inside as long; a NaN NIS is ignored."""
    if nis != nis:
        return 0
    s[AVG] += prm[MM_A] * (nis - s[AVG])
    if prm[MM_LO] <= s[AVG] <= prm[MM_HI]:
        s[OUT_SINCE] = math.nan
        if s[IN_SINCE] != s[IN_SINCE]:
            s[IN_SINCE] = t
        if s[FLAGGED] != 0.0 and t - s[IN_SINCE] >= prm[MM_DWELL]:
            s[FLAGGED] = 0.0
            return -1
    else:
        s[IN_SINCE] = math.nan
        if s[OUT_SINCE] != s[OUT_SINCE]:
            s[OUT_SINCE] = t
        if s[FLAGGED] == 0.0 and t - s[OUT_SINCE] >= prm[MM_DWELL]:
            s[FLAGGED] = 1.0
            return 1
    return 0


@njit
def report(s: FloatVector, prm: FloatVector, t: float, was: bool, flag_cause: int,
           health_cause: int, due: bool, out: IntVector) -> None:
    """After a step at t of the classifier and the mismatch detector (the flag was `was`
    before it): the new reported state (`reported_state`), into `out` the flag's change
    (cause `flag_cause`), the reported state's (cause `health_cause`; -1: model for an
    alarm the flag held until now, else estimate) and whether a `Diagnosis` is due: on
    any change, or if `due` and the publication period has passed."""
    prev = int(s[REPORTED])
    flagged = s[FLAGGED] != 0.0
    c = int(s[ST])
    w = prm[WITHHOLD] != 0.0
    new = _reported_state(c, prev, flagged, w)
    s[REPORTED] = float(new)
    changed = flagged != was
    out[FLAG] = flag_cause + 1 if changed else 0
    out[PREV] = prev
    out[CAUSE] = 0
    if new != prev:
        if health_cause < 0:
            held = was and not flagged and _reported_state(c, prev, True, w) != c
            health_cause = 1 if held else 0
        out[CAUSE] = health_cause
        changed = True
    if changed:
        out[EV] = 1
        s[LAST_PUBLISH] = t
    elif due and t - s[LAST_PUBLISH] >= prm[PUBLISH]:
        out[EV] = 2
        s[LAST_PUBLISH] = t
    else:
        out[EV] = 0


@njit
def on_sample(s: FloatVector, prm: FloatVector, t: float, gamma: float, gamma_sd: float,
              nis: float, restarted: bool, failed: bool, out: IntVector) -> bool:
    """One estimated output sample at t: the largest gamma^ (its standard deviation
    `gamma_sd`) and the NIS through the classifier and the mismatch detector, then
    `report`. `restarted`: the estimator
    restarted before it (the detector forgets, the flag's cause is restart); `failed`: the
    estimate went NaN and the estimator restarts (the detector forgets, nothing is
    classified, no periodic `Diagnosis`). Returns whether `out` holds anything to do (an
    event, a due `Diagnosis`, a count)."""
    out[MISMATCH] = 0
    out[SILENT] = 0
    was = s[FLAGGED] != 0.0
    s[LAST_T] = t
    fc = 0
    if restarted:
        mm_reset(s, prm)
        fc = 1
    if failed:
        mm_reset(s, prm)
        report(s, prm, t, was, 1, -1, False, out)
        return out[EV] != 0
    cls_update(s, prm, t, gamma, gamma_sd)
    if mm_update(s, prm, t, nis) == 1:
        out[MISMATCH] = 1
    report(s, prm, t, was, fc, -1, True, out)
    return out[EV] != 0


@njit
def on_tick(s: FloatVector, prm: FloatVector, t: float, out: IntVector) -> bool:
    """A tick at bus time t: a node without a sample for the silence timeout (or never)
    turns to NO_DATA (the detector forgets; cause silence), and while it is silent a
    `Diagnosis` is due every publication period. Returns whether `out` holds anything."""
    out[MISMATCH] = 0
    out[SILENT] = 0
    out[FLAG] = 0
    out[CAUSE] = 0
    out[EV] = 0
    out[PREV] = int(s[REPORTED])
    lt = s[LAST_T]
    silent = lt != lt or t - lt >= prm[SILENCE]
    if not silent:
        return False
    if int(s[ST]) != NO_DATA:
        was = s[FLAGGED] != 0.0
        cls_no_data(s, t)
        mm_reset(s, prm)
        out[SILENT] = 1
        report(s, prm, t, was, 2, 2, False, out)
        return True
    if t - s[LAST_PUBLISH] >= prm[PUBLISH]:
        out[EV] = 2
        s[LAST_PUBLISH] = t
        return True
    return False


@njit
def run(is_tick: B1, t: F8, gamma: F8, gamma_sd: F8, nis: F8, restarted: B1, failed: B1,
        s: F8, prm: F8, state_out: I8, ev: I8, prev_out: I8, cause: I8, fev: I8,
        flag_out: B1, counts: I8) -> None:
    """One node's samples and ticks in bus order through `on_sample` and `on_tick`.

    Per item: state_out the reported state after it, flag_out the flag after it; ev,
    prev_out, cause and fev its `OUT` fields ev, prev, cause and flag. counts +=
    [nodes/model_mismatch, nodes/silent]."""
    out = np.zeros(N_OUT, np.int64)
    for i in range(t.shape[0]):
        if is_tick[i]:
            on_tick(s, prm, t[i], out)
        else:
            on_sample(s, prm, t[i], gamma[i], gamma_sd[i], nis[i], restarted[i], failed[i],
                      out)
        ev[i] = out[EV]
        prev_out[i] = out[PREV]
        cause[i] = out[CAUSE]
        fev[i] = out[FLAG]
        state_out[i] = int(s[REPORTED])
        flag_out[i] = s[FLAGGED] != 0.0
        counts[0] += out[MISMATCH]
        counts[1] += out[SILENT]
