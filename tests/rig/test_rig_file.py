"""Rig files: the example equals the built-in rig, every mistake is one clear line (file,
key, problem) from the loader and from the command line, exit status 2."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

from monitor.bus.codec import Decoded, MotorDatabase
from monitor.bus.rigcodec import RigCodec
from monitor.rig import build_decoder, build_model, builtin_rig, load_rig
from tests.support import BIN
from tests.support.paths import ROOT, TEST_RIGS
from tests.support.rig_files import rig_refusal, written_rig

EXAMPLE = ROOT / "rigs" / "motor.toml"
SERVO = TEST_RIGS / "servo.toml"
SERVO_DBC = TEST_RIGS / "servo.dbc"


def test_example_rig_is_the_builtin_one() -> None:
    mine, shipped = load_rig(EXAMPLE), builtin_rig()
    assert mine.dbc[0].resolve() == shipped.dbc[0].resolve()
    for field in ("layout", "inputs", "outputs", "truth", "protection", "rate", "diagnosis",
                  "nodes"):
        assert getattr(mine, field) == getattr(shipped, field), field
    a, b = build_model(mine), build_model(shipped)
    for name in ("E", "A", "B", "C", "Qc", "R"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert isinstance(build_decoder(mine), MotorDatabase)


def test_foreign_rig_loads_with_its_layout() -> None:
    rig = load_rig(SERVO)
    codec = build_decoder(rig)
    assert isinstance(codec, RigCodec)
    assert codec.nodes == (1, 2)
    assert codec.frame_id("AxisFeedback", 2) == (2 << 5) | 2
    fid, ext, data = codec.encode_sample("AxisFeedback", 1, [0.0], [0.25])
    d = codec.decode(fid, data, ext, False, False, 1.0)
    assert isinstance(d, Decoded), d
    assert d.outputs == pytest.approx((0.25,), rel=1e-6)  # mA in the DBC, A in the model


SERVO_TEXT = SERVO.read_text()

MISTAKES = [
    ("unknown top-level key", SERVO_TEXT + "\n[extra]\nx = 1\n", "extra: unknown key"),
    ("unknown model key", SERVO_TEXT.replace("rate = 1000.0", "rate = 1000.0\nspeed = 3"),
     "model.speed: unknown key"),
    ("signal not in the DBC", SERVO_TEXT.replace('signal = "CurrentFb"', 'signal = "Curent"'),
     "signals.outputs[0].signal: AxisFeedback has no signal Curent"),
    ("message not in the DBC", SERVO_TEXT.replace('message = "AxisCommand"',
                                                  'message = "AxisCmd"'),
     "signals.inputs[0].message: no message AxisCmd in the DBC"),
    ("unit that does not convert", SERVO_TEXT.replace('unit = "A"', 'unit = "V"'),
     "signals.outputs[0].unit: cannot convert 'mA' to 'V'"),
    ("node bits that overlap node 0's ID", SERVO_TEXT.replace("node_bits = [5, 4]",
                                                              "node_bits = [0, 4]"),
     "bus.node_bits: AxisCommand has ID 0x1, whose node bits are not 0"),
    ("bad layout", SERVO_TEXT.replace('layout = "id_bits"', 'layout = "bits"'),
     "bus.layout: must be name_suffix, id_bits or explicit"),
    ("missing DBC", SERVO_TEXT.replace('dbc = "servo.dbc"', 'dbc = "nope.dbc"'),
     "nope.dbc: no such file"),
    ("not TOML", "[bus\n", "not valid TOML"),
    ("negative rate", SERVO_TEXT.replace("rate = 1000.0", "rate = -1.0"),
     "model.rate: must be > 0"),
    ("an input window of a whole period", SERVO_TEXT.replace(
        "rate = 1000.0", "rate = 1000.0\ninput_window = 1.0"),
     "model.input_window: must be a share of the period from 0 to below 1, got 1.0"),
    ("thresholds out of order", SERVO_TEXT.replace("f1 = 0.15", "f1 = 0.9"),
     "diagnosis.f1: thresholds must satisfy 0 < f1 < f2 < 1"),
    ("a silence timeout within two sample periods", SERVO_TEXT.replace(
        "rate = 1000.0", "rate = 5.0").replace("[diagnosis]",
                                               "[diagnosis]\nsilence_timeout_s = 0.3"),
     "diagnosis.silence_timeout_s: 0.3 s is not longer than 2 sample periods"),
    ("a motor parameter that is not a number", SERVO_TEXT.replace("J = 2e-5", 'J = "big"'),
     "model.J: must be a number"),
    ("a negative motor parameter", SERVO_TEXT.replace("J = 2e-5", "J = -2e-5"),
     "model: motor parameter J must be positive"),
    ("state-space shapes that disagree", SERVO_TEXT.replace(
        'kind = "dc_motor"', 'kind = "state_space"\nA = [[-1.0, 0.0], [0.0, -2.0]]\n'
        'B = [[1.0], [0.0], [0.0]]\nC = [[1.0, 0.0]]\nQ = [[1.0, 0.0], [0.0, 1.0]]\n'
        'R = [[0.01]]').replace("J = 2e-5\nb = 1e-5\nKe = 0.03\nKi = 0.03\nRa = 1.0\n"
                                "La = 1e-3\nprocess_noise = 1e-4\noutput_sigma = 0.01\n", ""),
     "model: B"),
    ("a fault the outputs cannot see", SERVO_TEXT.replace(
        'kind = "dc_motor"', 'kind = "state_space"\nA = [[-1.0, 0.0], [0.0, -2.0]]\n'
        'B = [[0.0], [1.0]]\nC = [[1.0, 0.0]]\nQ = [[1.0, 0.0], [0.0, 1.0]]\n'
        'R = [[0.01]]').replace("J = 2e-5\nb = 1e-5\nKe = 0.03\nKi = 0.03\nRa = 1.0\n"
                                "La = 1e-3\nprocess_noise = 1e-4\noutput_sigma = 0.01\n", ""),
     "not observable"),
    ("friction on a DC-motor model", SERVO_TEXT.replace(
        "rate = 1000.0", "rate = 1000.0\nfriction = { B = [1.0], speed = \"output\", "
        "width = 0.1 }"), "model.friction: only a state_space model has friction"),
    ("friction of an unknown speed", SERVO_TEXT.replace(
        'kind = "dc_motor"', 'kind = "state_space"\nA = [[-1.0]]\nB = [[1.0]]\n'
        'C = [[1.0]]\nQ = [[1.0]]\nR = [[0.01]]\n'
        'friction = { B = [1.0], speed = "velocity", width = 0.1 }').replace(
        "J = 2e-5\nb = 1e-5\nKe = 0.03\nKi = 0.03\nRa = 1.0\n"
        "La = 1e-3\nprocess_noise = 1e-4\noutput_sigma = 0.01\n", ""),
     "model.friction.speed: must be one of output, rate, got 'velocity'"),
    ("friction with a column of the wrong length", SERVO_TEXT.replace(
        'kind = "dc_motor"', 'kind = "state_space"\nA = [[-1.0]]\nB = [[1.0]]\n'
        'C = [[1.0]]\nQ = [[1.0]]\nR = [[0.01]]\n'
        'friction = { B = [1.0, 2.0], speed = "output", width = 0.1 }').replace(
        "J = 2e-5\nb = 1e-5\nKe = 0.03\nKi = 0.03\nRa = 1.0\n"
        "La = 1e-3\nprocess_noise = 1e-4\noutput_sigma = 0.01\n", ""),
     "model.friction: B has 2 columns, A has 1 states"),
    ("friction without a width", SERVO_TEXT.replace(
        'kind = "dc_motor"', 'kind = "state_space"\nA = [[-1.0]]\nB = [[1.0]]\n'
        'C = [[1.0]]\nQ = [[1.0]]\nR = [[0.01]]\n'
        'friction = { B = [1.0], speed = "output", width = -0.1 }').replace(
        "J = 2e-5\nb = 1e-5\nKe = 0.03\nKi = 0.03\nRa = 1.0\n"
        "La = 1e-3\nprocess_noise = 1e-4\noutput_sigma = 0.01\n", ""),
     "model.friction.width: must be > 0"),
    ("outputs in two messages", SERVO_TEXT.replace(
        'outputs = [{ message = "AxisFeedback", signal = "CurrentFb", unit = "A" }]',
        'outputs = [{ message = "AxisFeedback", signal = "CurrentFb", unit = "A" }, '
        '{ message = "AxisCommand", signal = "Mode" }]'), "every output must come in one"),
]


@pytest.mark.parametrize(("what", "text", "needle"), MISTAKES, ids=[m[0] for m in MISTAKES])
def test_each_mistake_is_one_line(tmp_path: Path, what: str, text: str, needle: str) -> None:
    msg = rig_refusal(written_rig(tmp_path, text, SERVO_DBC))
    assert needle in msg, msg


@pytest.mark.parametrize("cmd", [["motor-monitor", "replay", "x.log"],
                                 ["motor-monitor", "run", "--interface", "virtual"],
                                 ["sim-ecu", "--node", "1", "--scenario", "healthy",
                                  "--interface", "virtual"]])
def test_cli_says_it_in_one_line(tmp_path: Path, cmd: list[str]) -> None:
    path = written_rig(tmp_path, SERVO_TEXT.replace('signal = "CurrentFb"', 'signal = "Curent"'),
                       SERVO_DBC)
    (tmp_path / "x.log").write_text("")
    res = subprocess.run([str(BIN / cmd[0]), *cmd[1:], "--rig", str(path)], cwd=tmp_path,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in res.stderr, res.stderr
    assert f"error: rig file {path}: signals.outputs[0].signal:" in lines[0]
