"""The realistic runs after `identify`: `python -m tests.bench.realistic_identify [--keep DIR]`.

The route the README gives a user whose motor is not the paper's: record a healthy minute,
`motor-monitor identify` it, `motor-monitor replay` with the learned rig. Here on our own
bus (the built-in rig, `rigs/motor.toml`), for the motors of `tests.bench.realistic` and
the others the issue that asked for this named:

  noise-x3, load-steps, load+loss, friction+offset+loss: the paper's motor with what
      `tests.bench.realistic` adds (a sensor 3x noisier than the model's; load-torque
      steps; a constant load; Coulomb friction, a sensor offset and quantisation);
  paper-220V: the paper's motor as it is;
  paper-40V: the same motor run at 40 V;
  servo-24V: a small, stiff 24 V servo at 1 kHz (J = 2e-5, b = 1e-5, Ke = Ki = 0.03,
      Ra = 1, La = 1e-3, sensor sigma 0.01 A), which the built-in rig's model is not.

For each motor: a healthy minute excited by voltage steps between 25 % and 100 % of its
voltage, held 0.05-0.5 s each (with its load, friction, offset and noise: a user records the
motor as it runs), written as a candump log of our bus (python-can's writer, the frames'
counters and CRCs as our ECU sends them); `motor-monitor identify` on it with the built-in
rig and the default `--model auto`; then the motor's runs at its constant voltage (those of
`tests.bench.realistic` for the paper's motor, a healthy run and losses of 0.3 and 0.6
for the others), each replayed (`motor-monitor replay --events`) with the built-in rig's
model (the paper's motor: where that model is the truth's family) and with the learned rig,
and scored from the events (`tests.bench.zoo.score`: accuracy outside 0.3 s after each true
change and the first 2 s, false alarms, onset to the first alarm of each loss >= 0.3).

Output: a row per run and model, then the figures as JSON (per motor: identify's exit
status, seconds, chosen model and the last line of a refusal; per run and model: accuracy,
false alarms, delays, mismatch-flag share).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np

from monitor.bus.codec import load_database
from monitor.estimation.model import DCMotorParameters, dc_motor
from sim_ecu.plant import simulate
from sim_ecu.scenario import scenario_from_dict
from tests.bench.realistic import MODEL_SIGMA, RATE, Run, runs, sensor_reading
from tests.bench.rig_zoo import monitor_exe
from tests.bench.zoo.score import NodeTruth, read_events, score_node

ROOT = Path(__file__).resolve().parents[2]
BUILTIN_RIG = ROOT / "rigs" / "motor.toml"
NODE = 0
T0 = 1_750_000_000.0
CAPTURE_S = 60.0


@dataclass
class Motor:
    """A motor, what its sensor and load add, and its runs (at `volts`, constant)."""

    name: str
    params: DCMotorParameters
    volts: float
    rate: float
    sigma: float  # the sensor's noise, A
    q: float  # process-noise intensity of the plant
    extras: Run  # its load, offset and quantisation (its sigma and faults unused)
    runs: list[Run] = field(default_factory=list)
    default_fits: bool = True  # the built-in rig's model is this motor's


def motors() -> list[Motor]:
    paper = DCMotorParameters()
    servo = DCMotorParameters(J=2e-5, b=1e-5, Ke=0.03, Ki=0.03, Ra=1.0, La=1e-3)
    out = []
    for r in runs():
        out.append(Motor(r.name, paper, 220.0, RATE, r.sigma, 1.44, r, [r]))

    def losses(seed: int, sigma: float) -> list[Run]:
        return [Run("healthy", 30.0, seed, sigma=sigma),
                Run("loss 0.3", 30.0, seed + 1, sigma=sigma, faults=((12.0, 0.3),)),
                Run("loss 0.6", 30.0, seed + 2, sigma=sigma, faults=((12.0, 0.6),))]

    out.append(Motor("paper-220V", paper, 220.0, RATE, MODEL_SIGMA, 1.44,
                     Run("paper-220V", 0.0, 0), losses(201, MODEL_SIGMA)))
    out.append(Motor("paper-40V", paper, 40.0, RATE, MODEL_SIGMA, 1.44,
                     Run("paper-40V", 0.0, 0), losses(211, MODEL_SIGMA)))
    out.append(Motor("servo-24V", servo, 24.0, 1000.0, 0.01, 1e-4,
                     Run("servo-24V", 0.0, 0, sigma=0.01), losses(221, 0.01),
                     default_fits=False))
    return out


def excitation(volts: float, seconds: float, seed: int) -> list[list[float]]:
    """Voltage steps between 25 % and 100 % of `volts`, each held 0.05-0.5 s."""
    rng = np.random.default_rng(seed)
    steps, t = [], 0.0
    while t < seconds:
        steps.append([t, float(volts * rng.uniform(0.25, 1.0))])
        t += float(rng.uniform(0.05, 0.5))
    return steps


def simulated(motor: Motor, run: Run, duration: float, voltage: list[list[float]],
              seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t, u, sensor reading, true gamma) of `run`'s faults on `motor` with its extras."""
    T = 1.0 / motor.rate
    scenario = scenario_from_dict({
        "name": run.name, "duration": duration,
        "fault": [{"start": s, "gamma": g} for s, g in run.faults],
        "noise": {"current_sigma": motor.sigma, "process": 1.0},
        "voltage": {"steps": voltage},
    })
    plant = dc_motor(motor.params, q=motor.q, r=motor.sigma**2)
    # a load torque T_L enters the speed equation as -T_L / J
    sim = simulate(plant, scenario, T, seed=seed,
                   disturbance=[0.0, -1.0 / motor.params.J, 0.0], load=motor.extras.load)
    return sim.t, sim.u[:, 0], sensor_reading(motor.extras, sim.y)[:, 0], sim.gamma[:, 0]


