"""What `identify` checks before it writes a model: each figure of the fit's report, and a
replay of the capture(s) through the monitor with the learned rig, every one a pass or a
fail with what to do.

The replay is `motor-monitor replay CAPTURE --rig LEARNED --nodes NODE`: the same engine
(`monitor.archive.engine`, the replay command's default), the same configuration built from
the same rig (`options.monitor_config`), each capture a fresh monitor. After a short start
(the estimator's first transient) a model learned from a healthy capture must keep that
capture fault-free, keep the model-mismatch flag down and give a mean NIS inside the
mismatch detector's band: otherwise the monitor would raise alarms on the very plant it
was learned from, and every later replay would too.

`replay_capture` runs the replay, `report_checks` turns the report and the replay into
`Check`s, `gating_failures` picks those that keep a model from being written.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from monitor.app import options
from monitor.archive.engine import ENGINES, MonitorSetup, ReplaySettings, RunRecorder
from monitor.diagnosis import HealthState, MismatchDetector
from monitor.identify import validate as V
from monitor.identify.excitation import RECORDING_ADVICE
from monitor.pipeline.events import Sample, SampleColumns
from monitor.rig import Rig
from monitor.sinks.base import Sink

__all__ = ["MAX_MISMATCH_SHARE", "START_SHARE", "Check", "ReplayFigures", "gating_failures",
           "replay_capture", "report_checks"]

MAX_MISMATCH_SHARE = 0.01
"""The largest share of the replayed time the model-mismatch flag may be up. A fitting
model keeps the windowed NIS inside its band but for chance excursions (the band holds
1 - 1e-3 of it), and the flag needs one to last the dwell: on a healthy capture it stays
down; 1 % leaves room for one such excursion in a few minutes, not for a model that drifts
out of the band."""

START_SHARE = 0.1
"""The start left out of the replay figures: the mismatch detector's window (its average
forgets the estimator's first transient over it), but at most this share of a capture,
so that a short capture at a fast rate keeps most of its samples."""

_MORE_DATA = "more excitation (larger, faster input steps or a PRBS), a longer capture"
_ONE_CONDITION = "record the healthy node only, at one load"


@dataclass(frozen=True)
class Check:
    """One check of a learned model: `value` against `limit` (a number, or a [low, high]
    band), `advice` what to do when it fails; a failed `gating` check keeps the model from
    being written (without --force)."""

    check: str
    passed: bool
    value: float | None
    limit: float | list[float]
    advice: str
    gating: bool

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class ReplayFigures:
    """The identified node over the replay of its capture(s), after each one's start.

    seconds: the time estimated (samples times the period); state_seconds: of it, per
    health state; mismatch_seconds: with the model-mismatch flag up; mean_nis: of the
    normalised innovation squared (NaN: none), `nis_band` the mismatch detector's band;
    first_fault / first_mismatch: where the first fault or outage, the flag's first rise,
    is ("capture.log at 12.30 s"); failures: the replay's own failure lines (nothing
    decoded, a log damaged part way)."""

    files: list[str]
    start_s: float
    samples: int
    seconds: float
    state_seconds: dict[str, float]
    mismatch_seconds: float
    mean_nis: float
    nis_band: tuple[float, float]
    first_fault: str | None = None
    first_mismatch: str | None = None
    failures: list[str] = field(default_factory=list)

    @property
    def fault_seconds(self) -> float:
        """Time reported as fault or outage."""
        return sum(self.state_seconds.get(s.label, 0.0)
                   for s in (HealthState.FAULT, HealthState.OUTAGE))

    def share(self, seconds: float) -> float:
        return seconds / self.seconds if self.seconds > 0 else math.nan

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["nis_band"] = list(self.nis_band)
        d.update(fault_seconds=self.fault_seconds, fault_share=self.share(self.fault_seconds),
                 mismatch_share=self.share(self.mismatch_seconds))
        return d


@dataclass
class _Trace(RunRecorder):
    """The replay's recorder, keeping also the state, flag and NIS of every sample of one
    node (columns from the columnar engine, rows from the per-frame one)."""

    node: int = 0
    parts: list[tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.bool_],
                      NDArray[np.float64]]] = field(default_factory=list)

    def on_sample_columns(self, node: int, cols: SampleColumns) -> None:
        super().on_sample_columns(node, cols)
        if node == self.node:  # copies: a producer may reuse its buffers
            self.parts.append((np.array(cols.t, float), np.array(cols.state, np.int64),
                               np.array(cols.model_mismatch, bool), np.array(cols.nis, float)))

    def on_sample(self, sample: Sample) -> None:
        super().on_sample(sample)
        if sample.node == self.node:
            self.parts.append((np.array([sample.t]), np.array([int(sample.state)]),
                               np.array([sample.model_mismatch]), np.array([sample.nis])))

    def columns(self) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.bool_],
                               NDArray[np.float64]]:
        if not self.parts:
            return np.zeros(0), np.zeros(0, np.int64), np.zeros(0, bool), np.zeros(0)
        t, s, m, n = (np.concatenate(c) for c in zip(*self.parts, strict=True))
        return t, s.astype(np.int64), m.astype(bool), n


def replay_capture(rig: Rig, paths: Sequence[Path], node: int,
                   span: tuple[float, float] = (-math.inf, math.inf), *,
                   engine: str = "columnar") -> ReplayFigures:
    """Node `node` over the replay of each capture at `paths` through the monitor with
    `rig` (the learned rig, as loaded from the file about to be written). Every capture is
    replayed whole, but only the samples inside `span` (the first and last timestamps of
    the stretch the model was fitted to) count: what identify left out (a gap, a
    non-finite value, what follows it) is the capture's, not the model's."""
    settings = ReplaySettings(rig=None if rig.source is None else str(rig.source),
                              nodes=(node,))
    ns = settings.namespace()
    cfg = options.monitor_config(ns, rig)
    setup = MonitorSetup(settings, rig, cfg, options.database(ns, rig))
    period = 1.0 / cfg.rate
    band = MismatchDetector(len(rig.outputs), cfg.rate, window_s=cfg.mismatch_window_s,
                            dwell_s=cfg.mismatch_dwell_s).band
    counts = np.zeros(len(HealthState), np.int64)
    flagged, nis_sum, nis_n, samples, starts = 0, 0.0, 0, 0, []
    first_fault: str | None = None
    first_mismatch: str | None = None
    failures: list[str] = []
    bad = np.array([int(HealthState.FAULT), int(HealthState.OUTAGE)])
    for path in paths:
        trace = _Trace(node=node)
        run = ENGINES[engine](path, setup, _only(trace))
        if run.failure is not None:
            failures.append(run.failure)
        t, state, mismatch, nis = trace.columns()
        if not t.size:
            continue
        t0 = float(t[0])
        first, last = max(t0, span[0]), min(float(t[-1]), span[1])
        if first > last:  # the fitted stretch lies in another capture
            continue
        start = min(cfg.mismatch_window_s, START_SHARE * (last - first))
        starts.append(start)
        keep = (t >= first + start) & (t <= last)
        t, state, mismatch, nis = t[keep], state[keep], mismatch[keep], nis[keep]
        counts += np.bincount(state, minlength=len(HealthState))[:len(HealthState)]
        flagged += int(np.count_nonzero(mismatch))
        finite = nis[np.isfinite(nis)]
        nis_sum += float(finite.sum())
        nis_n += finite.size
        samples += t.size
        hits = np.flatnonzero(np.isin(state, bad))
        if first_fault is None and hits.size:
            first_fault = f"{path.name} at {float(t[hits[0]]) - t0:.2f} s"
        up = np.flatnonzero(mismatch)
        if first_mismatch is None and up.size:
            first_mismatch = f"{path.name} at {float(t[up[0]]) - t0:.2f} s"
    return ReplayFigures(
        files=[str(p) for p in paths], start_s=max(starts, default=0.0), samples=samples,
        seconds=samples * period,
        state_seconds={s.label: int(counts[s]) * period for s in HealthState if counts[s]},
        mismatch_seconds=flagged * period, mean_nis=nis_sum / nis_n if nis_n else math.nan,
        nis_band=band, first_fault=first_fault, first_mismatch=first_mismatch,
        failures=failures)


def _only(sink: Sink) -> Callable[[], list[Sink]]:
    """An engine's `open_sinks` that gives `sink` alone."""
    return lambda: [sink]


