"""The programs start with what their command uses: `motor-monitor run` parses its command
line with python-can alone (it opens its bus before it loads anything else); `motor-monitor
run` and `sim-ecu` start without python-can's MF4 support (asammdf:
`monitor.runtime.imports`), the daemon without the other commands' modules and, until a
recording is asked for, without rerun-sdk and pandas; the command list is whole where it is
asked for. Each case starts the program as its own process (``python -X importtime -m ...``:
the names it imported, from its stderr)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from monitor.app.cli import BUILTIN_COMMANDS, command_word
from tests.support.paths import ROOT


def _imported(*args: str) -> tuple[set[str], str]:
    """(every module the program imported, its stdout) for `python -X importtime -m args`."""
    res = subprocess.run([sys.executable, "-X", "importtime", "-m", *args], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    names = {line.rsplit("|", 1)[1].strip() for line in res.stderr.splitlines()
             if line.startswith("import time:") and line.count("|") == 2}
    assert "monitor" in names or "sim_ecu" in names, res.stderr[-2000:]
    return names, res.stdout


def _roots(names: set[str]) -> set[str]:
    """The packages of `names`, at every depth. (A refused import is listed too, as taking no
    time: asammdf itself, when left out; its modules are not.)"""
    return names | {n.rsplit(".", d)[0] for n in names for d in range(1, n.count(".") + 1)}


def test_the_daemon_starts_without_mf4_and_the_other_commands() -> None:
    names, out = _imported("monitor", "run", "--help")
    assert "--interface" in out
    roots = _roots(names)
    assert "can" in roots  # the bus opens first (`monitor.runtime.livebus`) ...
    # ... before the rig, the estimator and its numerical libraries load (`monitor.app.daemon`)
    for unused in ("numba", "scipy", "cantools", "monitor.estimation", "monitor.pipeline",
                   "monitor.app.daemon", "asammdf.blocks", "rerun", "pandas", "experiments",
                   "sim_ecu",
                   "monitor.identify", "monitor.archive", "monitor.app.replay",
                   "monitor.app.identify", "monitor.app.calibrate"):
        assert unused not in roots, unused


def test_the_virtual_ecu_starts_without_mf4() -> None:
    names, out = _imported("sim_ecu", "--help")
    assert "--scenario" in out
    assert "can" in _roots(names)
    assert "asammdf.blocks" not in _roots(names)


def test_a_command_that_reads_logs_keeps_mf4() -> None:
    names, _ = _imported("monitor", "replay", "--help")
    assert "asammdf.blocks" in _roots(names)  # python-can's MF4 reader, for .mf4 archives


def test_the_help_lists_every_command() -> None:
    _, out = _imported("monitor", "--help")
    for name in (*BUILTIN_COMMANDS, "demo", "reproduce"):
        assert f"\n    {name} " in out, name


@pytest.mark.parametrize(("argv", "word"), [
    (["run", "--channel", "vcan0"], "run"),
    (["-v", "-v", "replay", "x.log"], "replay"),
    (["-vv", "status", "m.prom"], "status"),
    (["--verbose", "demo"], "demo"),
    (["-h", "run"], None),  # the whole list is asked for
    (["--help"], None),
    (["--", "run"], None),
    ([], None),
])
def test_the_command_word(argv: list[str], word: str | None) -> None:
    assert command_word(argv) == word


def test_mf4_is_left_out_only_where_python_can_is_not_loaded_yet(tmp_path: Path) -> None:
    (tmp_path / "x.mf4").write_bytes(b"MDF     4.10    ")
    code = ("import pathlib, sys\n"
            "from monitor.runtime.imports import without_mf4\n"
            "first = without_mf4()\n"
            "import can, importlib.util\n"
            "from monitor.bus.logfile import LogError, read_log\n"
            "try:\n"
            "    list(read_log(pathlib.Path(sys.argv[1])))\n"
            "except LogError as exc:\n"
            "    print(first, without_mf4(), importlib.util.find_spec('asammdf'), exc)\n")
    res = subprocess.run([sys.executable, "-c", code, str(tmp_path / "x.mf4")], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    first, again, spec, message = res.stdout.strip().split(" ", 3)
    assert (first, again, spec) == ("True", "False", "None")
    assert "asammdf" in message and "mf4" in message
