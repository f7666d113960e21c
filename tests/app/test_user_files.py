"""No file a user hands over crashes, hangs or exhausts the monitor (issue 17).

Every file named on a command line or in a rig (--rig, --thresholds, --key, --dbc, a rig's
bus.dbc, `status FILE.prom`, a `calibrate` gamma^ file, a `sim-ecu --scenario` file) is
handed over as a FIFO, a device, a directory, a symbolic link loop, a path too long for the
file system, a file over the size limit of its kind, and binary content. Each must end in
exactly one stderr line ``<program>: error: ...`` naming the file's option or key, the path
and what it is, exit status 2, within seconds, and leave the input as it was.

FIFOs run the real programs in subprocesses, killed after a timeout: opening a FIFO for
reading blocks until a writer comes, and a hang must fail the test, not stall it. The
other kinds call the command lines' `main` in this process, under an alarm.
"""

from __future__ import annotations

import io
import os
import signal
import stat
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, redirect_stderr
from dataclasses import dataclass
from pathlib import Path

import cantools
import pytest

import sim_ecu.cli
from monitor.app import cli
from monitor.app.calibrate import GAMMA_FILE_LIMIT
from monitor.app.status import METRICS_FILE_LIMIT
from monitor.bus.codec import DBC_FILE_LIMIT, load_dbcs
from monitor.diagnosis import DiagnosisError, load_thresholds
from monitor.diagnosis.thresholds import THRESHOLDS_FILE_LIMIT
from monitor.errors import ERROR_LINE_LIMIT
from monitor.files import KIB, read_user_file, shown_path
from monitor.rig.load import RIG_FILE_LIMIT
from sim_ecu.scenario import SCENARIO_FILE_LIMIT
from tests.support import BIN
from tests.support.dbc import REPO_DBC
from tests.support.paths import ROOT

RUN = ["run", "--interface", "virtual", "--channel", "user-files"]
ECU = ["--node", "0", "--interface", "virtual", "--channel", "user-files", "--duration", "0.1"]
KEY_FILE_LIMIT = 4 * KIB  # monitor.bus.secoc.keys: a key file is 64 hex digits at most
SECONDS = 60  # a refusal takes well under a second; a hang or a read of /dev/zero never ends


@dataclass(frozen=True)
class Option:
    """A way a file reaches a program: its command line given the file's path (and the
    test's directory), the words naming it in the error line, its size limit."""

    name: str
    program: str  # "motor-monitor" or "sim-ecu"
    argv: Callable[[str, Path], list[str]]
    named: str
    limit: int
    binary: str  # what the error line says of binary content
    mode: int = 0o644
    suffix: str = ""


def _rig_naming(dbc: str, tmp: Path) -> Path:
    """A copy of the example rig whose bus.dbc is `dbc` (an absolute path)."""
    text = (ROOT / "rigs" / "motor.toml").read_text(encoding="utf-8")
    old = 'dbc = "../dbc/motor.dbc"'
    assert old in text
    rig = tmp / "with-dbc.toml"
    rig.write_text(text.replace(old, f"dbc = {dbc!r}".replace("'", '"')), encoding="utf-8")
    return rig


OPTIONS = [
    Option("rig", "motor-monitor", lambda p, _: [*RUN, "--rig", p], "rig file", RIG_FILE_LIMIT,
           "not UTF-8 text", suffix=".toml"),
    Option("thresholds", "motor-monitor", lambda p, _: [*RUN, "--thresholds", p],
           "thresholds file", THRESHOLDS_FILE_LIMIT, "not UTF-8 text", suffix=".toml"),
    Option("key", "motor-monitor", lambda p, _: [*RUN, "--key", p], "key", KEY_FILE_LIMIT,
           "not an AES key", mode=0o600),
    Option("dbc", "motor-monitor", lambda p, _: [*RUN, "--dbc", p], "DBC file", DBC_FILE_LIMIT,
           "not a valid DBC", suffix=".dbc"),
    Option("rig-dbc", "motor-monitor",
           lambda p, tmp: [*RUN, "--rig", str(_rig_naming(p, tmp))],
           "bus.dbc", DBC_FILE_LIMIT, "not a valid DBC", suffix=".dbc"),
    Option("status", "motor-monitor", lambda p, _: ["status", p], "metrics file",
           METRICS_FILE_LIMIT, "not UTF-8 text", suffix=".prom"),
    Option("gamma", "motor-monitor", lambda p, tmp: ["calibrate", p, "--out",
                                                     str(tmp / "out.toml")],
           "gamma^ file", GAMMA_FILE_LIMIT, "not UTF-8 text", suffix=".txt"),
    Option("scenario", "sim-ecu", lambda p, _: [*ECU, "--scenario", p], "scenario file",
           SCENARIO_FILE_LIMIT, "not UTF-8 text", suffix=".toml"),
]
BINARY = bytes(range(256)) * 4  # NUL bytes and bytes that are no UTF-8