def write_log(path: Path, t: np.ndarray, u: np.ndarray, y: np.ndarray) -> None:
    """Our bus as our ECU sends it: per sample the current frame, then the command's."""
    db = load_database()
    cur_id, volt_id = db.frame_id("current", NODE), db.frame_id("voltage", NODE)
    with can.Logger(str(path)) as log:
        for k in range(t.size):
            ts = T0 + float(t[k])
            log(can.Message(timestamp=ts, arbitration_id=cur_id, is_extended_id=False,
                            data=db.encode_current(NODE, float(y[k]), k & 0xF)))
            log(can.Message(timestamp=ts, arbitration_id=volt_id, is_extended_id=False,
                            data=db.encode_voltage(NODE, float(u[k]), k & 0xF)))


def motor_monitor(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """`motor-monitor ARGS` in `cwd`, as a user runs it (the rig zoo's executable)."""
    return subprocess.run([monitor_exe(), *args], cwd=cwd, capture_output=True, text=True,
                          timeout=1800)


def identify(motor: Motor, d: Path) -> dict[str, Any]:
    healthy = dataclasses.replace(motor.extras, faults=())
    t, u, y, _ = simulated(motor, healthy, CAPTURE_S, excitation(motor.volts, CAPTURE_S, 7),
                           seed=17)
    write_log(d / "identify.log", t, u, y)
    t0 = time.perf_counter()
    res = motor_monitor("identify", "identify.log", "--rig", str(BUILTIN_RIG), "--out",
                        "learned.toml", cwd=d)
    out: dict[str, Any] = {"exit": res.returncode, "seconds": time.perf_counter() - t0}
    if res.returncode != 0:
        out["reason"] = (res.stderr.strip().splitlines() or [""])[-1]
        return out
    report = json.loads((d / "learned.identify.json").read_text())
    out["model"] = f"{report['kind']} n={report['order']}"
    out["holdout_fit_pct"] = report["fit"]["nrmse_holdout_pct"][0]
    return out


def diagnose(motor: Motor, run: Run, d: Path, rig: Path) -> dict[str, Any]:
    stem = run.name.replace(" ", "_")
    log = d / f"{stem}.log"
    if not log.exists():
        t, u, y, _ = simulated(motor, run, run.duration, [[0.0, motor.volts]], run.seed)
        write_log(log, t, u, y)
        (d / f"{stem}.truth.json").write_text(json.dumps(
            {"steps": [[0.0, 0.0]] + [[s, v] for s, v in run.faults]}))
    events = d / f"{stem}.{rig.stem}.events.jsonl"
    res = motor_monitor("replay", log.name, "--rig", str(rig), "--events", events.name,
                        cwd=d)
    if res.returncode != 0:
        return {"exit": res.returncode,
                "reason": (res.stderr.strip().splitlines() or [""])[-1]}
    steps = json.loads((d / f"{stem}.truth.json").read_text())["steps"]
    truth = NodeTruth(T0, run.duration, [(T0 + s, v) for s, v in steps])
    ev, _ = read_events(events)
    sc = score_node(ev.get(NODE, []), truth)
    return {"exit": 0, "accuracy": sc.accuracy, "false_alarms": sc.false_alarms,
            "delays": sc.delays, "mismatch_share": sc.mismatch_share}


def _row(name: str, model: str, r: dict[str, Any]) -> str:
    if r["exit"] != 0:
        return f"{name:24s} {model:10s} exit {r['exit']}: {r['reason'][:90]}"
    d = r["delays"]
    ds = ("-" if not d else f"{max(d):.2f}" if all(math.isfinite(x) for x in d)
          else "missed")
    return (f"{name:24s} {model:10s} {100 * r['accuracy']:7.2f} {r['false_alarms']:3d} "
            f"{ds:>7s} {100 * r['mismatch_share']:9.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keep", type=Path, help="keep each motor's logs, rigs and events here")
    ap.add_argument("--motors", default="", help="only these motors, comma-separated")
    args = ap.parse_args()
    chosen = [x for x in args.motors.split(",") if x]
    unknown = sorted(set(chosen) - {m.name for m in motors()})
    if unknown:
        ap.error(f"--motors: no motor named {', '.join(unknown)} (the motors: "
                 f"{', '.join(m.name for m in motors())})")
    base = args.keep or Path(tempfile.mkdtemp(prefix="realistic-identify-"))
    out: dict[str, Any] = {}
    worst = math.inf
    print(f"{'run':24s} {'model':10s} {'acc %':>7s} {'FA':>3s} {'delay':>7s} "
          f"{'flag up %':>9s}")
    for motor in motors():
        if chosen and motor.name not in chosen:
            continue
        d = base / motor.name
        d.mkdir(parents=True, exist_ok=True)
        ident = identify(motor, d)
        line = (f"identify {motor.name}: " + (
            f"{ident['model']}, hold-out fit {ident['holdout_fit_pct']:.1f} %"
            if ident["exit"] == 0 else f"refused: {ident['reason']}")
            + f" ({ident['seconds']:.1f} s)")
        print(line, flush=True)
        rows: dict[str, Any] = {}
        for run in motor.runs:
            per: dict[str, Any] = {}
            rigs = ([("built-in", BUILTIN_RIG)] if motor.default_fits else []) + (
                [("learned", d / "learned.toml")] if ident["exit"] == 0 else [])
            for label, rig in rigs:
                per[label] = diagnose(motor, run, d, rig)
                print(_row(f"{motor.name}/{run.name}" if len(motor.runs) > 1 else run.name,
                           label, per[label]), flush=True)
                if label == "learned":
                    worst = min(worst, per[label].get("accuracy", 0.0))
            rows[run.name] = per
        out[motor.name] = {"identify": ident, "runs": rows}
    identified = sum(v["identify"]["exit"] == 0 for v in out.values())
    print(json.dumps({"benchmark": "realistic_identify", "motors": len(out),
                      "identified": identified,
                      "worst_learned_accuracy": None if math.isinf(worst) else worst,
                      "results": out}))


if __name__ == "__main__":
    main()
