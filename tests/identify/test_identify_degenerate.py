"""`motor-monitor identify` on degenerate captures (issue 17): each is written as a candump
.log by python-can's writer and identified by the real command line. A capture that cannot
give a model ends in exit status 2 and exactly one line on stderr that says what is wrong
with it -- no traceback, no log line beside it, no LAPACK message (captured at the file
descriptors) -- and a capture that can still give one gives it (exit 0).

Decisions, each tested below:

* values that are NaN or inf: the decoder rejects those outside the DBC's range; those it
  passes are left out and counted (report ``capture.non_finite_dropped``). Either way they
  are gaps: the longest gap-free stretch is fitted, and when it is too short the line says
  how many frames were rejected or left out, not that the capture is short;
* timestamps that go backwards or repeat: refused, naming the file and the frame -- identify
  does not sort a capture (two files given out of order would interleave two recordings);
* a fault in the middle: refused ("the halves of the capture fit different models").
  identify does not guess which half is healthy: a capture may as well start faulty and
  end repaired;
* a dead time of a few periods: identified (exit 0). The DC-motor structure leaves residuals
  correlated with the input, so auto takes the black box, whose extra fast states hold the
  delay; its hold-out fit is the healthy capture's and the monitor's own filter on the
  capture sees no fault (gamma^ near 0);
* two nodes interleaved: identify asks for --node, and with it identifies that node;
* a rig whose input is a current and whose output a speed (issue 16): auto fits the black
  box (a DC-motor model takes a voltage in and a current out), --model dc_motor is refused.
"""

from __future__ import annotations

import json
import logging
import struct
from collections.abc import Callable, Sequence
from pathlib import Path

import can
import numpy as np
import pytest

from monitor.app.cli import main
from monitor.bus.rigcodec import RigCodec
from monitor.estimation.model import ContinuousDescriptor, DCMotorParameters, dc_motor
from monitor.identify import IdentifyError, identify, prbs
from monitor.rig import build_decoder, load_rig
from tests.identify.captures import capture
from tests.support.paths import TEST_RIGS

CapFD = pytest.CaptureFixture[str]
CapLog = pytest.LogCaptureFixture
SERVO = TEST_RIGS / "servo.toml"
T = 0.01  # the Table-1 motor at 100 Hz
SECONDS = 40.0
START = 1.7e9
SERVO_MOTOR = ("J = 2e-5\nb = 1e-5\nKe = 0.03\nKi = 0.03\nRa = 1.0\nLa = 1e-3\n"
               "process_noise = 1e-4\noutput_sigma = 0.01\n")


def _rig(tmp: Path, *, speed: bool = False, unbounded: bool = False) -> Path:
    """The servo rig's bus (float32 signals, node in ID bits 5..8, no counters: any value can
    be written) at 100 Hz with the paper's motor; the DBC's voltage range widened to the
    paper's 220 V. `unbounded`: the current has no range, so inf passes the decoder.
    `speed`: the model's input is the current and its output the speed (issue 16)."""
    dbc = (SERVO.parent / "servo.dbc").read_text().replace("[-50|50]", "[-500|500]")
    if unbounded:
        dbc = dbc.replace("[-100000|100000]", "[0|0]")
    (tmp / "servo.dbc").write_text(dbc)
    text = SERVO.read_text().replace("rate = 1000.0", "rate = 100.0").replace(SERVO_MOTOR, "")
    if speed:
        text = text.replace('{ message = "AxisCommand", signal = "VoltageCmd", unit = "V" }',
                            '{ message = "AxisFeedback", signal = "CurrentFb", unit = "A" }', 1)
        text = text.replace('outputs = [{ message = "AxisFeedback", signal = "CurrentFb", '
                            'unit = "A" }]', 'outputs = [{ message = "AxisFeedback", signal = '
                            '"SpeedFb", unit = "rad/s" }]')
        text = text.replace('kind = "dc_motor"', 'kind = "state_space"\nA = [[-5.0]]\n'
                            'B = [[25.0]]\nC = [[1.0]]\nQ = [[0.01]]\nR = [[0.01]]')
    path = tmp / ("speed.toml" if speed else "rig.toml")
    path.write_text(text)
    return path