KINDS = {
    "fifo": "is a FIFO (named pipe), not a regular file",
    "device": "is a character device, not a regular file",
    "directory": "is a directory, not a regular file",
    "symlink-loop": "a loop of symbolic links",
    "too-long": "the path is too long for the file system",
    "huge": "more than the",
    "binary": "",  # the option's own words
}


def _make(kind: str, option: Option, tmp: Path) -> Path:
    """The file of `kind` for `option`, under `tmp`."""
    path = tmp / f"input{option.suffix}"
    if kind == "fifo":
        os.mkfifo(path, option.mode)
    elif kind == "device":
        path = Path("/dev/zero")
    elif kind == "directory":
        path.mkdir(mode=0o700)
    elif kind == "symlink-loop":
        os.symlink(path.name, path)
    elif kind == "too-long":
        path = tmp / ("x" * 300 + option.suffix)  # NAME_MAX is 255
    elif kind == "huge":  # sparse: no disk is used
        path.write_bytes(b"")
        os.truncate(path, option.limit + 1)
        path.chmod(option.mode)
    elif kind == "binary":
        path.write_bytes(BINARY)
        path.chmod(option.mode)
    return path


def _state(path: Path) -> tuple[int, int, bytes | None]:
    """What the test checks is unchanged: file type and mode, size, and the bytes of a
    regular file of a reasonable size."""
    try:
        st = os.lstat(path)
    except OSError as exc:
        return (-1, exc.errno or 0, None)
    small = stat.S_ISREG(st.st_mode) and st.st_size < 1 << 20
    return (st.st_mode, st.st_size, path.read_bytes() if small else None)


@contextmanager
def _deadline(seconds: int) -> Iterator[None]:
    """Raise in this (the main) thread if the body runs for more than `seconds`."""

    def expire(signum: int, frame: object) -> None:
        raise TimeoutError(f"still running after {seconds} s")

    old = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def _main(program: str, argv: list[str], cwd: Path) -> tuple[int, list[str]]:
    """(exit status, stderr lines) of the program's `main`, run in this process."""
    err = io.StringIO()
    main = cli.main if program == "motor-monitor" else sim_ecu.cli.main
    here = os.getcwd()
    os.chdir(cwd)
    try:
        with _deadline(SECONDS), redirect_stderr(err):
            try:
                code = main(argv)
            except SystemExit as exc:  # argparse
                code = exc.code if isinstance(exc.code, int) else 2
    finally:
        os.chdir(here)
    return code, [ln for ln in err.getvalue().splitlines() if ln.strip()]


