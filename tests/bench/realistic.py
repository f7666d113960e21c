"""What real rigs add to the paper's motor: `python -m tests.bench.realistic [--config k=v,...]`.

Seeded runs of the Table-1 motor at 100 Hz (the `sim_ecu` plant), the monitor's model
being the paper's own (sensor sigma 0.5 A, R = 0.25; process noise 1.44):

  (a) noise-x3: healthy, sensor noise 3x the model's (sigma 1.5 A, 9x R);
  (b) load-steps: healthy, load-torque steps 0 -> 2 -> 5 -> 1 N m (a load the model lacks);
  (c) load+loss: a constant 3 N m load, a 0.4 loss of effectiveness from t = 10 s;
  (d) friction+offset+loss: Coulomb friction 1 N m sign(omega), a +1 A offset on the current
      sensor, quantisation to 0.25 A, a 0.5 loss from t = 10 s.

Each run goes through what a node of the monitor runs: `FuzzyUKF` (default configuration,
no x0: it starts from what its first output says), the online classifier (default
thresholds, 30 ms dwell) and the model-mismatch detector (2 s window, 3 s dwell) on the
NIS. `--config bias=none` runs without the estimator's bias states (step 8 of
`monitor.estimation.fuzzy_ukf`), to compare. Per run: accuracy (share of the time the
reported state equals the true class, outside 0.3 s after each true change and the first
0.5 s), false alarms, detection delay of each onset (onset to the first alarm; '*'
missed), the share of the time the mismatch flag is up, the mean NIS and gamma^ over the
last 5 s, the structure and bias events. A table, then the figures as JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from experiments.scoring import score_run
from monitor.diagnosis import DEFAULT_THRESHOLDS, HealthState, OnlineClassifier
from monitor.diagnosis.classifier import MismatchDetector
from monitor.estimation.fuzzy_ukf import FuzzyUKF, FuzzyUKFConfig
from monitor.estimation.model import DCMotorParameters, dc_motor
from sim_ecu.plant import simulate
from sim_ecu.scenario import scenario_from_dict

Array = NDArray[np.float64]

RATE = 100.0
DWELL_S = 0.03
WINDOW_S = 0.3  # not scored after a true change
MODEL_SIGMA = 0.5  # the monitor's model: R = 0.25 A^2 (Table 1)


@dataclass
class Run:
    name: str
    duration: float
    seed: int
    sigma: float = MODEL_SIGMA  # the sensor's true noise
    faults: tuple[tuple[float, float], ...] = ()  # (start, gamma)
    load: Callable[[float, Array], float] | None = None  # N m, at (t, true state)
    offset: float = 0.0  # A, on the current sensor
    lsb: float = 0.0  # A, quantisation of the current sensor (0: none)


def _steps(levels: list[tuple[float, float]]) -> Callable[[float, Array], float]:
    """A piecewise-constant load: [(from time, N m), ...]."""
    def load(t: float, x: Array) -> float:
        v = 0.0
        for t0, lv in levels:
            if t >= t0:
                v = lv
        return v
    return load


def _coulomb(tc: float) -> Callable[[float, Array], float]:
    def load(t: float, x: Array) -> float:
        return tc * float(np.sign(x[1]))  # x[1]: speed (standard-form order current, speed)
    return load


def sensor_reading(r: Run, y: Array) -> Array:
    """What the current sensor of run `r` reads of the plant's noisy output `y`: its offset,
    then its quantisation."""
    out = y + r.offset
    return np.round(out / r.lsb) * r.lsb if r.lsb > 0.0 else out


def runs() -> list[Run]:
    return [
        Run("noise-x3", 30.0, 101, sigma=3.0 * MODEL_SIGMA),
        Run("load-steps", 32.0, 102, load=_steps([(8.0, 2.0), (16.0, 5.0), (24.0, 1.0)])),
        Run("load+loss", 25.0, 103, faults=((10.0, 0.4),), load=_steps([(0.0, 3.0)])),
        Run("friction+offset+loss", 25.0, 104, faults=((10.0, 0.5),), load=_coulomb(1.0),
            offset=1.0, lsb=0.25),
    ]


def run_one(r: Run, cfg: FuzzyUKFConfig) -> dict[str, Any]:
    T = 1.0 / RATE
    params = DCMotorParameters()
    scenario = scenario_from_dict({
        "name": r.name, "duration": r.duration,
        "fault": [{"start": s, "gamma": g} for s, g in r.faults],
        "noise": {"current_sigma": r.sigma, "process": 1.0},
        "voltage": {"steps": [[0.0, 220.0]]},
    })
    plant = dc_motor(params, q=1.44, r=r.sigma**2)
    # a load torque T_L enters the speed equation as -T_L / J
    sim = simulate(plant, scenario, T, seed=r.seed, disturbance=[0.0, -1.0 / params.J, 0.0],
                   load=r.load)
    y = sensor_reading(r, sim.y)
    model = dc_motor(params, q=1.44, r=MODEL_SIGMA**2).discretize(T)
    est = FuzzyUKF(model, cfg)
    N = len(sim.t)
    res = est.step_many(sim.u, y, np.full(N, T))
    assert res.count == N, "the estimator stopped on a NaN"
    clf = OnlineClassifier(DEFAULT_THRESHOLDS, dwell_s=DWELL_S, hysteresis=0.02)
    mis = MismatchDetector(model.p, RATE)
    rep = np.empty(N, dtype=np.int64)
    flag = np.zeros(N, dtype=bool)
    for k in range(N):
        clf.update(float(sim.t[k]), float(res.gamma[k, 0]), float(res.gamma_sd[k, 0]))
        rep[k] = int(clf.state)
        mis.update(float(sim.t[k]), float(res.nis[k]))
        flag[k] = mis.flagged
    sc = score_run(sim.t, sim.gamma[:, 0], res.gamma[:, 0], rep, DEFAULT_THRESHOLDS,
                   window=WINDOW_S)
    onsets = [m.alarm_delay for m in sc.transitions
              if m.before == HealthState.FAULT_FREE and m.after != HealthState.FAULT_FREE]
    tail = sim.t >= sim.t[-1] - 5.0
    return {
        "accuracy": sc.accuracy, "false_alarms": sc.false_alarms, "onset_delays": onsets,
        "mismatch_share": float(flag.mean()), "nis_tail": float(res.nis[tail].mean()),
        "gamma_tail": float(res.gamma[tail, 0].mean()),
        "structure_events": int(res.structure_event.sum()),
        "bias_events": est.bias_events, "bias_tail": est.out.bias.tolist(),
    }


def config_overrides(spec: str) -> FuzzyUKFConfig:
    """FuzzyUKFConfig with overrides "name=value,..." (numbers, true/false or words)."""
    cfg = FuzzyUKFConfig()
    if not spec:
        return cfg
    kw: dict[str, Any] = {}
    for item in spec.split(","):
        k, v = (part.strip() for part in item.split("="))
        if v.lower() in ("true", "false"):
            kw[k] = v.lower() == "true"
        else:
            try:
                kw[k] = float(v)
            except ValueError:
                kw[k] = v
    return dataclasses.replace(cfg, **kw)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--config", default="", help="FuzzyUKFConfig overrides, k=v,...")
    args = ap.parse_args()
    cfg = config_overrides(args.config)
    print(f"{'run':24s} {'acc %':>7s} {'FA':>3s} {'delay s':>8s} {'mismatch %':>10s} "
          f"{'NIS tail':>9s} {'gamma tail':>10s} {'events':>6s} {'bias ev':>7s}")
    out: dict[str, Any] = {}
    for r in runs():
        res = run_one(r, cfg)
        out[r.name] = res
        d = [x for x in res["onset_delays"] if x is not None]
        ds = (f"{max(d):.2f}" if d else "-") + "*" * sum(x is None for x in res["onset_delays"])
        print(f"{r.name:24s} {100 * res['accuracy']:7.2f} {res['false_alarms']:3d} {ds:>8s} "
              f"{100 * res['mismatch_share']:10.1f} {res['nis_tail']:9.2f} "
              f"{res['gamma_tail']:10.3f} {res['structure_events']:6d} "
              f"{res['bias_events']:7d}", flush=True)
    print(json.dumps({"benchmark": "realistic", "runs": out}))


if __name__ == "__main__":
    main()
