"""Scoring a diagnosis against ground truth: the figures of the benchmarks and the demo.

* True classes come from the true gamma through the same thresholds (76) the monitor uses.
* Transition windows: samples within `window` seconds after a true class change are not
  scored for accuracy (an estimator cannot know of a change before it has seen it).
* Detection delay: from a true change to the first report that leaves the old class (the
  alarm), and to the first report equal to the new class (the classification), each
  before the next true change (else the change counts as missed).
* False alarms: reported transitions into fault or outage while the true class is
  fault-free and outside the windows, per hour of such running.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from monitor.diagnosis import HealthState, Thresholds

__all__ = ["Score", "TransitionMatch", "match_transitions", "score_run", "true_classes"]


def true_classes(gamma_true: NDArray[np.float64], th: Thresholds) -> NDArray[np.int64]:
    """Class per sample by (76), with F1 <= gamma <= F2 being a fault."""
    g = np.asarray(gamma_true, dtype=float)
    cls = np.full(g.shape, int(HealthState.FAULT), dtype=np.int64)
    cls[g < th.f1] = int(HealthState.FAULT_FREE)
    cls[g > th.f2] = int(HealthState.OUTAGE)
    return cls


@dataclass(frozen=True)
class TransitionMatch:
    """A true class change; t_detected: the report first equals the new class;
    t_alarm: the report first leaves the old class (for an onset: the alarm)."""

    t_true: float
    before: HealthState
    after: HealthState
    t_detected: float | None
    t_alarm: float | None

    @property
    def delay(self) -> float | None:
        return None if self.t_detected is None else self.t_detected - self.t_true

    @property
    def alarm_delay(self) -> float | None:
        return None if self.t_alarm is None else self.t_alarm - self.t_true


def match_transitions(
    t: NDArray[np.float64], truth: NDArray[np.int64], reported: NDArray[np.int64]
) -> list[TransitionMatch]:
    """Each true class change with the time the report first agreed with it."""
    changes = np.nonzero(np.diff(truth))[0] + 1
    out: list[TransitionMatch] = []
    for i, k in enumerate(changes):
        end = changes[i + 1] if i + 1 < len(changes) else len(t)
        hit = np.nonzero(reported[k:end] == truth[k])[0]
        left = np.nonzero(reported[k:end] != truth[k - 1])[0]
        out.append(
            TransitionMatch(
                t_true=float(t[k]),
                before=HealthState(int(truth[k - 1])),
                after=HealthState(int(truth[k])),
                t_detected=float(t[k + hit[0]]) if hit.size else None,
                t_alarm=float(t[k + left[0]]) if left.size else None,
            )
        )
    return out


@dataclass(frozen=True)
class Score:
    accuracy: float  # fraction of scored samples whose report equals the true class
    scored_seconds: float
    fault_free_seconds: float
    false_alarms: int
    gamma_rmse: float
    transitions: tuple[TransitionMatch, ...]

    @property
    def false_alarms_per_hour(self) -> float:
        return self.false_alarms / max(self.fault_free_seconds, 1e-9) * 3600.0


def score_run(
    t: NDArray[np.float64],
    gamma_true: NDArray[np.float64],
    gamma_hat: NDArray[np.float64],
    reported: NDArray[np.int64],
    th: Thresholds,
    *,
    window: float = 0.5,
    settle: float = 0.5,
) -> Score:
    """Score one run. The first `settle` seconds (filter start-up) are not scored."""
    truth = true_classes(gamma_true, th)
    scored = t >= t[0] + settle
    for k in np.nonzero(np.diff(truth))[0] + 1:
        scored &= ~((t >= t[k]) & (t < t[k] + window))
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    acc = float(np.mean(reported[scored] == truth[scored])) if scored.any() else float("nan")
    ff = scored & (truth == int(HealthState.FAULT_FREE))
    alarm_states = (int(HealthState.FAULT), int(HealthState.OUTAGE))
    rising = np.zeros(t.shape, dtype=bool)
    rising[1:] = np.isin(reported[1:], alarm_states) & ~np.isin(reported[:-1], alarm_states)
    err = (gamma_hat - gamma_true)[scored]
    return Score(
        accuracy=acc,
        scored_seconds=float(scored.sum()) * dt,
        fault_free_seconds=float(ff.sum()) * dt,
        false_alarms=int(np.sum(rising & ff)),
        gamma_rmse=float(np.sqrt(np.mean(err**2))) if err.size else float("nan"),
        transitions=tuple(match_transitions(t, truth, reported)),
    )