def _subprocess(program: str, argv: list[str], cwd: Path) -> tuple[int, list[str]]:
    """(exit status, stderr lines) of the installed program; fails if it runs on."""
    start = time.monotonic()
    try:
        res = subprocess.run([str(BIN / program), *argv], cwd=cwd, capture_output=True,
                             text=True, timeout=SECONDS, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        pytest.fail(f"{program} {' '.join(argv)} still running after {SECONDS} s")
    assert time.monotonic() - start < SECONDS
    return res.returncode, [ln for ln in res.stderr.splitlines() if ln.strip()]


@pytest.mark.parametrize("kind", list(KINDS))
@pytest.mark.parametrize("option", OPTIONS, ids=[o.name for o in OPTIONS])
def test_a_file_that_cannot_serve_is_one_line(tmp_path: Path, option: Option, kind: str
                                              ) -> None:
    path = _make(kind, option, tmp_path)
    before = _state(path)
    argv = option.argv(str(path), tmp_path)
    run = _subprocess if kind == "fifo" else _main
    code, lines = run(option.program, argv, tmp_path)
    assert code == 2, lines
    assert len(lines) == 1, lines
    (line,) = lines
    assert line.startswith(f"{option.program}: error: "), line
    assert "Traceback" not in line
    assert option.named in line, line
    assert shown_path(path) in line, line
    assert (KINDS[kind] or option.binary) in line, line
    assert _state(path) == before


# ----------------------------------------------------------------------------- status


STATUS_FIXTURE = """\
# TYPE motor_monitor_up gauge
motor_monitor_up 1.0
# TYPE motor_monitor_last_write_timestamp_seconds gauge
motor_monitor_last_write_timestamp_seconds 1.7e+09
# TYPE motor_monitor_events_total counter
motor_monitor_events_total{name="bus/error_frames"} 2.0
motor_monitor_events_total{name="bus/socket_drops"} 5.0
motor_monitor_events_total{name="e2e/lost_frames"} 3.0
motor_monitor_events_total{name="frames/received"} 3520.0
motor_monitor_events_total{name="publish/sent"} 40.0
motor_monitor_events_total{name="rejected/crc"} 4.0
motor_monitor_events_total{name="rejected/counter"} 1.0
# TYPE motor_monitor_node_health_state gauge
motor_monitor_node_health_state{node="0"} 0.0
motor_monitor_node_health_state{node="10"} 1.0
motor_monitor_node_health_state{node="2"} 1.0
motor_monitor_node_health_state{node="3"} 3.0
motor_monitor_node_health_state{node="7"} 2.0
# TYPE motor_monitor_node_model_mismatch gauge
motor_monitor_node_model_mismatch{node="0"} 0.0
motor_monitor_node_model_mismatch{node="10"} 1.0
motor_monitor_node_model_mismatch{node="2"} 0.0
motor_monitor_node_model_mismatch{node="7"} 0.0
# TYPE motor_monitor_node_gamma gauge
motor_monitor_node_gamma{node="0"} 0.0123
motor_monitor_node_gamma{node="10"} 0.5
motor_monitor_node_gamma{node="2"} 0.41
motor_monitor_node_gamma{node="7"} 0.97
# TYPE motor_monitor_node_nis gauge
motor_monitor_node_nis{node="0"} 1.0404131431603534
motor_monitor_node_nis{node="10"} 31.5
motor_monitor_node_nis{node="2"} 0.9
# TYPE motor_monitor_node_output_noise_factor gauge
motor_monitor_node_output_noise_factor{node="0",output="Speed"} 1.0412
motor_monitor_node_output_noise_factor{node="0",output="Position"} 1.2749
motor_monitor_node_output_noise_factor{node="10",output="Speed"} 3.21
# TYPE motor_monitor_node_process_noise_factor gauge
motor_monitor_node_process_noise_factor{node="0"} 1.0
motor_monitor_node_process_noise_factor{node="10"} 41.73
# TYPE motor_monitor_node_samples_total counter
motor_monitor_node_samples_total{node="0"} 1599.0
motor_monitor_node_samples_total{node="10"} 12.0
motor_monitor_node_samples_total{node="2"} 800.0
motor_monitor_node_samples_total{node="7"} 3.0
# TYPE motor_monitor_bus_load_ratio gauge
motor_monitor_bus_load_ratio 0.05939999999999989
# TYPE motor_monitor_bus_frames_total counter
motor_monitor_bus_frames_total 3530.0
# TYPE motor_monitor_id_frames_total counter
motor_monitor_id_frames_total{id="0x110"} 1600.0
motor_monitor_id_frames_total{id="0x120"} 320.0
motor_monitor_id_frames_total{id="0x18FF0012"} 55.0
# TYPE motor_monitor_id_period_seconds gauge
motor_monitor_id_period_seconds{id="0x110"} 0.010000000005964207
motor_monitor_id_period_seconds{id="0x120"} 0.05000000014947872
# TYPE motor_monitor_id_jitter_seconds gauge
motor_monitor_id_jitter_seconds{id="0x110"} 1.5e-06
motor_monitor_id_jitter_seconds{id="0x120"} 2.25e-05
# TYPE motor_monitor_estimation_latency_seconds histogram
motor_monitor_estimation_latency_seconds_bucket{le="0.001"} 2400.0
motor_monitor_estimation_latency_seconds_bucket{le="+Inf"} 2411.0
motor_monitor_estimation_latency_seconds_count 2411.0
motor_monitor_estimation_latency_seconds_sum 1.2055
"""

# what `status` prints for STATUS_FIXTURE (the file's own write time makes the age; the path
# is printed as given; the noise factors: the noisiest output's, "-" for a node the file
# has none of, as a file of a monitor from before them)
STATUS_TABLE = """\
monitor.prom (written {age} s ago)
bus load 5.9 %, 3530 frames, 2 error frames, 5 kernel drops, 5 rejected, 3 lost, 40 diagnoses sent

node  state       mismatch  gamma^     NIS  noise x process x   samples
   0  fault_free  no         0.012    1.04     1.27         1      1599
   2  fault       no         0.410    0.90        -         -       800
   3  no_data     -            nan     nan        -         -         0
   7  outage      no         0.970     nan        -         -         3
  10  fault       yes        0.500   31.50     3.21      41.7        12

        id    frames  period ms  jitter ms
     0x110      1600      10.00      0.002
     0x120       320      50.00      0.023
0x18FF0012        55        nan        nan

estimation latency: mean 0.50 ms over 2411 samples
"""


def _status_file(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "monitor.prom"
    path.write_text(text, encoding="utf-8")
    return path


def test_status_renders_a_monitor_file_as_before(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    written = time.time() - 42
    _status_file(tmp_path, STATUS_FIXTURE.replace("1.7e+09", repr(written)))
    here = os.getcwd()
    os.chdir(tmp_path)
    try:
        assert cli.main(["status", "monitor.prom"]) == 0
    finally:
        os.chdir(here)
    out = capsys.readouterr().out
    age = out.split("(written ", 1)[1].split(" s ago", 1)[0]
    assert 42 <= int(age) <= 42 + SECONDS
    assert out == STATUS_TABLE.format(age=age)


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("", "no metrics in it; is the monitor running with --metrics?"),
        ("# nothing but a comment\n\n", "no metrics in it"),
        ('motor_monitor_node_health_state{node="0"} NaN\n', "is nan, not a health state"),
        ('motor_monitor_node_health_state{node="0"} +Inf\n', "is inf, not a health state"),
        ('motor_monitor_node_health_state{node="0"} -Inf\n', "is -inf, not a health state"),
        ('motor_monitor_node_health_state{node="0"} 9\n', "is 9.0, not a health state"),
        ('motor_monitor_node_health_state{node="0"} 1.5\n', "is 1.5, not a health state"),
        ('motor_monitor_node_health_state{node="0"} 4\n', "is 4.0, not a health state (0 to 3)"),
        ('motor_monitor_node_model_mismatch{node="0"} 2\n', "is 2.0, not 0 or 1"),
        ("motor_monitor_node_health_state 1\n", "has no 'node' label"),
        ('motor_monitor_node_health_state{node="abc"} 1\n', "node='abc' is not a node number"),
        ('motor_monitor_node_gamma{node="1e9"} 1\n', "is not a node number"),
        ('motor_monitor_node_nis{id="0x1"} 1\n', "has no 'node' label"),
        ('motor_monitor_id_frames_total{id="zz"} 1\n', "id='zz' is not a CAN ID"),
        ('motor_monitor_id_frames_total{id="0x1"} 1\nmotor_monitor_id_period_seconds 1\n',
         "has no 'id' label"),
        ("motor_monitor_events_total 1\n", "has no 'name' label"),
        ("motor_monitor_up {\n", "not Prometheus text"),
        ('motor_monitor_node_health_state{node="' + "9" * 100_000 + '"} 1\n',
         "is not a node number"),
    ],
    ids=["empty", "comment", "nan", "inf", "-inf", "nine", "fraction", "four", "flag-two",
         "no-node",
         "node-text", "node-float", "nis-no-node", "id-text", "period-no-id", "no-name",
         "not-prometheus", "node-huge"],
)
def test_status_of_a_file_the_monitor_never_writes_is_one_line(tmp_path: Path, text: str,
                                                               needle: str) -> None:
    path = _status_file(tmp_path, text)
    code, lines = _main("motor-monitor", ["status", str(path)], tmp_path)
    assert code == 2 and len(lines) == 1, lines
    assert lines[0].startswith(f"motor-monitor: error: metrics file {path}: "), lines
    assert needle in lines[0], lines
    assert len(lines[0]) < 400


@pytest.mark.parametrize("watch", ["-1", "0", "nan", "inf", "-inf", "soon"])
def test_status_watch_must_be_a_positive_finite_number(tmp_path: Path, watch: str) -> None:
    path = _status_file(tmp_path, STATUS_FIXTURE)
    code, lines = _main("motor-monitor", ["status", str(path), f"--watch={watch}"], tmp_path)
    assert code == 2 and len(lines) == 1, lines
    assert "argument --watch:" in lines[0] and repr(watch) in lines[0], lines


def test_status_watch_shows_a_vanished_file_and_goes_on(tmp_path: Path) -> None:
    """--watch keeps watching through a file that is missing for a while (the daemon
    restarting): the error takes the table's place, and the table comes back."""
    path = _status_file(tmp_path, STATUS_FIXTURE)
    proc = subprocess.Popen([str(BIN / "motor-monitor"), "status", str(path), "--watch",
                             "0.1"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            stdin=subprocess.DEVNULL)
    out = bytearray()

    def pump() -> None:
        assert proc.stdout is not None
        while chunk := os.read(proc.stdout.fileno(), 65536):
            out.extend(chunk)

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()

    def wait_for(text: bytes, after: int) -> int:
        deadline = time.monotonic() + SECONDS
        while time.monotonic() < deadline:
            at = bytes(out).find(text, after)
            if at >= 0:
                return at + len(text)
            assert proc.poll() is None, (proc.returncode, bytes(out)[-500:])
            time.sleep(0.05)
        pytest.fail(f"no {text!r} after {SECONDS} s: {bytes(out)[-500:]!r}")

    try:
        seen = wait_for(b"  10  fault       yes", 0)
        path.unlink()
        seen = wait_for(f"metrics file {path}: no such file".encode(), seen)
        seen = wait_for(b"trying again every 0.1 s", seen)
        _status_file(tmp_path, STATUS_FIXTURE)
        wait_for(b"  10  fault       yes", seen)
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=SECONDS)
        reader.join(timeout=SECONDS)
    assert b"Traceback" not in err, err


def test_status_watch_refuses_a_file_it_cannot_show_at_the_start(tmp_path: Path) -> None:
    code, lines = _main("motor-monitor", ["status", str(tmp_path / "no.prom"), "--watch",
                                          "0.1"], tmp_path)
    assert code == 2 and len(lines) == 1, lines
    assert "no such file; is the monitor running with --metrics?" in lines[0], lines


# ----------------------------------------------------------------------------- thresholds


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ('quantity = "gamma"\nf1 = 1e400\nf2 = 0.5\n', "f1 must be finite, got inf"),
        ('quantity = "gamma"\nf1 = 0.1\nf2 = ' + "9" * 400 + "\n",
         "f2 must be finite, got an integer too large"),
        ('quantity = "gamma"\nf1 = 0.1\nf2 = ' + "9" * 5000 + "\n", "not valid TOML"),
        ('quantity = "' + "q" * 50_000 + '"\nf1 = 0.1\nf2 = 0.5\n',
         "thresholds are for quantity 'qqq"),
        ('quantity = "gamma"\nf1 = 0.1\nf2 = 0.5\nx = ' + "{a = " * 3000 + "1"
         + "}" * 3000 + "\n", "not valid TOML: nested too deeply"),
        ('quantity = "gamma"\nf1 = 0.1\nf2 = 0.5\n\x00\n', "not text (a NUL byte"),
    ],
    ids=["inf", "huge-int", "thousands-of-digits", "huge-quantity", "deep", "nul"],
)
def test_absurd_thresholds_are_one_short_line(tmp_path: Path, text: str, needle: str) -> None:
    path = tmp_path / "t.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(DiagnosisError) as info:
        load_thresholds(path)
    message = str(info.value)
    assert "\n" not in message and message.startswith(f"thresholds file {path}: "), message
    assert needle in message, message
    assert len(message) <= 500


