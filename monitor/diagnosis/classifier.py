"""Health states, eq (76), and views of the per-node diagnosis rules (`monitor.diagnosis.rules`):
the online classifier (eq (76) with hysteresis and dwell) and the model-mismatch detector."""

from __future__ import annotations

from collections.abc import Iterable
from enum import IntEnum

from monitor.diagnosis import rules
from monitor.diagnosis.rules import reported_state
from monitor.diagnosis.thresholds import DEFAULT_THRESHOLDS, DiagnosisError, Thresholds

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

    NaN (no estimate) gives NO_DATA (`rules.region`).
    """
    return _STATES[rules.region(value, thresholds.f1, thresholds.f2)]


class OnlineClassifier:
    """Debounced online version of (76) for a stream of (timestamp, value) samples: a view
    of `rules.cls_update` and `rules.cls_no_data` on a state vector of its own (the rules
    the monitor's engines run per node).

    Hysteresis: the region of the reported state is widened by `hysteresis` on each side,
    so to leave a region the value must cross its threshold by that much (fault-free is
    left at value >= F1 + h, fault at value < F1 - h or value > F2 + h, outage at
    value <= F2 - h). With h = 0 the regions are exactly those of (76).

    Significance: an alarm's edge is raised to `significance` times the value's standard
    deviation where that exceeds h, when `update` is given one: fault-free is left at
    value >= F1 + max(h, significance sd) (`rules.cls_update`).

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
    """

    __slots__ = ("_prm", "_s", "thresholds")

    def __init__(
        self, thresholds: Thresholds, *, dwell_s: float = rules.DEFAULTS.dwell_s,
        hysteresis: float = rules.DEFAULTS.hysteresis,
        significance: float = rules.DEFAULTS.significance
    ) -> None:
        self.thresholds = thresholds
        prm = rules.params(thresholds, dwell_s=dwell_s, hysteresis=hysteresis,
                           significance=significance)
        self._s, self._prm, _ = rules.step_vectors(prm)

    @property
    def state(self) -> HealthState:
        """The reported state."""
        return _STATES[int(self._s[rules.ST])]

    @property
    def since(self) -> float | None:
        """Timestamp at which the reported state was adopted (None before any input)."""
        return _time(self._s[rules.SINCE])

    @property
    def onset(self) -> float | None:
        """Timestamp of the first sample supporting the reported state (since - dwell, about)."""
        return _time(self._s[rules.ONSET])

    @property
    def n_ignored_nan(self) -> int:
        return int(self._s[rules.N_NAN])

    @property
    def n_ignored_time(self) -> int:
        return int(self._s[rules.N_TIME])

    def mark_no_data(self, t: float) -> HealthState | None:
        """Force NO_DATA at time t (e.g. the ECU fell silent); returns it if it is new."""
        return HealthState.NO_DATA if rules.cls_no_data(self._s, float(t)) else None

    def update(self, t: float, value: float, sd: float = 0.0) -> HealthState | None:
        """Feed one sample (`sd`: the value's standard deviation, 0 when none is known);
        return the new state on a transition, else None."""
        if rules.cls_update(self._s, self._prm, float(t), float(value), float(sd)):
            return _STATES[int(self._s[rules.ST])]
        return None


def _time(v: float) -> float | None:
    """A time field of the state vector: NaN stands for None."""
    return None if v != v else float(v)


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
    longer than a dwell. A view of `rules.mm_update` and `rules.mm_reset` on a state
    vector of its own (the rules the monitor's engines run per node).

    With a fitting model the normalised innovation squared (NIS, nu' S^-1 nu) of a Kalman
    filter is chi-square with p degrees of freedom, independent from sample to sample. Its
    exponential average with coefficient a (a window of `window_s`) has mean p and variance
    2 p a / (2 - a), which is that of p / v times a chi-square with v = p (2 - a) / a degrees
    of freedom; the band is its [`alpha`/2, 1 - `alpha`/2] quantiles (`rules.chi2_quantile`),
    never narrower than p times `rules.NIS_BAND_FLOOR` (p / 1.5 to 1.25 p). A
    loss of effectiveness is absorbed by gamma^ within a fraction of a second; a drifted
    resistance, an unmodelled load or a wrong rig file keeps the average out of the band,
    and after `dwell_s` the node is flagged. It is cleared when the average has been back
    inside the band for `dwell_s`. Timestamps are sample time, never the wall clock.
    """

    __slots__ = ("_prm", "_s", "dwell_s")

    def __init__(self, outputs: int, rate: float, *,
                 window_s: float = rules.DEFAULTS.mismatch_window_s,
                 dwell_s: float = rules.DEFAULTS.mismatch_dwell_s, alpha: float = 1e-3) -> None:
        prm = rules.params(DEFAULT_THRESHOLDS, outputs=outputs, rate=rate,
                           window_s=window_s, mismatch_dwell_s=dwell_s, alpha=alpha)
        self._s, self._prm, _ = rules.step_vectors(prm)
        self.dwell_s = dwell_s

    @property
    def band(self) -> tuple[float, float]:
        """The band of the windowed NIS for a fitting model."""
        return float(self._prm[rules.MM_LO]), float(self._prm[rules.MM_HI])

    @property
    def average(self) -> float:
        return float(self._s[rules.AVG])

    @property
    def flagged(self) -> bool:
        """Whether the model-mismatch flag is up."""
        return bool(self._s[rules.FLAGGED] != 0.0)

    def reset(self, outputs: int) -> None:
        """Forget the history (a restarted estimator) of an estimator of `outputs` outputs."""
        self._prm[rules.OUTPUTS] = float(outputs)
        rules.mm_reset(self._s, self._prm)

    def update(self, t: float, nis: float) -> bool | None:
        """Feed one NIS at sample time t; True or False when the flag changes, else None."""
        change = rules.mm_update(self._s, self._prm, float(t), float(nis))
        return None if change == 0 else change > 0
