"""Malformed DBC, threshold and scenario files and wrong command lines: each must end in one
clear error line naming the program, with exit status 2 and no traceback (`CliOutcome.clean`).

`cli_cases` run on the host (`run_cli_case`, `run_cli_cases`); the wrong-channel cases run in
robustness boot A, on a kernel with SocketCAN (``scripts/boot_a.sh`` writes their exit status
and stderr as ``cli_*_nochan.rc`` / ``.err``), and are read back by `guest_cli_outcomes`.
"""

from __future__ import annotations

import os
import re
import subprocess
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from tests.support import BIN
from tests.support.dbc import REPO_DBC
from tests.support.paths import ROOT

__all__ = [
    "CliCase",
    "CliOutcome",
    "cli_cases",
    "guest_cli_outcomes",
    "run_cli_case",
    "run_cli_cases",
    "write_bad_files",
]


@dataclass(frozen=True)
class CliCase:
    key: str
    title: str
    argv: tuple[str, ...]  # program name first: "motor-monitor" or "sim-ecu"
    expect: str  # a substring of the one error line


@dataclass(frozen=True)
class CliOutcome:
    case: CliCase
    returncode: int
    lines: tuple[str, ...]

    @property
    def traceback(self) -> bool:
        return any("Traceback" in ln for ln in self.lines)

    @property
    def clean(self) -> bool:
        """Exit status 2, one line naming the program, the expected text, no traceback."""
        prog = self.case.argv[0]
        return (self.returncode == 2 and len(self.lines) == 1 and not self.traceback
                and self.lines[0].startswith(f"{prog}") and ": error: " in self.lines[0]
                and self.case.expect in self.lines[0])


