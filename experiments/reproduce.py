"""`motor-monitor reproduce`: the paper's DC-motor experiment (section 5, Figs. 1-4).

Table 1 motor, u = 220 V, Q = 1.44 I, R = 0.25, alpha = 1e-4, beta = 2 and
x(0) = [9.432, -0.176, -1.240] (75), at the ECU's sample period (10 ms by default: the
paper's T = 1 s Euler model is unstable, see model.py). The paper does not say which fault
it injected; this run spins the motor up from x(0) fault-free, then loses 50 % of the
actuator's effectiveness at step 360, has an outage (gamma = 1) at step 720 and recovers at
step 1080, so that all three regions of Fig. 4 occur and can be clustered.

Outputs (in --out DIR): fig1_fault_curve.png, fig2_current_error.png, fig3_rule_count.png,
fig4_fault_regions.png, thresholds.toml (the calibration the monitor can load) and
summary.json with the figures compared point by point with the paper's statements.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from monitor.diagnosis import calibrate, fcm_memberships, fuzzy_c_means, save_thresholds
from monitor.estimation.fuzzy_ukf import FuzzyUKF, FuzzyUKFConfig
from monitor.estimation.model import dc_motor
from monitor.plotting import pyplot
from monitor.runtime.argtypes import positive_float
from sim_ecu.plant import simulate
from sim_ecu.scenario import Scenario, scenario_from_dict

Array = NDArray[np.float64]

__all__ = ["PAPER_X0", "ReproduceResult", "paper_scenario", "reproduce", "run_paper_experiment"]

PAPER_X0 = (9.432, -0.176, -1.240)
PAPER_U = 220.0
FAULT_STEP, OUTAGE_STEP, RECOVERY_STEP, END_STEP = 360, 720, 1080, 1440


def paper_scenario(T: float) -> Scenario:
    return scenario_from_dict(
        {
            "name": "paper-dc-motor",
            "duration": END_STEP * T,
            "noise": {"current_sigma": math.sqrt(0.25), "process": 1.0},
            "voltage": {"steps": [[0.0, PAPER_U]]},
            "fault": [
                {"start": FAULT_STEP * T, "end": OUTAGE_STEP * T, "gamma": 0.5},
                {"start": OUTAGE_STEP * T, "end": RECOVERY_STEP * T, "gamma": 1.0},
            ],
        }
    )


@dataclass
class ReproduceResult:
    steps: NDArray[np.int64]
    gamma_true: Array
    gamma_hat: Array
    fault_current: Array  # f^ on the current state (A per step), Fig. 1
    x_e_current: Array  # x~ - x^ current component, Fig. 2
    est_error_current: Array  # x^ - x_true current component
    rules: NDArray[np.int64]
    summary: dict[str, Any]


def run_paper_experiment(T: float = 0.01, seed: int = 0) -> ReproduceResult:
    model = dc_motor(q=1.44, r=0.25)
    scen = paper_scenario(T)
    run = simulate(model, scen, T, seed=seed, x0=PAPER_X0, settle=False)
    est = FuzzyUKF(model.discretize(T), FuzzyUKFConfig(alpha=1e-4, beta=2.0), x0=PAPER_X0)
    N = len(run.t)
    g = np.empty(N)
    fc = np.empty(N)
    xe = np.empty(N)
    err = np.empty(N)
    rules = np.empty(N, dtype=np.int64)
    for k in range(N):
        out = est.step(run.u[k], run.y[k], T)
        g[k] = out.gamma[0]
        fc[k] = out.fault[0]
        xe[k] = out.x_e[0]
        err[k] = out.x_hat[0] - run.x[k, 0]
        rules[k] = out.rules
    steps = np.arange(N, dtype=np.int64)
    res = ReproduceResult(steps, run.gamma[:, 0].copy(), g, fc, xe, err, rules, {})
    res.summary = _summary(res, est, T, seed)
    return res


def _summary(r: ReproduceResult, est: FuzzyUKF, T: float, seed: int) -> dict[str, Any]:
    after = r.steps >= 180
    within = float(np.mean(np.abs(r.x_e_current[after]) <= 0.02))
    fcm = fuzzy_c_means(r.gamma_hat, 3)
    th = calibrate(r.gamma_hat)
    seg = {
        "fault_free": (200, FAULT_STEP),
        "fault": (FAULT_STEP + 50, OUTAGE_STEP),
        "outage": (OUTAGE_STEP + 50, RECOVERY_STEP),
        "recovered": (RECOVERY_STEP + 50, END_STEP),
    }
    seg_stats = {
        name: {
            "gamma_true": float(np.mean(r.gamma_true[a:b])),
            "gamma_hat_mean": float(np.mean(r.gamma_hat[a:b])),
            "gamma_hat_std": float(np.std(r.gamma_hat[a:b])),
        }
        for name, (a, b) in seg.items()
    }
    delays = {}
    for name, k0 in (("fault", FAULT_STEP), ("outage", OUTAGE_STEP), ("recovery", RECOVERY_STEP)):
        target = r.gamma_true[k0]
        before = r.gamma_true[k0 - 1]
        half = 0.5 * (target + before)
        seg_g = r.gamma_hat[k0:]
        crossed = np.nonzero(seg_g >= half if target > before else seg_g <= half)[0]
        delays[name] = int(crossed[0]) if crossed.size else None
    return {
        "sample_period_s": T,
        "seed": seed,
        "steps": int(r.steps.size),
        "paper": {
            "current_error_within_0.02_after_step_180": True,
            "rules_before_step_360": 2,
            "rules_when_stable": 10,
            "F1": 0.3,
            "F2": 1.0,
        },
        "ours": {
            "x_e_current_max_abs_after_step_180": float(np.max(np.abs(r.x_e_current[after]))),
            "x_e_current_fraction_within_0.02_after_step_180": within,
            "x_e_current_rms_after_step_180": float(np.sqrt(np.mean(r.x_e_current[after] ** 2))),
            "estimate_error_current_rms_after_step_180": float(
                np.sqrt(np.mean(r.est_error_current[after] ** 2))
            ),
            "rules_at_step_359": int(r.rules[FAULT_STEP - 1]),
            "rules_max_before_step_360": int(np.max(r.rules[:FAULT_STEP])),
            "rules_final": int(r.rules[-1]),
            "structure_events": est.structure_events,
            "fcm_centres": [float(c) for c in fcm.centres],
            "F1": th.f1,
            "F2": th.f2,
            "threshold_quantity": "gamma_hat (loss of effectiveness, 0..1)",
            "segments": seg_stats,
            "half_way_delay_steps": delays,
            "cholesky_repairs": est.repairs,
        },
    }


def _figures(r: ReproduceResult, out: Path, f1: float, f2: float) -> list[Path]:
    plt = pyplot()
    from matplotlib.ticker import MaxNLocator

    paths = []
    s = r.steps

    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    a1.plot(s, r.fault_current, lw=0.8, color="tab:red")
    a1.set_ylabel("f^ on current (A/step)")
    a1.set_title("Fig. 1 - fault curve: f^ = -B gamma^ u (10) and gamma^")
    a2.plot(s, r.gamma_true, color="k", lw=1.5, label="true gamma")
    a2.plot(s, r.gamma_hat, color="tab:blue", lw=0.8, label="gamma^ (fuzzy UKF)")
    a2.set_ylabel("loss of effectiveness")
    a2.set_xlabel("step")
    a2.legend(loc="upper left")
    for a in (a1, a2):
        for k in (FAULT_STEP, OUTAGE_STEP, RECOVERY_STEP):
            a.axvline(k, color="grey", ls=":", lw=0.8)
    fig.tight_layout()
    paths.append(out / "fig1_fault_curve.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    a1.plot(s, r.x_e_current, lw=0.8)
    a1.axhspan(-0.02, 0.02, color="tab:green", alpha=0.25, label="paper: within +-0.02")
    a1.axvline(180, color="grey", ls=":", lw=0.8)
    a1.set_ylabel("x~ - x^ current (A)")
    a1.set_title("Fig. 2 - current estimate error x_e = x~ - x^ (50)")
    a1.set_ylim(-2, 2)
    a1.legend(loc="upper right")
    a2.plot(s, r.est_error_current, lw=0.8, color="tab:purple")
    a2.set_ylabel("x^ - x (true) current (A)")
    a2.set_xlabel("step")
    a2.set_ylim(-2, 2)
    fig.tight_layout()
    paths.append(out / "fig2_current_error.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(8, 3.5))
    ax.step(s, r.rules, where="post")
    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax.axvline(360, color="grey", ls=":", lw=0.8)
    ax.set_xlabel("step")
    ax.set_ylabel("rules")
    ax.set_title("Fig. 3 - number of fuzzy rules")
    fig.tight_layout()
    paths.append(out / "fig3_rule_count.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    fcm = fuzzy_c_means(r.gamma_hat, 3)
    u = fcm_memberships(r.gamma_hat, fcm.centres)
    label = np.argmax(u, axis=0)
    fig, ax = plt.subplots(figsize=(8, 4))
    regions = (("fault-free", "tab:green"), ("fault", "tab:orange"), ("outage", "tab:red"))
    for c, (name, col) in enumerate(regions):
        sel = label == c
        tag = f"{name} (centre {fcm.centres[c]:.2f})"
        ax.scatter(s[sel], r.gamma_hat[sel], s=3, color=col, label=tag)
    ax.axhline(f1, color="k", ls="--", lw=0.8, label=f"F1 = {f1:.3f}")
    ax.axhline(f2, color="k", ls="-.", lw=0.8, label=f"F2 = {f2:.3f}")
    ax.set_xlabel("step")
    ax.set_ylabel("gamma^")
    ax.set_title("Fig. 4 - fault regions by fuzzy c-means (55)-(62), (76)")
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    paths.append(out / "fig4_fault_regions.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    return paths


def reproduce(out: Path, T: float = 0.01, seed: int = 0) -> dict[str, Any]:
    """Run the experiment, write figures, thresholds.toml and summary.json into `out`."""
    out.mkdir(parents=True, exist_ok=True)
    r = run_paper_experiment(T, seed)
    f1 = float(r.summary["ours"]["F1"])
    f2 = float(r.summary["ours"]["F2"])
    figs = _figures(r, out, f1, f2)
    th = calibrate(r.gamma_hat)
    save_thresholds(out / "thresholds.toml", th, source=f"motor-monitor reproduce (seed {seed})")
    r.summary["files"] = [p.name for p in figs] + ["thresholds.toml"]
    (out / "summary.json").write_text(json.dumps(r.summary, indent=2) + "\n", encoding="utf-8")
    return r.summary


def _cmd_reproduce(args: argparse.Namespace) -> int:
    summary = reproduce(Path(args.out), T=args.period, seed=args.seed)
    ours = summary["ours"]
    print(f"wrote {', '.join(summary['files'])} and summary.json to {args.out}")
    print(
        f"thresholds F1 = {ours['F1']:.3f}, F2 = {ours['F2']:.3f} on gamma^ "
        f"(paper: F1 = 0.3, F2 = 1 in its own units)"
    )
    print(
        f"rules: {ours['rules_at_step_359']} at step 359 (paper: 2), "
        f"{ours['rules_final']} at the end (paper: 10)"
    )
    print(
        "current error x~ - x^ after step 180: rms "
        f"{ours['x_e_current_rms_after_step_180']:.3f} A, "
        f"{100 * ours['x_e_current_fraction_within_0.02_after_step_180']:.0f} % within +-0.02"
    )
    return 0


def add_command(sub: argparse._SubParsersAction[Any]) -> None:
    """`motor-monitor reproduce` (registered through the motor_monitor.commands entry point)."""
    r = sub.add_parser("reproduce", help="the paper's DC-motor experiment, Figs. 1-4")
    r.add_argument("--out", default="out/reproduce", help="output directory")
    r.add_argument("--period", type=positive_float, default=0.01, help="sample period, s")
    r.add_argument("--seed", type=int, default=0)
    r.set_defaults(func=_cmd_reproduce)
