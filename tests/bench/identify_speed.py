"""Speed of `identify` at high sample rates: `python -m tests.bench.identify_speed
[--rounds R] [--seeds S,S]`.

1. The record simulation the fits repeat thousands of times (`monitor.identify.lti.dsim`,
   x(k+1) = A x(k) + B u(k), y(k) = C x(k), compiled), against scipy.signal.dlsim, the
   library's form of the same recursion, on one record of a minute at 2 kHz (120,000
   samples), orders 2, 4 and 6: rounds with the two interleaved, the median per method,
   reported as the ratio (machine noise hits both alike), and the largest difference of
   their outputs relative to the output's size.
2. `motor-monitor identify` from the command line, as the rig zoo runs it, on the healthy
   minute of zoo rigs at 2 kHz (default seeds 10 and 41: a DC motor's current accepted, a
   free position refused): the wall time, and where the report has them its own timings.

Figures in a table, JSON on the last line.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import scipy.signal

from monitor.identify.lti import dsim
from tests.bench.rig_zoo import prepare
from tests.support import BIN

RATE = 2000.0
SECONDS = 60.0


def _system(n: int, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """A stable random (A, B, C) of order n, one input and one output, its slowest pole
    near the unit circle as a fitted model's is."""
    M = rng.normal(size=(n, n))
    A = 0.999 * M / max(abs(np.linalg.eigvals(M)))
    return A, rng.normal(size=(n, 1)), rng.normal(size=(1, n))


def _simulation(rounds: int) -> list[dict[str, Any]]:
    rng = np.random.default_rng(0)
    N = int(RATE * SECONDS)
    rows = []
    for n in (2, 4, 6):
        A, B, C = _system(n, rng)
        u = rng.normal(size=(N, 1))
        x0 = rng.normal(size=n)
        ours = dsim(A, B, C, u, x0)  # compiles once, outside the timing
        lib = np.asarray(scipy.signal.dlsim((A, B, C, np.zeros((1, 1)), 1.0), u, x0=x0)[1])
        diff = float(np.max(np.abs(ours - lib)) / np.max(np.abs(lib)))
        times: dict[str, list[float]] = {"dsim": [], "dlsim": []}
        for _ in range(rounds):
            t0 = time.perf_counter()
            dsim(A, B, C, u, x0)
            times["dsim"].append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            scipy.signal.dlsim((A, B, C, np.zeros((1, 1)), 1.0), u, x0=x0)
            times["dlsim"].append(time.perf_counter() - t0)
        ms = {k: 1e3 * statistics.median(v) for k, v in times.items()}
        rows.append({"order": n, "samples": N, "dsim_ms": round(ms["dsim"], 2),
                     "dlsim_ms": round(ms["dlsim"], 1),
                     "ratio": round(ms["dlsim"] / ms["dsim"], 1),
                     "relative_difference": diff})
    return rows


def _identify(seed: int) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        rig, _, _ = prepare(seed, d)
        cmd = [str(BIN / "motor-monitor"), "identify", "identify.log", "--rig", "rig.toml",
               "--out", "learned.toml", "--node", str(rig.nodes[0])]
        t0 = time.perf_counter()
        res = subprocess.run(cmd, cwd=d, capture_output=True, text=True, check=False)
        wall = time.perf_counter() - t0
        report_path = d / "learned.identify.json"
        report = json.loads(report_path.read_text()) if report_path.exists() else {}
        last = (res.stderr.strip().splitlines() or [""])[-1]
        return {"seed": seed, "rate_hz": rig.rate, "exit": res.returncode,
                "wall_s": round(wall, 1),
                "timing_s": {k: round(v, 1) for k, v in report.get("timing_s", {}).items()},
                "outcome": "written" if res.returncode == 0 else last[:120]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=5, help="timing rounds per order")
    ap.add_argument("--seeds", default="10,41", help="zoo rigs at 2 kHz to identify")
    args = ap.parse_args(argv)
    sim = _simulation(args.rounds)
    print(f"record simulation, {SECONDS:g} s at {RATE:g} Hz (median of {args.rounds}):")
    print(f"  {'order':>5} {'dsim ms':>9} {'dlsim ms':>9} {'ratio':>7} {'difference':>11}")
    for r in sim:
        print(f"  {r['order']:>5} {r['dsim_ms']:>9} {r['dlsim_ms']:>9} {r['ratio']:>7} "
              f"{r['relative_difference']:>11.1e}")
    runs = [_identify(int(s)) for s in args.seeds.split(",") if s]
    print("identify on zoo rigs:")
    for r in runs:
        print(f"  seed {r['seed']} at {r['rate_hz']:g} Hz: {r['wall_s']} s, exit {r['exit']} "
              f"({r['outcome']}); report timings {r['timing_s']}")
    print(json.dumps({"simulation": sim, "identify": runs}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