def write_bad_files(d: Path) -> dict[str, str]:
    """Malformed DBC, threshold and scenario files; returns name -> path."""
    d.mkdir(parents=True, exist_ok=True)
    dbc = REPO_DBC.read_text()
    files = {
        "garbage.dbc": 'VERSION ""\nBO_ 1 broken\n',
        "empty.dbc": "",
        "binary.dbc": "\x00\x01\x02\xff" * 10,
        "foreign.dbc": ('VERSION ""\n\nBU_: A\nBO_ 100 Foo: 8 A\n'
                        ' SG_ X : 0|8@1+ (1,0) [0|255] "" A\n'),
        "truncated.dbc": dbc[: len(dbc) // 3],
        "wrong_e2e.dbc": dbc.replace('BA_ "E2EDataID" BO_ 272 16;', 'BA_ "E2EDataID" BO_ 272 17;'),
        "no_current_n5.dbc": re.sub(r"BO_ 277 MotorCurrent_N5: 8 MotorECU\n(?: SG_[^\n]*\n)*",
                                    "", dbc),
        "bad.toml": "f1 = [unclosed\n",
        "swapped.toml": 'quantity = "gamma"\nf1 = 0.9\nf2 = 0.1\n',
        "nan.toml": 'quantity = "gamma"\nf1 = nan\nf2 = 0.8\n',
        "string.toml": 'quantity = "gamma"\nf1 = "low"\nf2 = 0.8\n',
        "no_f2.toml": 'quantity = "gamma"\nf1 = 0.1\n',
        "other_quantity.toml": 'quantity = "fault_volts"\nf1 = 0.1\nf2 = 0.8\n',
        "gamma2.toml": "duration = 5\n[[fault]]\nstart = 1\nend = 3\ngamma = 2\n",
        "backwards.toml": "duration = 5\n[[fault]]\nstart = 3\nend = 1\ngamma = 0.5\n",
        "negdur.toml": "duration = -5\n",
        "nangamma.toml": "duration = 5\n[[fault]]\nstart = 1\nend = 3\ngamma = nan\n",
        "badmotor.toml": "duration = 5\n[motor]\nJ = -1\n",
        "notoml.toml": "duration = = 5\n",
    }
    paths: dict[str, str] = {}
    for name, text in files.items():
        p = d / name
        p.write_text(text, errors="surrogateescape")
        paths[name] = str(p)
    paths["missing"] = str(d / "missing.file")
    return paths


def cli_cases(d: Path) -> list[CliCase]:
    """Malformed files and wrong arguments, each must end in one clear line, exit status 2."""
    f = write_bad_files(d)
    run = ("motor-monitor", "run", "--interface", "virtual", "--channel", "bad-input")
    ecu = ("sim-ecu", "--interface", "virtual", "--channel", "bad-input", "--node", "0",
           "--duration", "0.1")
    cases = [
        CliCase("dbc_garbage", "DBC: a broken message line", (*run, "--dbc", f["garbage.dbc"]),
                "garbage.dbc"),
        CliCase("dbc_empty", "DBC: empty file", (*run, "--dbc", f["empty.dbc"]), "empty.dbc"),
        CliCase("dbc_binary", "DBC: binary file", (*run, "--dbc", f["binary.dbc"]),
                "binary.dbc"),
        CliCase("dbc_foreign", "DBC: another bus's DBC", (*run, "--dbc", f["foreign.dbc"]),
                "unexpected message"),
        CliCase("dbc_truncated", "DBC: truncated", (*run, "--dbc", f["truncated.dbc"]),
                "truncated.dbc"),
        CliCase("dbc_e2e", "DBC: wrong E2EDataID", (*run, "--dbc", f["wrong_e2e.dbc"]),
                "E2EDataID"),
        CliCase("dbc_missing_msg", "DBC: a message missing",
                (*run, "--dbc", f["no_current_n5.dbc"]), "missing message MotorCurrent_N5"),
        CliCase("dbc_missing", "DBC: no such file", (*run, "--dbc", f["missing"]),
                "no such file"),
        CliCase("dbc_canopen", "DBC: given with a CANopen rig (described by its EDS)",
                (*run, "--rig", str(ROOT / "rigs" / "cia402-example.toml"),
                 "--dbc", str(REPO_DBC)), "is a CANopen rig"),
        CliCase("thr_toml", "thresholds: invalid TOML", (*run, "--thresholds", f["bad.toml"]),
                "not valid TOML"),
        CliCase("thr_swapped", "thresholds: f1 >= f2",
                (*run, "--thresholds", f["swapped.toml"]), "must be less than"),
        CliCase("thr_nan", "thresholds: NaN", (*run, "--thresholds", f["nan.toml"]), "finite"),
        CliCase("thr_string", "thresholds: not a number",
                (*run, "--thresholds", f["string.toml"]), "must be a number"),
        CliCase("thr_nokey", "thresholds: key missing", (*run, "--thresholds", f["no_f2.toml"]),
                "missing key"),
        CliCase("thr_quantity", "thresholds: other quantity",
                (*run, "--thresholds", f["other_quantity.toml"]), "quantity"),
        CliCase("thr_missing", "thresholds: no such file", (*run, "--thresholds", f["missing"]),
                "no such file"),
        CliCase("scen_gamma", "scenario: gamma > 1 (sim-ecu)",
                (*ecu, "--scenario", f["gamma2.toml"]), "[0, 1]"),
        CliCase("scen_backwards", "scenario: fault ends before it starts (sim-ecu)",
                (*ecu, "--scenario", f["backwards.toml"]), "start < end"),
        CliCase("scen_negdur", "scenario: negative duration (sim-ecu)",
                (*ecu, "--scenario", f["negdur.toml"]), "duration"),
        CliCase("scen_nan", "scenario: NaN gamma (sim-ecu)",
                (*ecu, "--scenario", f["nangamma.toml"]), "finite"),
        CliCase("scen_motor", "scenario: negative motor inertia (sim-ecu)",
                (*ecu, "--scenario", f["badmotor.toml"]), "positive"),
        CliCase("scen_toml", "scenario: invalid TOML (sim-ecu)",
                (*ecu, "--scenario", f["notoml.toml"]), "notoml"),
        CliCase("scen_unknown", "scenario: unknown name (sim-ecu)", (*ecu, "--scenario", "nope"),
                "unknown scenario"),
        CliCase("scen_demo", "scenario: gamma > 1 (motor-monitor demo)",
                ("motor-monitor", "demo", "--scenario", f["gamma2.toml"]), "[0, 1]"),
        CliCase("arg_nodes16", "CLI: --nodes 16", ("motor-monitor", "run", "--nodes", "16"),
                "0..15"),
        CliCase("arg_nodes_text", "CLI: --nodes a,b", ("motor-monitor", "run", "--nodes", "a,b"),
                "nodes must be"),
        CliCase("arg_rate_text", "CLI: --rate fast", (*run, "--rate", "fast"), "invalid float"),
        CliCase("arg_rate_zero", "CLI: --rate 0", (*run, "--rate", "0"), "rate"),
        CliCase("arg_rate_neg", "CLI: --rate -5", (*run, "--rate", "-5"), "rate"),
        CliCase("arg_rate_nan", "CLI: --rate nan", (*run, "--rate", "nan"), "rate"),
        CliCase("arg_iface", "CLI: unknown interface",
                ("motor-monitor", "run", "--interface", "nosuchbus", "--channel", "x"),
                "cannot open CAN interface"),
        CliCase("arg_rrd_dir", "CLI: --rrd into a missing directory",
                (*run, "--rrd", str(d / "nodir" / "x.rrd")), "does not exist"),
        CliCase("arg_events_dir", "CLI: --events into a missing directory",
                (*run, "--events", str(d / "nodir" / "ev.jsonl")), "nodir"),
        CliCase("arg_command", "CLI: unknown command", ("motor-monitor", "frobnicate"),
                "invalid choice"),
        CliCase("arg_ecu_node", "CLI: sim-ecu --node 16",
                (*ecu, "--scenario", "healthy", "--node", "16"), "--node"),
        CliCase("arg_ecu_rate", "CLI: sim-ecu --rate 0",
                (*ecu, "--scenario", "healthy", "--rate", "0"), "--rate"),
        CliCase("arg_ecu_duration", "CLI: sim-ecu --duration -1",
                ("sim-ecu", "--interface", "virtual", "--channel", "x", "--node", "0",
                 "--scenario", "healthy", "--duration", "-1"), "--duration"),
    ]
    return cases


def _lines(text: str) -> tuple[str, ...]:
    """The non-blank lines of a program's stderr."""
    return tuple(ln for ln in text.splitlines() if ln.strip())


def run_cli_case(case: CliCase, cwd: Path, timeout: float = 120.0) -> CliOutcome:
    exe = str(BIN / case.argv[0])
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAN_")}
    try:
        proc = subprocess.run([exe, *case.argv[1:]], capture_output=True, text=True,
                              timeout=timeout, cwd=cwd, env=env, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired as exc:
        err = exc.stderr.decode(errors="replace") if isinstance(exc.stderr, bytes) else ""
        note = f"(timed out after {timeout:.0f} s: the program ran instead of refusing)"
        return CliOutcome(case, -9, (*_lines(err), note))
    return CliOutcome(case, proc.returncode, _lines(proc.stderr))


def run_cli_cases(cases: Iterable[CliCase], cwd: Path, workers: int = 2,
                  timeout: float = 60.0) -> list[CliOutcome]:
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(lambda c: run_cli_case(c, cwd, timeout), cases))


def guest_cli_outcomes(out: Path) -> list[CliOutcome]:
    """The wrong-channel runs of boot A, on a kernel with SocketCAN."""
    cases = [
        CliCase("guest_mon_nochan", "CLI: motor-monitor on a CAN channel that does not exist "
                "(SocketCAN kernel)", ("motor-monitor",), "cannot open CAN interface"),
        CliCase("guest_ecu_nochan", "CLI: sim-ecu on a CAN channel that does not exist "
                "(SocketCAN kernel)", ("sim-ecu",), "cannot open CAN"),
    ]
    res: list[CliOutcome] = []
    for case, stem in zip(cases, ("cli_mon_nochan", "cli_ecu_nochan"), strict=True):
        rc_path, err_path = out / f"{stem}.rc", out / f"{stem}.err"
        rc = int(rc_path.read_text().strip()) if rc_path.exists() else -1
        err = err_path.read_text(errors="replace") if err_path.exists() else ""
        res.append(CliOutcome(case, rc, _lines(err)))
    return res
