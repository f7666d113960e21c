"""Rig files: the example equals the built-in rig, a mistake (the cases of mistakes.toml)
is one clear line (file, key, problem) from the command line too, exit status 2."""

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
from tests.support.rig_files import written_rig

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
