"""`motor-monitor` command line: reproduce, calibrate, run, replay, demo.

Every configuration or usage mistake ends in one line `motor-monitor: error: ...` on
stderr and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn

__all__ = ["UsageError", "main"]


class UsageError(Exception):
    """A mistake in what the user asked for; printed as one line, exit status 2."""


class _Parser(argparse.ArgumentParser):
    """argparse prints its usage block before an error: two lines. One is enough."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not v > 0:
        raise argparse.ArgumentTypeError(f"must be positive: {text!r}")
    return v


def _cmd_reproduce(args: argparse.Namespace) -> int:
    from experiments.reproduce import reproduce

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


def _cmd_calibrate(args: argparse.Namespace) -> int:
    import numpy as np

    from monitor.diagnosis import calibrate, save_thresholds

    path = Path(args.gamma_file)
    try:
        values = np.loadtxt(path, dtype=float, ndmin=1, comments="#", delimiter=",", usecols=0)
    except (OSError, ValueError) as exc:
        raise UsageError(f"{path}: cannot read gamma^ samples ({exc})") from None
    th = calibrate(values)
    save_thresholds(args.out, th, source=str(path))
    print(json.dumps({"f1": th.f1, "f2": th.f2, "centres": list(th.centres)}))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="motor-monitor",
        description="CAN-bus monitor: fuzzy UKF actuator-fault estimation and diagnosis",
    )
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    r = sub.add_parser("reproduce", help="the paper's DC-motor experiment, Figs. 1-4")
    r.add_argument("--out", default="out/reproduce", help="output directory")
    r.add_argument("--period", type=_positive_float, default=0.01, help="sample period, s")
    r.add_argument("--seed", type=int, default=0)
    r.set_defaults(func=_cmd_reproduce)

    c = sub.add_parser("calibrate", help="learn thresholds F1 < F2 from gamma^ samples")
    c.add_argument("gamma_file", help="text/CSV file, gamma^ in the first column")
    c.add_argument("--out", default="thresholds.toml")
    c.set_defaults(func=_cmd_calibrate)

    from monitor import daemon, demo

    daemon.add_commands(sub)
    demo.add_command(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    from monitor.bus.codec import CodecError
    from monitor.app.daemon import BusError
    from monitor.diagnosis import DiagnosisError
    from monitor.estimation.model import ModelError
    from sim_ecu.scenario import ScenarioError
    from monitor.bus.secoc import SecOCError

    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(args.func(args))
    except (UsageError, BusError, CodecError, DiagnosisError, ModelError, ScenarioError,
            SecOCError) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        print(f"motor-monitor: error: {msg}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"motor-monitor: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
