"""A user's files are never destroyed: no command writes an output onto one of its inputs
(the same path, a symbolic link or a hard link to it), and none replaces a file
motor-monitor did not write unless given --force.

Every case runs the real command line (`monitor.app.cli.main`, `sim_ecu.cli.main`) and reads
back what it did: the exit status, the one line on stderr and the input's bytes.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from monitor.app.cli import main
from monitor.diagnosis import load_thresholds
from monitor.runtime.paths import PNG_MAGIC, RIG_HEADER, Kind, is_own_file
from sim_ecu.cli import main as sim_ecu_main
from tests.archive.logs import ecu_frames, write_log
from tests.support.dbc import REPO_DBC
from tests.support.paths import ROOT

VIRTUAL = ("--interface", "virtual", "--channel", "outputs-never-inputs")
ECU = (*VIRTUAL, "--node", "0", "--scenario", "healthy", "--duration", "0.2")


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """A candump log of a node through fault, outage and recovery (diagnosis events)."""
    path = tmp_path_factory.mktemp("capture") / "cap.log"
    return write_log(path, ecu_frames(["fault-outage-recovery"])).read_bytes()


def _gamma_samples() -> str:
    rng = np.random.default_rng(3)
    values = np.concatenate([rng.normal(c, 0.02, 150) for c in (0.02, 0.5, 0.98)])
    return "\n".join(f"{v:.4f}" for v in np.clip(values, 0.0, 1.0)) + "\n"


@pytest.fixture
def work(tmp_path: Path, capture: bytes) -> Path:
    """The inputs every command reads: a capture, a rig with its DBC beside it, thresholds,
    a SecOC key, gamma^ samples and a scenario."""
    (tmp_path / "cap.log").write_bytes(capture)
    shutil.copy(REPO_DBC, tmp_path / "motor.dbc")
    rig = (ROOT / "rigs" / "motor.toml").read_text()
    assert 'dbc = "../dbc/motor.dbc"' in rig
    (tmp_path / "rig.toml").write_text(rig.replace("../dbc/motor.dbc", "motor.dbc"))
    (tmp_path / "thr.toml").write_text('quantity = "gamma"\nf1 = 0.2\nf2 = 0.8\n')
    key = tmp_path / "key"
    key.write_text(bytes(range(16)).hex() + "\n")
    key.chmod(0o600)
    (tmp_path / "gamma.txt").write_text(_gamma_samples())
    (tmp_path / "scenario.toml").write_text('name = "short"\nduration = 1.0\n')
    return tmp_path


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _run(argv: list[str], capsys: pytest.CaptureFixture[str], *,
         prog: str = "motor-monitor") -> tuple[int, list[str]]:
    """Exit status and the non-empty stderr lines of one command."""
    capsys.readouterr()
    code = sim_ecu_main(argv) if prog == "sim-ecu" else main(argv)
    return code, [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]


def _refused(code: int, lines: list[str], *expect: str, prog: str = "motor-monitor") -> str:
    assert code == 2, lines
    assert len(lines) == 1, lines
    line = lines[0]
    assert line.startswith(f"{prog}: error: "), line
    assert "Traceback" not in line and ".tmp" not in line, line
    for text in expect:
        assert text in line, (text, line)
    return line


# --- an output that is an input -------------------------------------------------------


@dataclass(frozen=True)
class Case:
    """A command whose output `out` lands on the input `victim`: `out` is the output's name
    in `argv` ("{out}"), or, for an output the command names itself (identify's report, the
    archive's files), the file it writes, with `argv` naming no output."""

    name: str
    argv: tuple[str, ...]
    victim: str
    out: str
    expect: tuple[str, ...]
    prog: str = "motor-monitor"

    @property
    def derived(self) -> bool:
        return "{out}" not in self.argv


CAP, RIG, THR, KEY = "{w}/cap.log", "{w}/rig.toml", "{w}/thr.toml", "{w}/key"
CASES = [
    # identify: RIG_OUT, and the report it writes beside it
    Case("identify --out = CAPTURE", ("identify", CAP, "--out", "{out}"), "cap.log",
         "learned.toml", ("--out", "CAPTURE", "cap.log")),
    Case("identify --out = --rig", ("identify", CAP, "--rig", RIG, "--out", "{out}"),
         "rig.toml", "learned.toml", ("--out", "--rig", "rig.toml")),
    Case("identify --out = the rig's DBC", ("identify", CAP, "--rig", RIG, "--out", "{out}"),
         "motor.dbc", "learned.toml", ("--out", "the DBC file of --rig", "motor.dbc")),
    Case("identify report JSON = CAPTURE",
         ("identify", CAP, "--out", "{w}/learned.toml"), "cap.log", "learned.identify.json",
         ("--out", "learned.identify.json", "CAPTURE")),
    Case("identify report PNG = --rig",
         ("identify", CAP, "--rig", RIG, "--out", "{w}/learned.toml"), "rig.toml",
         "learned.identify.png", ("--out", "learned.identify.png", "--rig")),
    # calibrate
    Case("calibrate --out = CAPTURE", ("calibrate", CAP, "--out", "{out}"), "cap.log",
         "th.toml", ("--out", "CAPTURE")),
    Case("calibrate --out = GAMMA_FILE", ("calibrate", "{w}/gamma.txt", "--out", "{out}"),
         "gamma.txt", "th.toml", ("--out", "GAMMA_FILE")),
    Case("calibrate --out = --rig", ("calibrate", CAP, "--rig", RIG, "--out", "{out}"),
         "rig.toml", "th.toml", ("--out", "--rig")),
    # replay of one log
    Case("replay --events = PATH", ("replay", CAP, "--events", "{out}"), "cap.log",
         "ev.jsonl", ("--events", "PATH")),
    Case("replay --rrd = PATH", ("replay", CAP, "--rrd", "{out}"), "cap.log", "rec.rrd",
         ("--rrd", "PATH")),
    Case("replay --events = --rig", ("replay", CAP, "--rig", RIG, "--events", "{out}"),
         "rig.toml", "ev.jsonl", ("--events", "--rig")),
    Case("replay --rrd = --thresholds", ("replay", CAP, "--thresholds", THR, "--rrd", "{out}"),
         "thr.toml", "rec.rrd", ("--rrd", "--thresholds")),
    Case("replay --events = --key", ("replay", CAP, "--key", KEY, "--events", "{out}"), "key",
         "ev.jsonl", ("--events", "--key")),
    Case("replay --rrd = --dbc", ("replay", CAP, "--dbc", "{w}/motor.dbc", "--rrd", "{out}"),
         "motor.dbc", "rec.rrd", ("--rrd", "--dbc")),
    # (named as the input itself, the suffix is refused first: .toml is no table)
    Case("replay --samples = --rig", ("replay", CAP, "--rig", RIG, "--samples", "{out}"),
         "rig.toml", "s.csv", ("--samples", "rig.toml")),
    # the archive replay: the files it names under --out DIR
    Case("replay --out DIR: a log's events = PATH", ("replay", CAP, "--out", "{w}/arch"),
         "cap.log", "arch/cap.log.events.jsonl", ("--out", "cap.log.events.jsonl", "PATH")),
    Case("replay --out DIR --rrd: a log's recording = PATH",
         ("replay", CAP, "--out", "{w}/arch", "--rrd"), "cap.log", "arch/cap.log.rrd",
         ("--out", "cap.log.rrd", "PATH")),
    Case("replay --out DIR: the summary = --rig",
         ("replay", CAP, "--rig", RIG, "--out", "{w}/arch"), "rig.toml", "arch/summary.csv",
         ("--out", "summary.csv", "--rig")),
    # run
    Case("run --events = --rig", ("run", *VIRTUAL, "--rig", RIG, "--events", "{out}"),
         "rig.toml", "ev.jsonl", ("--events", "--rig")),
    Case("run --rrd = --thresholds", ("run", *VIRTUAL, "--thresholds", THR, "--rrd", "{out}"),
         "thr.toml", "rec.rrd", ("--rrd", "--thresholds")),
    Case("run --metrics = --key", ("run", *VIRTUAL, "--key", KEY, "--metrics", "{out}"), "key",
         "m.prom", ("--metrics", "--key")),
    Case("run --secoc-state = --key",
         ("run", *VIRTUAL, "--key", KEY, "--secoc-state", "{out}"), "key", "state.json",
         ("--secoc-state", "--key")),
    Case("run --events = --dbc", ("run", *VIRTUAL, "--dbc", "{w}/motor.dbc", "--events",
                                  "{out}"), "motor.dbc", "ev.jsonl", ("--events", "--dbc")),
    # sim-ecu
    Case("sim-ecu --secoc-state = --key", (*ECU, "--key", KEY, "--secoc-state", "{out}"),
         "key", "state.json", ("--secoc-state", "--key"), prog="sim-ecu"),
    Case("sim-ecu --secoc-state = --scenario",
         (*VIRTUAL, "--node", "0", "--scenario", "{w}/scenario.toml", "--key", KEY,
          "--secoc-state", "{out}"), "scenario.toml", "state.json",
         ("--secoc-state", "--scenario"), prog="sim-ecu"),
    Case("sim-ecu --secoc-state = the rig's DBC",
         (*ECU, "--rig", RIG, "--key", KEY, "--secoc-state", "{out}"), "motor.dbc",
         "state.json", ("--secoc-state", "the DBC file of --rig"), prog="sim-ecu"),
]


def _alias(target: Path, how: str, at: Path) -> Path:
    """The output's path: `target` itself, or a symbolic or hard link to it at `at`."""
    if how == "same":
        return target
    at.parent.mkdir(parents=True, exist_ok=True)
    if how == "symlink":
        at.symlink_to(target)
    else:
        at.hardlink_to(target)
    return at


@pytest.mark.parametrize("how", ["same", "symlink", "hardlink"])
@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_an_output_never_lands_on_an_input(case: Case, how: str, work: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    if case.derived and how == "same":
        pytest.skip("the command names this output itself: only a link can be an input")
    victim = work / case.victim
    before = _digest(victim)
    out = _alias(victim, how, work / case.out)
    argv = [a.format(w=work, out=out) for a in case.argv]
    code, lines = _run(argv, capsys, prog=case.prog)
    _refused(code, lines, *case.expect, prog=case.prog)
    assert victim.is_file() and not victim.is_symlink()
    assert _digest(victim) == before
    if how == "symlink":
        assert out.is_symlink() and out.resolve() == victim.resolve()


def test_two_outputs_are_never_one_file(work: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, lines = _run(["replay", str(work / "cap.log"), "--events", str(work / "x.out"),
                        "--rrd", str(work / "x.out")], capsys)
    _refused(code, lines, "--events", "--rrd", "same file")
    assert not (work / "x.out").exists()
    code, lines = _run(["run", *VIRTUAL, "--key", str(work / "key"), "--events",
                        str(work / "o.jsonl"), "--secoc-state", str(work / "o.jsonl")], capsys)
    _refused(code, lines, "--events", "--secoc-state")


def test_an_input_named_like_a_rotated_file_is_not_in_the_rotation(
        work: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--raw-dir and --record-dir delete their oldest rotated files: an input there, named
    like one of them, would be deleted."""
    rig = work / "bus-20240101T000000-0001.toml"
    shutil.copy(work / "rig.toml", rig)
    before = _digest(rig)
    for option in ("--raw-dir", "--record-dir"):
        code, lines = _run(["run", *VIRTUAL, "--rig", str(rig), option, str(work)], capsys)
        _refused(code, lines, option, "--rig", rig.name)
    assert _digest(rig) == before


# --- where an output may go ---------------------------------------------------------------


def test_a_directory_or_a_missing_directory_is_refused_before_any_work(
        work: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, lines = _run(["identify", str(work / "cap.log"), "--out", str(work)], capsys)
    _refused(code, lines, "--out", "is a directory")
    code, lines = _run(["calibrate", str(work / "gamma.txt"), "--out", str(work)], capsys)
    _refused(code, lines, "--out", "is a directory")
    missing = work / "nodir" / "th.toml"
    code, lines = _run(["calibrate", str(work / "gamma.txt"), "--out", str(missing)], capsys)
    _refused(code, lines, "--out", "nodir", "does not exist")
    code, lines = _run(["identify", str(work / "cap.log"), "--out",
                        str(work / "cap.log" / "x.toml")], capsys)
    _refused(code, lines, "--out", "cap.log is not a directory")
    code, lines = _run(["calibrate", str(work / "gamma.txt"), "--out",
                        str(work / "cap.log" / "sub" / "x.toml")], capsys)
    _refused(code, lines, "--out", "cap.log is not a directory")
    code, lines = _run(["replay", str(work / "cap.log"), "--out", str(work / "cap.log")], capsys)
    _refused(code, lines, "--out", "not a directory")
    # an output directory below a file: the file in the way is named, as for a file output
    code, lines = _run(["replay", str(work / "cap.log"), "--out", str(work / "cap.log" / "d")],
                       capsys)
    _refused(code, lines, "--out", "cap.log is not a directory")
    code, lines = _run(["run", *VIRTUAL, "--record-dir", str(work / "cap.log" / "d")], capsys)
    _refused(code, lines, "--record-dir", "cap.log is not a directory")


def test_a_write_that_fails_names_the_users_file(work: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """/proc takes no new file (not even root's): the error names --out's file, not the
    temporary file beside it."""
    code, lines = _run(["calibrate", str(work / "gamma.txt"), "--out", "/proc/th.toml"], capsys)
    _refused(code, lines, "/proc/th.toml")
    assert not Path("/proc/th.toml").exists()


# --- files motor-monitor wrote, and files it did not --------------------------------------


def test_own_files_are_replaced_without_force(work: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    th, ev, rrd = work / "th.toml", work / "ev.jsonl", work / "rec.rrd"
    replay = ["replay", str(work / "cap.log"), "--events", str(ev), "--rrd", str(rrd)]
    runs = []
    for _ in range(2):
        assert _run(["calibrate", str(work / "gamma.txt"), "--out", str(th)], capsys)[0] == 0
        load_thresholds(th)
        assert _run(replay, capsys)[0] == 0
        runs.append(ev.read_text().splitlines())
        assert rrd.read_bytes()[:4] == b"RRF2"
    events = runs[0]
    assert len(events) >= 2  # fault and outage at least
    assert runs[1] == events  # replaced, not appended to
    out = work / "arch"
    archive = ["replay", str(work / "cap.log"), "--out", str(out), "--rrd"]
    assert _run(archive, capsys)[0] == 0
    assert _run(archive, capsys)[0] == 0
    assert (out / "cap.log.events.jsonl").read_text().splitlines() == events


def _foreign(path: Path) -> str:
    path.write_text("my notes\nkeep them\n")
    return _digest(path)


FOREIGN = [
    ("calibrate", lambda w, o: ["calibrate", f"{w}/gamma.txt", "--out", o], "th.toml",
     "replace"),
    ("replay --events", lambda w, o: ["replay", f"{w}/cap.log", "--events", o], "ev.jsonl",
     "replace"),
    ("replay --rrd", lambda w, o: ["replay", f"{w}/cap.log", "--rrd", o], "rec.rrd", "replace"),
    ("replay --out DIR", lambda w, o: ["replay", f"{w}/cap.log", "--out", str(Path(o).parent)],
     "arch/summary.csv", "replace"),
    ("run --events", lambda w, o: ["run", *VIRTUAL, "--events", o], "ev.jsonl", "append to"),
    ("run --metrics", lambda w, o: ["run", *VIRTUAL, "--metrics", o], "m.prom", "replace"),
    ("identify --out", lambda w, o: ["identify", f"{w}/cap.log", "--out", o], "learned.toml",
     "replace"),
]


@pytest.mark.parametrize(("argv", "name", "how"), [c[1:] for c in FOREIGN],
                         ids=[c[0] for c in FOREIGN])
def test_a_foreign_file_is_written_over_only_with_force(
        argv: Callable[[Path, str], list[str]], name: str, how: str, work: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    path = work / name
    path.parent.mkdir(exist_ok=True)
    before = _foreign(path)
    code, lines = _run(argv(work, str(path)), capsys)
    _refused(code, lines, name, "was not written by motor-monitor", f"--force to {how} it")
    assert _digest(path) == before


def test_force_replaces_a_foreign_file(work: Path, capsys: pytest.CaptureFixture[str]) -> None:
    th, ev = work / "th.toml", work / "ev.jsonl"
    _foreign(th)
    _foreign(ev)
    calibrate = ["calibrate", str(work / "gamma.txt"), "--out", str(th)]
    assert _run([*calibrate, "--force"], capsys)[0] == 0
    load_thresholds(th)
    replay = ["replay", str(work / "cap.log"), "--events", str(ev)]
    assert _run([*replay, "--force"], capsys)[0] == 0
    assert "my notes" not in ev.read_text()
    # once motor-monitor has written them, they are its own
    assert _run(calibrate, capsys)[0] == 0
    assert _run(replay, capsys)[0] == 0


def test_identify_replaces_its_own_files_and_no_other(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A rig, report and plot identify wrote are replaced without --force (each atomically,
    the new rig loading); the same names written by someone else are refused before the
    captures are read."""
    from tests.support.identify import PRESS, press_capture

    cap = press_capture(tmp_path / "press.log")
    out = tmp_path / "learned.toml"
    report, png = out.with_suffix(".identify.json"), out.with_suffix(".identify.png")
    argv = ["identify", str(cap), "--rig", str(PRESS), "--node", "1", "--out", str(out)]
    report.write_text(json.dumps({"capture": {"files": ["old.log"]}}))
    for name, foreign in ((out, "[bus]\n# my rig\n"), (png, "not a picture")):
        name.write_text(foreign)
        code, lines = _run(argv, capsys)
        _refused(code, lines, name.name, "--force")
        assert name.read_text() == foreign
        name.unlink()
    out.write_text(f"{RIG_HEADER} from old.log (node 1)\n[bus]\n")
    png.write_bytes(PNG_MAGIC + b"\x00\x00\x00\rIHDR" + b"\x00" * 17 + b"tEXtSoftware\x00"
                    b"Matplotlib version3")
    out.chmod(0o644)
    code, lines = _run(argv, capsys)
    assert code == 0, lines
    assert out.read_text().startswith(RIG_HEADER + " from press.log (node 1)")
    assert out.stat().st_mode & 0o777 == 0o644  # the replaced file's permissions
    assert json.loads(report.read_text())["capture"]["files"] == [str(cap)]
    assert not list(tmp_path.glob(".*.tmp*"))


def test_calibrate_help_shows_where_it_writes(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", "--help"])
    assert exc.value.code == 0
    help_text = " ".join(capsys.readouterr().out.split())
    assert "default: thresholds.toml" in help_text
    assert "--force" in help_text


# --- how motor-monitor recognises its own files -------------------------------------------


def test_own_event_lines_are_recognised_by_their_first_and_last_line(tmp_path: Path) -> None:
    line = json.dumps({"t": 1.0, "node": 0, "state": "fault", "previous": "fault_free",
                       "gamma": 0.5, "fault_input": 1.0, "rules": 3, "cause": "estimate",
                       "model_mismatch": False, "kind": "health", "fault_input_unit": "A"})
    ev = tmp_path / "ev.jsonl"
    ev.write_text("")
    assert is_own_file(ev, "events")  # nothing to lose
    # an older monitor's lines: the fault as `fault_volts`, with and without the flag
    older = {"t": 1.0, "node": 0, "state": "fault", "previous": "fault_free", "gamma": 0.5,
             "fault_volts": 1.0, "rules": 3, "cause": "estimate"}
    for doc in (older, {**older, "model_mismatch": False, "kind": "health"}):
        ev.write_text(f"{json.dumps(doc)}\n{line}\n")
        assert is_own_file(ev, "events")
    ev.write_text(f"{line}\n{line}\n")
    assert is_own_file(ev, "events")
    ev.write_text(f"{line}\n{line}\n{line[:20]}")  # a last line cut short by a kill
    assert is_own_file(ev, "events")
    ev.write_text(f"{line}\n" + '{"t": 1.0}\n')
    assert not is_own_file(ev, "events")
    ev.write_text("0.1\n0.2\n")
    assert not is_own_file(ev, "events")
    assert not is_own_file(tmp_path / "missing", "events")


def test_own_recordings_plots_and_headers_are_recognised(tmp_path: Path) -> None:
    f = tmp_path / "f"
    cases: list[tuple[bytes, Kind, bool]] = [
        (b"RRF2\x00)\x00\x00\x01\x02\x00\x00", "rrd", True),
        (b"1700000000.0 vcan0 123#00\n", "rrd", False),
        (f"{RIG_HEADER} from cap.log (node 0)\n[bus]\n".encode(), "rig", True),
        (b"[bus]\ndbc = 'x.dbc'\n", "rig", False),
        (b"# motor-monitor diagnosis thresholds, eq (76)\nf1 = 0.1\n", "thresholds", True),
        (b'quantity = "gamma"\n', "thresholds", False),
        (b"# HELP motor_monitor_up 1 while the monitor runs\n", "metrics", True),
        (b"# HELP node_load1 load\n", "metrics", False),
        (PNG_MAGIC + b"\x00" * 20 + b"Matplotlib version", "png", True),
        (PNG_MAGIC + b"\x00" * 20 + b"GIMP", "png", False),
    ]
    for data, kind, ours in cases:
        f.write_bytes(data)
        assert is_own_file(f, kind) is ours, (data, kind)
