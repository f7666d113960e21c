"""Health states and the online classifier: eq (76) with hysteresis and dwell."""

from __future__ import annotations

import math
from collections.abc import Iterable
from enum import IntEnum

from monitor.diagnosis.thresholds import DiagnosisError, Thresholds

__all__ = ["HealthState", "MismatchDetector", "OnlineClassifier", "classify", "reported_state",
           "transitions"]


class HealthState(IntEnum):
    """Diagnosed actuator health; the integer values are sent on the CAN bus.

    The regions of (76) give FAULT_FREE, FAULT and OUTAGE; NO_DATA is a silent node. Whether
    the model explains the plant is not a state but a flag beside it (`MismatchDetector`):
    a node keeps its diagnosis while the flag is up.
    """

    FAULT_FREE = 0
    FAULT = 1
    OUTAGE = 2
    NO_DATA = 3

    @property
    def label(self) -> str:
        """'fault_free', 'fault', 'outage' or 'no_data'."""
        return self.name.lower()


_STATES = (HealthState.FAULT_FREE, HealthState.FAULT, HealthState.OUTAGE, HealthState.NO_DATA)


def classify(value: float, thresholds: Thresholds) -> HealthState:
    """Eq (76): value < F1 fault-free; F1 <= value <= F2 fault; value > F2 outage.

    NaN (no estimate) gives NO_DATA.
    """
    if value < thresholds.f1:
        return HealthState.FAULT_FREE
    if value <= thresholds.f2:
        return HealthState.FAULT
    if value > thresholds.f2:
        return HealthState.OUTAGE
    return HealthState.NO_DATA  # NaN: every comparison above was False


class OnlineClassifier:
    """Debounced online version of (76) for a stream of (timestamp, value) samples.

    Hysteresis: the region of the reported state is widened by `hysteresis` on each side,
    so to leave a region the value must cross its threshold by that much (fault-free is
    left at value >= F1 + h, fault at value < F1 - h or value > F2 + h, outage at
    value <= F2 - h). With h = 0 the regions are exactly those of (76).

    Dwell: the reported state changes to a candidate only after the candidate has persisted
    for `dwell_s` seconds of *sample time* (the timestamps passed to `update`, never the
    wall clock); it is reported on the first sample at or after onset + dwell_s. If the
    value stays outside the reported region for dwell_s but alternates between the two
    other states (noise right at the far threshold), the state moves one step towards
    them (fault-free or outage -> fault; from fault, to the latest candidate), and the
    usual rule continues from there.

    NO_DATA: the classifier starts in NO_DATA, and `mark_no_data(t)` forces it (a silent
    ECU). The first valid sample after NO_DATA is classified by (76) and reported at once,
    without dwell or hysteresis: there is no previous state to debounce against.

    NaN values are ignored and counted (`n_ignored_nan`); samples whose timestamp is NaN
    or earlier than the previous sample are ignored and counted (`n_ignored_time`).
    `update` uses plain floats and ints only; it is cheap enough for thousands of calls
    per second.
    """

    __slots__ = (
        "_away_since",
        "_cand",
        "_cand_since",
        "_dwell",
        "_f1",
        "_f1_down",
        "_f1_up",
        "_f2",
        "_f2_down",
        "_f2_up",
        "_last_t",
        "_n_nan",
        "_n_time",
        "_onset",
        "_since",
        "_state",
        "thresholds",
    )

    def __init__(
        self, thresholds: Thresholds, *, dwell_s: float = 0.05, hysteresis: float = 0.02
    ) -> None:
        dwell_s = float(dwell_s)
        hysteresis = float(hysteresis)
        if not (math.isfinite(dwell_s) and dwell_s >= 0.0):
            raise DiagnosisError(f"dwell_s must be a finite number >= 0, got {dwell_s!r}")
        half_gap = 0.5 * (thresholds.f2 - thresholds.f1)
        if not (math.isfinite(hysteresis) and 0.0 <= hysteresis < half_gap):
            raise DiagnosisError(
                f"hysteresis must be in [0, (f2 - f1)/2 = {half_gap:g}), got {hysteresis!r}"
            )
        self.thresholds = thresholds
        self._f1 = thresholds.f1
        self._f2 = thresholds.f2
        self._f1_up = thresholds.f1 + hysteresis
        self._f1_down = thresholds.f1 - hysteresis
        self._f2_up = thresholds.f2 + hysteresis
        self._f2_down = thresholds.f2 - hysteresis
        self._dwell = dwell_s
        self._state = 3
        self._since: float | None = None
        self._onset: float | None = None
        self._cand = -1
        self._cand_since = 0.0
        self._away_since: float | None = None
        self._last_t = -math.inf
        self._n_nan = 0
        self._n_time = 0

    @property
    def state(self) -> HealthState:
        """The reported state."""
        return _STATES[self._state]

    @property
    def since(self) -> float | None:
        """Timestamp at which the reported state was adopted (None before any input)."""
        return self._since

    @property
    def onset(self) -> float | None:
        """Timestamp of the first sample supporting the reported state (since - dwell, about)."""
        return self._onset

    @property
    def n_ignored_nan(self) -> int:
        return self._n_nan

    @property
    def n_ignored_time(self) -> int:
        return self._n_time

    def _enter(self, state: int, t: float, onset: float) -> HealthState | None:
        self._cand = -1
        self._away_since = None
        if state == self._state:
            return None
        self._state = state
        self._since = t
        self._onset = onset
        return _STATES[state]

    def mark_no_data(self, t: float) -> HealthState | None:
        """Force NO_DATA at time t (e.g. the ECU fell silent); returns it if it is new."""
        if t > self._last_t:
            self._last_t = t
        return self._enter(3, t, t)

    def update(self, t: float, value: float) -> HealthState | None:
        """Feed one sample; return the new state on a transition, else None."""
        if value != value:  # NaN
            self._n_nan += 1
            return None
        if not t >= self._last_t:  # also catches a NaN timestamp
            self._n_time += 1
            return None
        self._last_t = t
        s = self._state
        if (
            (s == 0 and value < self._f1_up)
            or (s == 1 and self._f1_down <= value <= self._f2_up)
            or (s == 2 and value > self._f2_down)
        ):  # inside the reported state's region widened by the hysteresis
            self._cand = -1
            self._away_since = None
            return None
        # Outside the reported (widened) region, or NO_DATA: plain (76).
        c = 0 if value < self._f1 else (1 if value <= self._f2 else 2)
        if s == 3:
            return self._enter(c, t, t)
        if self._away_since is None:
            self._away_since = t
        if c != self._cand:
            self._cand = c
            self._cand_since = t
        slack = 1e-9 + abs(t) * 1e-15  # float round-off in timestamp differences
        if t - self._cand_since >= self._dwell - slack:
            return self._enter(c, t, self._cand_since)
        if t - self._away_since >= self._dwell - slack:
            return self._enter(1 if s != 1 else c, t, self._away_since)
        return None


