"""Accuracy benchmark: `python -m tests.bench.accuracy [--quick]`.

Seeded scenarios (abrupt partial loss, outage, incipient ramp, intermittent fault,
recovery, varying voltage command, several noise levels, 100 Hz and 1 kHz sampling, the
La = 0 motor, and a fault-free simulated hour), each run through the fuzzy UKF, the
augmented Kalman filter and filterpy's UKF on the augmented model. Every method's gamma^
goes through the same online classifier (default thresholds, 30 ms dwell). Per method:
gamma RMSE after settling (outside 0.5 s after each true transition), detection delay of
abrupt losses >= 0.3 at 100 Hz (onset to first alarm; the table shows the worst per
scenario, '*' for a missed onset), the median delay until the right class is reported,
false alarms per hour of fault-free running, classification accuracy outside 0.5 s after
each true transition. A table, then the figures as JSON on the last line.

`--methods fuzzy_ukf,fuzzy_ukf:bias=none` compares the fuzzy UKF with FuzzyUKFConfig
overrides ("name=value;..." after the colon) side by side in one run.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from experiments.scoring import score_run
from monitor.diagnosis import DEFAULT_THRESHOLDS, HealthState, OnlineClassifier
from monitor.estimation.fuzzy_ukf import FuzzyUKF, FuzzyUKFConfig
from monitor.estimation.model import DCMotorParameters, DiscreteModel, dc_motor
from sim_ecu.plant import simulate
from sim_ecu.scenario import Scenario, scenario_from_dict
from tests.bench.common import METHODS, GammaEstimator
from tests.bench.realistic import config_overrides

DWELL_S = 0.03


@dataclass
class Case:
    scenario: Scenario
    rate: float
    seed: int
    abrupt: bool = False  # counts towards the 100 Hz detection-delay target
    la: float = 2.0
    tags: list[str] = field(default_factory=list)


def _sc(name: str, duration: float, faults: list[dict[str, Any]], *, sigma: float = 0.5,
        process: float = 1.0, volts: list[list[float]] | None = None) -> Scenario:
    return scenario_from_dict({
        "name": name, "duration": duration, "fault": faults,
        "noise": {"current_sigma": sigma, "process": process},
        "voltage": {"steps": volts or [[0.0, 220.0]]},
    })


def cases(quick: bool) -> list[Case]:
    step = lambda s, g, e=None: {"start": s, "gamma": g, **({"end": e} if e else {})}  # noqa: E731
    c: list[Case] = []
    for i, g in enumerate((0.3, 0.4, 0.5, 0.7)):
        c.append(Case(_sc(f"abrupt-{g}", 10, [step(4.0, g)]), 100, 10 + i, abrupt=True))
    c.append(Case(_sc("abrupt-0.3-1kHz", 8, [step(3.0, 0.3)]), 1000, 20))
    c.append(Case(_sc("outage", 10, [step(4.0, 1.0)]), 100, 21, abrupt=True))
    c.append(Case(_sc("outage-1kHz", 8, [step(3.0, 1.0)]), 1000, 22))
    ramp = {"kind": "ramp", "start": 3.0, "end": 13.0, "gamma_from": 0.0, "gamma_to": 0.6}
    c.append(Case(_sc("incipient", 16, [ramp]), 100, 23))
    c.append(Case(_sc("incipient-1kHz", 16, [ramp]), 1000, 24))
    inter = {"kind": "intermittent", "start": 3.0, "end": 13.0, "gamma": 0.5, "period": 2.0,
             "duty": 0.5}
    c.append(Case(_sc("intermittent", 15, [inter]), 100, 25))
    c.append(Case(_sc("intermittent-1kHz", 15, [inter]), 1000, 26))
    c.append(Case(_sc("fault-recovery", 12, [step(3.0, 0.4, 7.0)]), 100, 27, abrupt=True))
    c.append(Case(_sc("outage-recovery", 12, [step(3.0, 1.0, 7.0)]), 100, 28, abrupt=True))
    c.append(Case(_sc("fault-outage-recovery", 16, [step(4.0, 0.4, 8.0), step(8.0, 1.0, 11.0)]),
                  100, 29, abrupt=True))
    volts = [[0.0, 220.0], [3.0, 150.0], [6.0, 250.0], [9.0, 120.0]]
    c.append(Case(_sc("voltage-steps-healthy", 12, [], volts=volts), 100, 30))
    c.append(Case(_sc("voltage-steps-fault", 12, [step(7.5, 0.4)], volts=volts), 100, 31,
                  abrupt=True))
    c.append(Case(_sc("low-voltage-fault", 10, [step(4.0, 0.3)], volts=[[0.0, 100.0]]), 100, 32,
                  abrupt=True))
    for j, sigma in enumerate((0.1, 1.0, 2.0)):
        c.append(Case(_sc(f"noise-{sigma}A", 10, [step(4.0, 0.4)], sigma=sigma), 100, 33 + j,
                      abrupt=True))
    c.append(Case(_sc("process-noise-x5", 10, [step(4.0, 0.4)], process=5.0), 100, 36,
                  abrupt=True))
    # a minute of it on a healthy motor: what a process noise above the model's does
    # between faults (the estimator's adaptive process noise, step 5c of its kernel)
    c.append(Case(_sc("process-noise-x5-healthy", 60, [], process=5.0), 100, 39))
    c.append(Case(_sc("La0-abrupt", 10, [step(4.0, 0.4)]), 100, 37, abrupt=True, la=0.0))
    c.append(Case(_sc("healthy-hour", 300.0 if quick else 3600.0, []), 100, 38))
    return c


class _ConfiguredFuzzyUKF:
    """The fuzzy UKF with a non-default configuration (a method "fuzzy_ukf:k=v;...")."""

    def __init__(self, model: DiscreteModel, x0: Any, cfg: FuzzyUKFConfig) -> None:
        self.est = FuzzyUKF(model, cfg, x0=x0)

    def step(self, u: Any, y: Any, dt: float) -> Any:
        return self.est.step(u, y, dt).gamma

    def spread(self) -> Any:
        return self.est.out.gamma_sd


def _estimator(method: str, model: DiscreteModel, x0: Any) -> GammaEstimator:
    base, _, spec = method.partition(":")
    if not spec:
        return METHODS[method](model, x0)
    if base != "fuzzy_ukf":
        raise SystemExit(f"--methods: overrides only for fuzzy_ukf, got {method!r}")
    return _ConfiguredFuzzyUKF(model, x0, config_overrides(spec.replace(";", ",")))


def run_case(case: Case, method: str) -> dict[str, Any]:
    T = 1.0 / case.rate
    plant_model = dc_motor(DCMotorParameters(La=case.la), q=1.44 * case.scenario.process,
                           r=case.scenario.current_sigma**2)
    run = simulate(plant_model, case.scenario, T, seed=case.seed)
    est = _estimator(method, plant_model.discretize(T), run.x[0])
    clf = OnlineClassifier(DEFAULT_THRESHOLDS, dwell_s=DWELL_S, hysteresis=0.02)
    N = len(run.t)
    g = np.empty(N)
    rep = np.empty(N, dtype=np.int64)
    failed = None
    t0 = time.perf_counter()
    for k in range(N):
        try:
            gk = float(est.step(run.u[k], run.y[k], T)[0])
        except (np.linalg.LinAlgError, ValueError) as exc:  # filterpy: non-PSD covariance
            failed = f"{type(exc).__name__} at t = {run.t[k]:.2f} s"
            g[k:] = np.nan
            rep[k:] = int(HealthState.NO_DATA)
            break
        g[k] = gk
        clf.update(float(run.t[k]), gk, float(est.spread()[0]))
        rep[k] = int(clf.state)
    elapsed = time.perf_counter() - t0
    sc = score_run(run.t, run.gamma[:, 0], g, rep, DEFAULT_THRESHOLDS)
    onsets = [
        m for m in sc.transitions
        if m.before == HealthState.FAULT_FREE and m.after != HealthState.FAULT_FREE
    ]
    delays = [m.alarm_delay for m in onsets]
    class_delays = [m.delay for m in sc.transitions]
    return {
        "rmse": sc.gamma_rmse, "accuracy": sc.accuracy, "false_alarms": sc.false_alarms,
        "fault_free_s": sc.fault_free_seconds, "scored_s": sc.scored_seconds,
        "onset_delays": delays, "class_delays": class_delays, "failed": failed,
        "steps": N, "seconds": elapsed,
        # the structure test's (20) events, where the method has one (the fuzzy UKF)
        "structure_events": getattr(getattr(est, "est", None), "structure_events", None),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="5-minute healthy run, not an hour")
    ap.add_argument("--methods", default=",".join(METHODS))
    args = ap.parse_args()
    methods = args.methods.split(",")
    cs = cases(args.quick)
    per: dict[str, dict[str, dict[str, Any]]] = {m: {} for m in methods}
    print(f"{'scenario':26s} {'Hz':>5s} " + " ".join(f"{m:>28s}" for m in methods))
    print(f"{'':26s} {'':5s} " + " ".join(f"{'rmse   acc%  delay_s  FA':>28s}" for _ in methods))
    for case in cs:
        row = f"{case.scenario.name:26s} {case.rate:5.0f} "
        for m in methods:
            r = run_case(case, m)
            per[m][case.scenario.name] = r | {"abrupt": case.abrupt, "rate": case.rate}
            d = [x for x in r["onset_delays"] if x is not None]
            miss = sum(1 for x in r["onset_delays"] if x is None)
            ds = f"{max(d):.3f}" if d else "  -  "
            ds += "*" * miss
            cell = f"{r['rmse']:.4f} {100 * r['accuracy']:6.2f} {ds:>7s} {r['false_alarms']:3d}"
            if r["failed"]:
                cell = f"FAILED {r['failed']}"[:28]
            row += f"{cell:>28s} "
        print(row, flush=True)
    summary: dict[str, Any] = {}
    for m in methods:
        rs = list(per[m].values())
        ok = [r for r in rs if not r["failed"]]
        abrupt_delays = [
            x for r in ok if r["abrupt"] and r["rate"] == 100 for x in r["onset_delays"]
        ]
        detected = [x for x in abrupt_delays if x is not None]
        ff_h = sum(r["fault_free_s"] for r in ok) / 3600.0
        scored = sum(r["scored_s"] for r in ok)
        cls = [x for r in ok for x in r["class_delays"]]
        cls_ok = [x for x in cls if x is not None]
        summary[m] = {
            "classification_delay_median_s": float(np.median(cls_ok)) if cls_ok else None,
            "transitions_never_classified": sum(1 for x in cls if x is None),
            "gamma_rmse_mean": float(np.mean([r["rmse"] for r in ok])) if ok else math.nan,
            "gamma_rmse_median": float(np.median([r["rmse"] for r in ok])) if ok else math.nan,
            "detection_delay_max_s": max(detected) if detected else None,
            "detection_delay_mean_s": float(np.mean(detected)) if detected else None,
            "abrupt_onsets": len(abrupt_delays),
            "abrupt_onsets_missed": sum(1 for x in abrupt_delays if x is None),
            "false_alarms_per_hour": sum(r["false_alarms"] for r in ok) / max(ff_h, 1e-9),
            "fault_free_hours": ff_h,
            "accuracy": sum(r["accuracy"] * r["scored_s"] for r in ok) / max(scored, 1e-9),
            "failed_scenarios": [k for k, r in per[m].items() if r["failed"]],
            "healthy_hour_false_alarms": per[m].get("healthy-hour", {}).get("false_alarms"),
            "healthy_hour_structure_events": per[m].get("healthy-hour", {}).get(
                "structure_events"),
            "us_per_step": 1e6 * sum(r["seconds"] for r in rs) / sum(r["steps"] for r in rs),
        }
    print()
    print(f"{'method':14s} {'rmse mean':>10s} {'delay max':>10s} {'missed':>7s} {'FA/h':>7s} "
          f"{'acc %':>7s}")
    for m, s in summary.items():
        dmax = s["detection_delay_max_s"]
        print(f"{m:14s} {s['gamma_rmse_mean']:10.4f} "
              f"{(f'{dmax:.3f}' if dmax is not None else '-'):>10s} "
              f"{s['abrupt_onsets_missed']:7d} {s['false_alarms_per_hour']:7.2f} "
              f"{100 * s['accuracy']:7.3f}")
    print(json.dumps({"benchmark": "accuracy", "scenarios": len(cs), "methods": summary}))


if __name__ == "__main__":
    main()