# ----------------------------------------------------------------------------- DBC decoding


def test_a_dbc_is_decoded_as_cantools_reads_a_file(tmp_path: Path) -> None:
    """cp1252 (a degree sign, a byte cp1252 lacks) and CRLF line ends read as cantools'
    own add_dbc_file reads them."""
    text = REPO_DBC.read_bytes().replace(b"\n", b"\r\n")
    assert b' "A" ' in text
    text = text.replace(b' "A" ', b' "\xb0A\x81" ', 1)
    path = tmp_path / "cp1252.dbc"
    path.write_bytes(text)
    ours = load_dbcs([path])
    theirs = cantools.database.can.Database(strict=True)
    theirs.add_dbc_file(str(path))
    units = [(m.name, s.name, s.unit) for m in ours.messages for s in m.signals]
    assert units == [(m.name, s.name, s.unit) for m in theirs.messages for s in m.signals]
    assert any(u == "\u00b0A\ufffd" for _, _, u in units)
    assert path.read_bytes() == text


# ----------------------------------------------------------------------------- calibrate


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("", "no gamma^ samples in it"),
        ("# gamma^\n\n   \n", "no gamma^ samples in it"),
        ("0.1\n0.2\nnan\n", "line 3: gamma^ must be a finite number, got nan"),
        ("# c\n0.1,x\n\n1e999\n", "line 4: gamma^ must be a finite number, got inf"),
        ("0.1\n-inf, 3\n", "line 2: gamma^ must be a finite number, got -inf"),
        ("0.1\n0.2\nabc\n", "line 3: 'abc' is not a number"),
        ("0.1\n,0.2\n", "line 2: '' is not a number"),
    ],
    ids=["empty", "comments", "nan", "inf", "-inf", "text", "empty-column"],
)
def test_a_gamma_file_without_finite_samples_is_one_line(tmp_path: Path, text: str,
                                                         needle: str) -> None:
    path = tmp_path / "gamma.txt"
    path.write_text(text, encoding="utf-8")
    out = tmp_path / "th.toml"
    code, lines = _main("motor-monitor", ["calibrate", str(path), "--out", str(out)], tmp_path)
    assert code == 2 and len(lines) == 1, lines
    assert lines[0].startswith(f"motor-monitor: error: gamma^ file {path}: "), lines
    assert needle in lines[0], lines
    assert not out.exists()