def reported_state(classified: int, reported: int, flagged: bool, withhold: bool) -> int:
    """The health state a node reports, from the classifier's (eq (76), debounced).

    The classifier's state, except with `withhold` (a rig's `withhold_alarms_on_mismatch`)
    while the model-mismatch flag is up: a change to fault (1) or outage (2) is held -- the
    node keeps reporting `reported`, the state it reported before -- because gamma^ is read
    through a model the innovations reject. Every other change (to fault_free, no_data) goes
    through. When the flag falls the classifier's state is reported again: an alarm still
    there is reported then. Plain ints (`HealthState` values), so the columnar kernels
    compile this very function.
    """
    if withhold and flagged and classified != reported and (classified == 1 or classified == 2):
        return reported
    return classified


def transitions(
    times: Iterable[float], states: Iterable[int | HealthState]
) -> list[tuple[float, HealthState, HealthState]]:
    """State changes in a sampled state sequence: [(time, from_state, to_state), ...].

    The time is that of the first sample in the new state. `times` and `states` must have
    the same length; states are HealthState members or their integer values.
    """
    ts = [float(t) for t in times]
    try:
        ss = [HealthState(int(s)) for s in states]
    except ValueError as exc:
        raise DiagnosisError(f"invalid health state: {exc}") from None
    if len(ts) != len(ss):
        raise DiagnosisError(f"times has {len(ts)} entries but states has {len(ss)}")
    return [(ts[i], ss[i - 1], ss[i]) for i in range(1, len(ss)) if ss[i] != ss[i - 1]]



class MismatchDetector:
    """Flags a model that stops fitting: the windowed NIS outside its chi-square band for
    longer than a dwell.

    With a fitting model the normalised innovation squared (NIS, nu' S^-1 nu) of a Kalman
    filter is chi-square with p degrees of freedom, independent from sample to sample. Its
    exponential average with coefficient a (a window of `window_s`) has mean p and variance
    2 p a / (2 - a), which is that of p / v times a chi-square with v = p (2 - a) / a degrees
    of freedom; the band is its [`alpha`/2, 1 - `alpha`/2] quantiles (scipy.stats.chi2). A
    loss of effectiveness is absorbed by gamma^ within a fraction of a second; a drifted
    resistance, an unmodelled load or a wrong rig file keeps the average out of the band,
    and after `dwell_s` the node is flagged. It is cleared when the average has been back
    inside the band for `dwell_s`. Timestamps are sample time, never the wall clock.
    """

    __slots__ = ("_a", "_avg", "_hi", "_in_since", "_lo", "_out_since", "dwell_s", "flagged")

    def __init__(self, outputs: int, rate: float, *, window_s: float = 2.0,
                 dwell_s: float = 3.0, alpha: float = 1e-3) -> None:
        from scipy.stats import chi2

        if not (window_s > 0 and dwell_s > 0 and rate > 0 and 0 < alpha < 1):
            raise DiagnosisError("mismatch window, dwell and rate must be > 0, alpha in (0, 1)")
        a = min(1.0, 1.0 / (window_s * rate))
        dof = outputs * (2.0 - a) / a
        self._a = a
        self._lo = float(chi2.ppf(0.5 * alpha, dof)) * outputs / dof
        self._hi = float(chi2.ppf(1.0 - 0.5 * alpha, dof)) * outputs / dof
        self._avg = float(outputs)
        self._out_since: float | None = None
        self._in_since: float | None = None
        self.dwell_s = dwell_s
        self.flagged = False

    @property
    def band(self) -> tuple[float, float]:
        """The band of the windowed NIS for a fitting model."""
        return self._lo, self._hi

    @property
    def average(self) -> float:
        return self._avg

    def reset(self, outputs: int) -> None:
        """Forget the history (a restarted estimator)."""
        self._avg = float(outputs)
        self._out_since = self._in_since = None
        self.flagged = False

    def update(self, t: float, nis: float) -> bool | None:
        """Feed one NIS at sample time t; True or False when the flag changes, else None."""
        if nis != nis:  # NaN: nothing learnt
            return None
        self._avg += self._a * (nis - self._avg)
        inside = self._lo <= self._avg <= self._hi
        if inside:
            self._out_since = None
            if self._in_since is None:
                self._in_since = t
            if self.flagged and t - self._in_since >= self.dwell_s:
                self.flagged = False
                return False
        else:
            self._in_since = None
            if self._out_since is None:
                self._out_since = t
            if not self.flagged and t - self._out_since >= self.dwell_s:
                self.flagged = True
                return True
        return None