def _healthy(seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    u = prbs(SECONDS, T, level=220.0, amplitude=40.0, clock=0.3, seed=seed)
    return u, capture(dc_motor(), T, u, seed=seed)


def _clock(n: int) -> np.ndarray:
    return START + T * np.arange(n)


def _write(path: Path, rig: Path, t: np.ndarray, u: np.ndarray, y: np.ndarray,
           nodes: Sequence[int] | None = None, *, speed: bool = False) -> Path:
    """A candump .log of the samples (the command frame, then the feedback, at each t);
    NaN and inf are written into the float32 signal's bytes (the codec encodes only
    finite values)."""
    codec = build_decoder(load_rig(rig))
    assert isinstance(codec, RigCodec)

    def frame(name: str, node: int, signal: str, value: float, fmt: str,
              extra: dict[str, float], when: float) -> can.Message:
        fid, ext, data = codec.encode(name, node, {signal: value if np.isfinite(value) else 0.0,
                                                   **extra})
        payload = bytearray(data)
        if not np.isfinite(value):
            payload[0:4] = struct.pack(fmt, value)
        return can.Message(arbitration_id=fid, is_extended_id=ext, data=bytes(payload),
                           timestamp=when)

    with can.Logger(str(path)) as log:
        for k in range(len(t)):
            node = 1 if nodes is None else nodes[k]
            if speed:  # current (input) and speed (output) in the feedback frame
                log(frame("AxisFeedback", node, "CurrentFb", 1000.0 * u[k, 0], ">f",
                          {"SpeedFb": y[k, 0]}, t[k]))
                continue
            log(frame("AxisCommand", node, "VoltageCmd", u[k, 0], "<f", {}, t[k]))
            log(frame("AxisFeedback", node, "CurrentFb", 1000.0 * y[k, 0], ">f", {}, t[k]))
    return path


def _identify(capfd: CapFD, caplog: CapLog,
              *args: str) -> tuple[int, list[str], str, list[str]]:
    """The command line in this process: (exit status, stderr lines, stdout, log lines of
    WARNING and above -- what the installed command prints on stderr beside its error)."""
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        rc = main(["identify", *args])
    out, err = capfd.readouterr()
    logged = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    return rc, err.strip().splitlines(), out, logged


def _refused(capfd: CapFD, caplog: CapLog,
             cap: Path, rig: Path, *extra: str) -> str:
    """identify refuses `cap` in one line, writes nothing; returns the line."""
    out = cap.with_name(f"{cap.stem}-learned.toml")
    rc, err, _, logged = _identify(capfd, caplog, str(cap), "--rig", str(rig), "--node", "1",
                                   *extra, "--out", str(out))
    assert rc == 2, (rc, err)
    assert len(err) == 1 and not logged, (err, logged)
    assert err[0].startswith("motor-monitor: error: ") and "Traceback" not in err[0]
    assert not out.exists()
    return err[0]


# ---- refused: the capture cannot give a model


@pytest.mark.parametrize(("damage", "phrases"), [
    pytest.param(lambda y: np.full_like(y, 7.0), ("output 'CurrentFb' is stuck at 7",),
                 id="stuck at one value"),
    pytest.param(lambda y: np.minimum(y, np.percentile(y, 70)),  # a current limit
                 ("sits at its largest value", "saturated"), id="saturated"),
    pytest.param(lambda y: 5.0 + 2.0 * np.digitize(y, np.percentile(y, [33, 66])).astype(float),
                 ("takes only 3 distinct values", "resolution"), id="quantised to three levels"),
])
def test_an_output_that_cannot_give_a_model(tmp_path: Path, capfd: CapFD, caplog: CapLog,
                                            damage: Callable[[np.ndarray], np.ndarray],
                                            phrases: tuple[str, ...]) -> None:
    rig = _rig(tmp_path)
    u, y = _healthy()
    cap = _write(tmp_path / "output.log", rig, _clock(len(u)), u, damage(y))
    line = _refused(capfd, caplog, cap, rig)
    assert all(phrase in line for phrase in phrases), line


@pytest.mark.parametrize("model", ["auto", "state_space"])
def test_input_constant(tmp_path: Path, capfd: CapFD, caplog: CapLog, model: str) -> None:
    rig = _rig(tmp_path)
    u, y = _healthy()
    cap = _write(tmp_path / "flat.log", rig, _clock(len(u)), np.full_like(u, 220.0), y)
    line = _refused(capfd, caplog, cap, rig, "--model", model)
    assert "input 'VoltageCmd' is constant (220)" in line and "record" in line, line


def test_nan_in_one_frame_of_seven(tmp_path: Path, capfd: CapFD, caplog: CapLog) -> None:
    rig = _rig(tmp_path)
    u, y = _healthy()
    y[::7] = np.nan
    cap = _write(tmp_path / "nan.log", rig, _clock(len(u)), u, y)
    line = _refused(capfd, caplog, cap, rig)
    # not "capture too short: 0.06 s": the capture is 40 s, its gaps leave 6 samples
    assert "longest stretch without a gap is 6 samples" in line, line
    assert f"{len(u) // 7 + 1} out_of_range" in line and "NaN or inf" in line, line


def test_a_single_frame(tmp_path: Path, capfd: CapFD, caplog: CapLog) -> None:
    rig = _rig(tmp_path)
    u, y = _healthy()
    cap = _write(tmp_path / "one.log", rig, _clock(1), u[:1], y[:1])
    line = _refused(capfd, caplog, cap, rig)
    assert "1 usable output sample(s) of node 1" in line, line


@pytest.mark.parametrize(("shift", "how"), [(-1.0, "go backwards"), (-T, "repeat")])
def test_timestamps_out_of_order(tmp_path: Path, capfd: CapFD, caplog: CapLog, shift: float,
                                 how: str) -> None:
    rig = _rig(tmp_path)
    u, y = _healthy()
    t = _clock(len(u))
    t[2000:] += shift  # the clock jumps back at sample 2000 (frames 4001, 4002)
    cap = _write(tmp_path / "clock.log", rig, t, u, y)
    line = _refused(capfd, caplog, cap, rig)
    assert f"clock.log: the timestamps of node 1's output samples {how} at frame 4002" in line, \
        line


def test_a_fault_in_the_middle(tmp_path: Path, capfd: CapFD, caplog: CapLog) -> None:
    rig = _rig(tmp_path)
    u, _ = _healthy()
    gamma = np.zeros_like(u)
    gamma[len(u) // 2:] = 0.5
    y = capture(dc_motor(), T, u, seed=3, gamma=gamma)
    cap = _write(tmp_path / "fault.log", rig, _clock(len(u)), u, y)
    line = _refused(capfd, caplog, cap, rig)
    assert "the halves of the capture fit different models" in line and "a fault" in line \
        and "healthy node only" in line, line
    # the load refit (tried for halves that differ) is refused by the same check: said once
    assert line.endswith("(a refit with load steps: refused the same way)"), line


def test_dc_motor_asked_of_a_current_to_speed_rig(tmp_path: Path, capfd: CapFD,
                                                  caplog: CapLog) -> None:
    rig = _rig(tmp_path, speed=True)
    u, y = _speed_capture()
    cap = _write(tmp_path / "speed.log", rig, _clock(len(u)), u, y, speed=True)
    line = _refused(capfd, caplog, cap, rig, "--model", "dc_motor")
    assert "--model dc_motor:" in line and "voltage" in line and "state_space" in line, line


# ---- identified: the capture still gives a model


def _identified(capfd: CapFD, caplog: CapLog,
                cap: Path, rig: Path, *extra: str) -> tuple[dict[str, object], list[str]]:
    out = cap.with_name(f"{cap.stem}-learned.toml")
    rc, err, stdout, logged = _identify(capfd, caplog, str(cap), "--rig", str(rig), *extra,
                                        "--out", str(out))
    assert rc == 0, err
    assert "hold-out fit" in stdout
    load_rig(out)  # the rig written loads, every key checked
    report: dict[str, object] = json.loads(out.with_suffix(".identify.json").read_text())
    return report, logged


def _speed_capture() -> tuple[np.ndarray, np.ndarray]:
    """The speed of the paper's motor from its current: J w' = Ki i - b w."""
    plant = ContinuousDescriptor(E=np.array([[0.01]]), A=np.array([[-0.05]]),
                                 B=np.array([[0.25]]), C=np.array([[1.0]]),
                                 Qc=np.array([[1e-4]]), R=np.array([[0.01]]),
                                 state_names=("speed",))
    u = prbs(SECONDS, T, level=5.0, amplitude=1.0, clock=0.3, seed=5)
    return u, capture(plant, T, u, seed=5, sigma=0.1)


def test_two_nodes_interleaved(tmp_path: Path, capfd: CapFD, caplog: CapLog) -> None:
    rig = _rig(tmp_path)
    u, y = _healthy()
    n = len(u)
    t = np.repeat(_clock(n), 2) + np.tile([0.0, 0.003], n)
    cap = _write(tmp_path / "two.log", rig, t, np.repeat(u, 2, axis=0),
                 np.repeat(y, 2, axis=0), nodes=[1, 2] * n)
    rc, err, _, _ = _identify(capfd, caplog, str(cap), "--rig", str(rig), "--out",
                              str(tmp_path / "x.toml"))
    assert rc == 2 and len(err) == 1 and "choose one with --node" in err[0], err
    report, logged = _identified(capfd, caplog, cap, rig, "--node", "2")
    assert report["kind"] == "dc_motor" and not logged, logged
    assert report["capture"]["node"] == 2  # type: ignore[index]


def test_inf_in_a_few_frames_is_left_out_and_counted(tmp_path: Path, capfd: CapFD,
                                                     caplog: CapLog) -> None:
    rig = _rig(tmp_path, unbounded=True)  # no range in the DBC: inf is out of range all the same
    u, y = _healthy()
    y[[3500, 3700, 3900]] = np.inf
    cap = _write(tmp_path / "inf.log", rig, _clock(len(u)), u, y)
    report, _ = _identified(capfd, caplog, cap, rig, "--node", "1")
    capture_info = report["capture"]
    assert isinstance(capture_info, dict)
    assert capture_info["frames"]["rejected/out_of_range"] == 3
    assert capture_info["samples"] == 3500  # the stretch before the first inf


def test_a_dead_time_of_three_periods(tmp_path: Path, capfd: CapFD, caplog: CapLog) -> None:
    rig = _rig(tmp_path)
    u, _ = _healthy()
    late = np.vstack([np.full((3, 1), u[0, 0]), u[:-3]])  # applied 30 ms late
    y = capture(dc_motor(), T, late, seed=3)
    cap = _write(tmp_path / "late.log", rig, _clock(len(u)), u, y)
    report, _ = _identified(capfd, caplog, cap, rig, "--node", "1")
    # the dead time is learned as an input delay (the motor's own lag adds to it), so the
    # model needs no spurious poles to describe it
    delay = report["input_delay"]
    assert isinstance(delay, dict) and 3 <= delay["samples"] <= 4, delay
    fit = report["fit"]
    assert isinstance(fit, dict) and fit["nrmse_holdout_pct"][0] > 80.0
    ukf = report["fuzzy_ukf"]
    assert isinstance(ukf, dict) and ukf["gamma_max_holdout"][0] < 0.1


def test_current_to_speed_rig_gets_the_black_box(tmp_path: Path, capfd: CapFD,
                                                 caplog: CapLog) -> None:
    rig = _rig(tmp_path, speed=True)
    u, y = _speed_capture()
    cap = _write(tmp_path / "speed.log", rig, _clock(len(u)), u, y, speed=True)
    report, logged = _identified(capfd, caplog, cap, rig, "--node", "1")
    assert report["kind"] == "state_space" and report["order"] == 1
    assert not logged, logged


# ---- the DC-motor fit that fails: auto falls back to the black box in one logged line


def test_auto_falls_back_to_the_black_box_when_the_motor_fit_fails(
        caplog: CapLog) -> None:
    # J in the wrong units (1e100 kg m^2): the motor model's speed-noise intensity J^2 q
    # leaves the float range the estimator needs, so the DC-motor fit cannot give a model
    u, y = _healthy()
    bad = DCMotorParameters(J=1e100)
    with caplog.at_level(logging.WARNING):
        ident = identify(u, y, T, template=bad, run_filter=False)
    assert ident.kind == "state_space"
    warned = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warned) == 1 and "the DC-motor model does not fit" in warned[0], warned
    assert "J = 1e+100" in ident.report["auto"]["dc_motor_failed"]
    with pytest.raises(IdentifyError, match="the DC-motor model does not fit") as info:
        identify(u, y, T, kind="dc_motor", template=bad, run_filter=False)
    assert "\n" not in str(info.value)