def report_checks(report: Mapping[str, Any], replay: ReplayFigures) -> list[Check]:
    """Every check of a learned model: the report's figures, then the replay's.

    Only the replay's checks gate. They judge the model the way the monitor will use it:
    the estimator on the capture, with the diagnosis and the flag. The fit's figures judge
    a simulation and the steady-state Kalman filter's innovations, and `identify` already
    refuses the captures where they mean the model is wrong (a training fit below
    MIN_FIT, halves that disagree, a hold-out far below the training, an input that does
    not excite). What is left of them is advice: real plants rarely give white
    innovations (unmodelled fast dynamics, a coloured load, quantised sensors; a user's
    capture gave a Ljung-Box p of 3e-56 with a model that may still serve), and a model
    whose replay stays fault-free, unflagged and consistent serves the monitor whatever
    its whiteness. When the replay fails, their failures say what to change."""
    fit = report.get("fit", {})
    white = report.get("whiteness", {})
    cross = report.get("cross_correlation", {})
    drops = report.get("consistency", {}).get("halves_nrmse_drop_pct", [])
    excitation = report.get("excitation", {})
    holdout = min(fit.get("nrmse_holdout_pct") or [math.nan])
    p_floor = 1.0 - V.CONFIDENCE
    structure = _structure_advice(report)
    checks = [
        Check("holdout_fit", bool(holdout >= V.MIN_FIT), _num(holdout), V.MIN_FIT,
              f"{_MORE_DATA}; or {structure}", gating=False),
        Check("whiteness", bool(white.get("passed", False)),
              _num(min(white.get("p_value") or [math.nan])), p_floor,
              "the innovations are coloured (dynamics the model leaves out), harmless while "
              f"the replay passes; to improve, {structure}, or a lower sample rate (the "
              "output sent less often)", gating=False),
        Check("cross_correlation", bool(cross.get("passed", False)),
              _num(min(cross.get("p_value") or [math.nan])), p_floor,
              f"the innovations still follow the input: {structure}; {_MORE_DATA}",
              gating=False),
        Check("consistency", bool(max(drops or [math.nan]) <= V.CONSISTENCY_DROP),
              _num(max(drops or [math.nan])), V.CONSISTENCY_DROP, _ONE_CONDITION, gating=False),
        Check("excitation",
              bool(excitation.get("hankel_singular_ratio", math.nan) >= V.MIN_PE_RATIO),
              _num(excitation.get("hankel_singular_ratio", math.nan)), V.MIN_PE_RATIO,
              RECORDING_ADVICE, gating=False),
        *_replay_checks(replay, structure),
    ]
    # advice is for what failed: a passing check has nothing to do
    return [c if not c.passed else Check(c.check, True, c.value, c.limit, "", c.gating)
            for c in checks]