# ----------------------------------------------------------------------------- one line


def test_a_huge_value_echoed_back_is_cut(tmp_path: Path) -> None:
    """A signal name of a megabyte in a rig: the one error line stays short."""
    text = (ROOT / "rigs" / "motor.toml").read_text(encoding="utf-8")
    old = 'signal = "ArmatureCurrent"'
    assert old in text
    rig = tmp_path / "rig.toml"
    rig.write_text(text.replace(old, f'signal = "{"S" * 1_000_000}"').replace(
        "../dbc/motor.dbc", str(REPO_DBC)), encoding="utf-8")
    code, lines = _main("motor-monitor", [*RUN, "--rig", str(rig)], tmp_path)
    assert code == 2 and len(lines) == 1, [ln[:200] for ln in lines]
    assert lines[0].startswith(f"motor-monitor: error: rig file {rig}: signals.outputs[0]")
    assert len(lines[0]) <= len("motor-monitor: error: ") + ERROR_LINE_LIMIT


def test_a_huge_scenario_value_is_one_short_line(tmp_path: Path) -> None:
    path = tmp_path / "s.toml"
    path.write_text(f'name = "{"n" * 100_000}"\nduration = {"9" * 400}\n', encoding="utf-8")
    code, lines = _main("sim-ecu", [*ECU, "--scenario", str(path)], tmp_path)
    assert code == 2 and len(lines) == 1, [ln[:200] for ln in lines]
    assert lines[0].startswith(f"sim-ecu: error: scenario file {path}: "), lines[0][:200]
    assert len(lines[0]) <= len("sim-ecu: error: ") + ERROR_LINE_LIMIT


# ----------------------------------------------------------------------------- the reader


def test_read_user_file_checks_the_open_file_before_reading(tmp_path: Path) -> None:
    """The `check` hook sees the opened file's status before a byte is read, and its
    exception passes unchanged; the limit is inclusive."""
    path = tmp_path / "f"
    path.write_bytes(b"abc")
    seen: list[int] = []

    class Refused(Exception):
        pass

    def refuse(st: os.stat_result) -> None:
        seen.append(st.st_size)
        raise Refused

    with pytest.raises(Refused):
        read_user_file(path, what="test file", limit=10, check=refuse)
    assert seen == [3]
    assert read_user_file(path, what="test file", limit=3) == b"abc"
    with pytest.raises(ValueError, match=r"^test file .*/f: is 3 bytes, more than the 2 bytes"):
        read_user_file(path, what="test file", limit=2)
