"""Speed and numerical-soak benchmark: `python -m tests.bench.estimator [--soak-steps N]`.

1. Cost per step of the fuzzy UKF and the augmented KF against filterpy's
   UnscentedKalmanFilter on the same augmented DC-motor model, measured side by side in
   one run: rounds of a fixed block of samples, methods interleaved, the median per
   method; reported as ratios to filterpy (machine noise hits all alike).
2. The same fuzzy UKF code interpreted (NUMBA_DISABLE_JIT=1, in a subprocess): what the
   JIT buys; and the ahead-of-time build the hardened service runs (if built:
   `python -m monitor.estimation.kernels_aot`).
3. filterpy with the paper's alpha = 1e-4: how often it fails (non-PSD covariance).
4. A soak: random motors (also La = 0), random scenarios, rates 100 Hz - 1 kHz, missed
   samples (dt = k T) and random voltage commands; every step checks for NaN and every
   covariance for positive definiteness (a clamped Cholesky pivot counts as a failure).
Figures in a table, JSON on the last line.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from typing import Any

import numpy as np

from monitor.estimation.fuzzy_ukf import FuzzyUKF
from monitor.estimation.model import DCMotorParameters, dc_motor
from sim_ecu.plant import simulate
from sim_ecu.scenario import load_scenario, scenario_from_dict
from tests.bench.common import METHODS, FilterpyAugmentedUKF

BLOCK = 2000


def _timing(rounds: int) -> dict[str, float]:
    model = dc_motor()
    T = 0.01
    run = simulate(model, load_scenario("fault-outage-recovery"), T, seed=1)
    d = model.discretize(T)
    ests = {name: make(d, run.x[0]) for name, make in METHODS.items()}
    U = [np.ascontiguousarray(u) for u in run.u]
    Y = [np.ascontiguousarray(y) for y in run.y]
    times: dict[str, list[float]] = {name: [] for name in ests}
    pos = 0
    for _ in range(rounds):
        for name, est in ests.items():
            t0 = time.perf_counter()
            for k in range(pos, pos + BLOCK):
                j = k % len(U)
                est.step(U[j], Y[j], T)
            times[name].append((time.perf_counter() - t0) / BLOCK)
        pos += BLOCK
    return {name: statistics.median(v) for name, v in times.items()}


def _kernel_cost(kernel: str) -> float | None:
    """Per-step cost of the fuzzy UKF with another kernel (subprocess, JIT switched off):
    "python" runs the same code interpreted, "aot" the ahead-of-time build (None if absent).
    """
    code = (
        "import time, numpy as np\n"
        "from monitor.estimation.model import dc_motor\n"
        "from monitor.estimation.fuzzy_ukf import FuzzyUKF\n"
        "e = FuzzyUKF(dc_motor().discretize(0.01), x0=[67.7, 338.5, 0.0])\n"
        "u = np.array([220.0]); y = np.array([67.7])\n"
        "for _ in range(50): e.step(u, y, 0.01)\n"
        "t = time.perf_counter()\n"
        "for _ in range(1000): e.step(u, y, 0.01)\n"
        "print((time.perf_counter() - t) / 1000)\n"
    )
    env = dict(os.environ, NUMBA_DISABLE_JIT="1", MOTOR_MONITOR_KERNEL=kernel)
    try:
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                             text=True, timeout=300, check=True)
        return float(out.stdout.strip().splitlines()[-1])
    except (subprocess.SubprocessError, ValueError):
        return None


def _filterpy_paper_alpha(steps: int) -> dict[str, Any]:
    model = dc_motor()
    run = simulate(model, load_scenario("fault-outage-recovery"), 0.01, seed=2)
    d = model.discretize(0.01)
    failures = 0
    first: str | None = None
    done = 0
    est = FilterpyAugmentedUKF(d, run.x[0], alpha=1e-4)
    for k in range(steps):
        j = k % len(run.t)
        try:
            est.step(run.u[j], run.y[j], 0.01)
            P = est.ukf.P
            if not np.all(np.isfinite(P)) or np.min(np.linalg.eigvalsh(P)) <= 0:
                raise np.linalg.LinAlgError("covariance not positive definite")
        except (np.linalg.LinAlgError, ValueError) as exc:
            failures += 1
            first = first or f"step {k}: {exc}"
            est = FilterpyAugmentedUKF(d, run.x[j], alpha=1e-4)  # restart, as a user would
        done += 1
    return {"steps": done, "failures": failures, "first_failure": first}


def _random_case(rng: np.random.Generator) -> tuple[Any, Any, float]:
    params = DCMotorParameters(
        J=float(rng.uniform(0.002, 0.05)), b=float(rng.uniform(0.01, 0.3)),
        Ke=float(rng.uniform(0.1, 0.6)), Ki=float(rng.uniform(0.1, 0.6)),
        Ra=float(rng.uniform(0.5, 4.0)), La=float(rng.choice([0.0, 0.05, 0.5, 2.0])),
    )
    T = float(rng.choice([0.001, 0.002, 0.005, 0.01]))
    model = dc_motor(params, q=float(rng.uniform(0.1, 5.0)), r=float(rng.uniform(0.01, 1.0)))
    dur = float(rng.uniform(2.0, 8.0))
    faults = []
    t = float(rng.uniform(0.2, 1.0))
    while t < dur - 0.2:
        end = min(dur, t + float(rng.uniform(0.2, 2.0)))
        kind = str(rng.choice(["step", "ramp", "intermittent"]))
        f: dict[str, Any] = {"kind": kind, "start": t, "end": end}
        if kind == "ramp":
            f |= {"gamma_from": float(rng.uniform(0, 1)), "gamma_to": float(rng.uniform(0, 1))}
        else:
            f |= {"gamma": float(rng.uniform(0, 1))}
            if kind == "intermittent":
                f |= {"period": float(rng.uniform(0.1, 1.0)), "duty": float(rng.uniform(0.1, 0.9))}
        faults.append(f)
        t = end + float(rng.uniform(0.0, 1.0))
    volts = [[0.0, float(rng.uniform(-300, 300))]]
    for _ in range(int(rng.integers(0, 4))):
        volts.append([volts[-1][0] + float(rng.uniform(0.3, 2.0)), float(rng.uniform(-300, 300))])
    sc = scenario_from_dict({
        "name": "soak", "duration": dur, "fault": faults, "voltage": {"steps": volts},
        "noise": {"current_sigma": float(np.sqrt(model.R[0, 0]))},
    })
    return model, sc, T


def soak(steps: int, seed: int = 0) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    total = 0
    nan_steps = 0
    non_pd = 0
    repairs = 0
    runs = 0
    max_rules = 0
    t0 = time.perf_counter()
    while total < steps:
        model, sc, T = _random_case(rng)
        run = simulate(model, sc, T, seed=int(rng.integers(2**31)))
        est = FuzzyUKF(model.discretize(T), x0=None if rng.random() < 0.5 else run.x[0])
        gaps = rng.random(len(run.t)) < 0.05  # 5 % of samples lost
        k_prev = -1
        for k in range(len(run.t)):
            if gaps[k] and k > 0:
                continue
            dt = T * (k - k_prev) if k_prev >= 0 else T
            k_prev = k
            out = est.step(run.u[k], run.y[k], dt)
            g = out.gamma[0]
            if not (g == g and np.isfinite(out.x_hat).all()):
                nan_steps += 1
            P = est.P
            if not (P[0, 0] > 0 and (P.shape[0] == 1 or np.linalg.det(P) > 0)):
                non_pd += 1
            total += 1
        runs += 1
        repairs += est.repairs
        max_rules = max(max_rules, est.out.rules)
        if not np.all(np.linalg.eigvalsh(est.P) > 0):
            non_pd += 1
    return {
        "steps": total, "runs": runs, "nan_steps": nan_steps, "non_pd_steps": non_pd,
        "cholesky_repairs": repairs, "max_rules": max_rules,
        "seconds": time.perf_counter() - t0,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--soak-steps", type=int, default=1_000_000)
    ap.add_argument("--filterpy-alpha-steps", type=int, default=20_000)
    args = ap.parse_args()
    cost = _timing(args.rounds)
    interp = _kernel_cost("python")
    aot = _kernel_cost("aot")
    base = cost["filterpy_ukf"]
    print(f"{'method':28s} {'us/step':>10s} {'filterpy / method':>18s}")
    for name, c in cost.items():
        print(f"{name:28s} {1e6 * c:10.2f} {base / c:18.1f}")
    if interp is not None:
        print(f"{'fuzzy_ukf, interpreted':28s} {1e6 * interp:10.2f} {base / interp:18.1f}")
    if aot is not None:
        print(f"{'fuzzy_ukf, AOT build (W^X)':28s} {1e6 * aot:10.2f} {base / aot:18.1f}")
    fp = _filterpy_paper_alpha(args.filterpy_alpha_steps)
    print(f"filterpy UKF with the paper's alpha = 1e-4: {fp['failures']} failures in "
          f"{fp['steps']} steps ({fp['first_failure']})")
    sk = soak(args.soak_steps)
    print(f"soak: {sk['steps']} steps over {sk['runs']} random runs in {sk['seconds']:.0f} s: "
          f"{sk['nan_steps']} NaN, {sk['non_pd_steps']} non-PD covariances, "
          f"{sk['cholesky_repairs']} clamped pivots, up to {sk['max_rules']} rules")
    print(json.dumps({
        "benchmark": "estimator",
        "us_per_step": {k: 1e6 * v for k, v in cost.items()},
        "speedup_vs_filterpy": {k: base / v for k, v in cost.items()},
        "fuzzy_ukf_interpreted_us_per_step": None if interp is None else 1e6 * interp,
        "fuzzy_ukf_aot_us_per_step": None if aot is None else 1e6 * aot,
        "filterpy_paper_alpha": fp,
        "soak": sk,
    }))


if __name__ == "__main__":
    main()