def _replay_checks(r: ReplayFigures, structure: str) -> list[Check]:
    lo, hi = r.nis_band
    nis = r.mean_nis
    if r.samples == 0:
        why = "; ".join(r.failures) or "no output sample of the node was estimated"
        health = Check("replay_fault_free", False, None, 0.0,
                       f"the replay estimated nothing ({why}): check --rig and --node",
                       gating=True)
    else:
        share = r.share(r.fault_seconds)
        health = Check("replay_fault_free", share == 0.0, _num(share), 0.0,
                       f"fault or outage from {r.first_fault}: the model misses the input's "
                       f"effect: {structure}; {_MORE_DATA}; {_ONE_CONDITION}",
                       gating=True)
    if lo <= nis <= hi:
        # consistent on average but not throughout: the innovations grow and shrink
        flag_advice = (f"flag up from {r.first_mismatch} on while the mean NIS fits: the "
                       f"noise or the plant changes within the capture; {_ONE_CONDITION}")
    else:
        flag_advice = f"flag up from {r.first_mismatch} on: see replay_mean_nis"
    if nis < lo:
        nis_advice = ("the learned noise is larger than the capture's, so the flag would miss "
                      f"a drifting plant: a longer capture; {_ONE_CONDITION}")
    else:
        nis_advice = (f"the model explains the capture worse than its noise says: {structure}; "
                      f"{_MORE_DATA}")
    mismatch = r.share(r.mismatch_seconds) if r.samples else math.nan
    return [
        health,
        Check("replay_model_mismatch", bool(mismatch <= MAX_MISMATCH_SHARE), _num(mismatch),
              MAX_MISMATCH_SHARE, flag_advice, gating=True),
        Check("replay_mean_nis", bool(lo <= nis <= hi), _num(nis), [lo, hi], nis_advice,
              gating=True),
    ]


def _structure_advice(report: Mapping[str, Any]) -> str:
    """What to change in the model's structure: another order, an input delay."""
    order = report.get("order")
    if report.get("kind") == "state_space" and isinstance(order, int):
        text = " or ".join(f"--order {n}" for n in (order + 1, order - 1) if n >= 1)
    else:
        text = "--model state_space --order 2 to 4"
    return f"try {text}, or an input delay ([model] input_delay, whole samples)"


def _num(v: float) -> float | None:
    """A figure for JSON: None where it is not a number."""
    return float(v) if math.isfinite(v) else None


def gating_failures(checks: Sequence[Check]) -> list[Check]:
    """The failed checks that keep a model from being written."""
    return [c for c in checks if c.gating and not c.passed]
