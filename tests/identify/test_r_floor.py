"""`identify` floors each output's learned R at the variance its quantisation adds, step^2 / 12
(Widrow's model of uniform quantisation noise), where the rig says the output is decoded in
whole steps (an integer-coded signal: its scale times the unit factor); a float-coded output
keeps the R it learned (issue 16)."""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from monitor.bus.codec import load_database
from monitor.bus.rigcodec import RigCodec, output_quantisation
from monitor.identify import quantisation_floor
from monitor.rig import build_decoder, build_model, load_rig
from sim_ecu.rig_ecu import RigECU
from sim_ecu.scenario import scenario_from_dict
from tests.support.identify import PRESS, run_identify
from tests.support.paths import ROOT, TEST_RIGS

SERVO = TEST_RIGS / "servo.toml"
CIA402 = ROOT / "rigs" / "cia402-example.toml"
PRESS_STEP = 0.01  # A: tests/rigs/press.dbc's MotorCurrent, 16-bit integer, scale 0.01


def _quiet_capture(rig_path: Path, path: Path, *, level: float, amplitude: float, clock: float,
                   duration: float, quiet: float) -> Path:
    """A healthy capture of node 1 of the rig's twin under a PRBS, whose sensor adds almost
    no noise (its sigma `quiet` times the rig's): what the output carries beside the plant's
    own noise is the rounding to its signal's steps."""
    rig = load_rig(rig_path)
    codec = build_decoder(rig)
    assert isinstance(codec, RigCodec)
    scenario = scenario_from_dict({
        "name": "quiet", "duration": duration,
        "noise": {"current_sigma": 0.5 * quiet, "process": 1.0},
        "voltage": {"prbs": {"level": level, "amplitude": amplitude, "clock": clock,
                             "seed": 3}}})
    with can.Logger(str(path)) as log:
        for msg in RigECU(None, codec, rig, 1, scenario, seed=1).frames(start_time=1.7e9):
            log(msg)
    return path


def _identify_quiet(rig_path: Path, tmp_path: Path, **capture: float
                    ) -> tuple[subprocess.CompletedProcess[str], Path, dict[str, Any]]:
    """`identify` of node 1 on a `_quiet_capture` of the rig (`capture`: its keywords), which
    must succeed: its result, the rig file written and the JSON report beside it."""
    cap = _quiet_capture(rig_path, tmp_path / "quiet.log", **capture)
    out = tmp_path / "learned.toml"
    res = run_identify(str(cap), "--rig", str(rig_path), "--node", "1", "--out", str(out),
                       cwd=tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    return res, out, json.loads(out.with_suffix(".identify.json").read_text())


def _written_r(out: Path) -> float:
    """The R the monitor reads from the written rig file (either model kind)."""
    return float(build_model(load_rig(out)).R[0, 0])


def test_a_quantised_output_is_floored_at_its_steps_variance(tmp_path: Path) -> None:
    res, out, report = _identify_quiet(PRESS, tmp_path, level=220.0, amplitude=20.0,
                                       clock=0.5, duration=60.0, quiet=2e-6)
    floor = PRESS_STEP ** 2 / 12.0
    # the rig written, which the replay checks judged, holds the floored R
    assert _written_r(out) == pytest.approx(floor, rel=1e-9, abs=0.0)
    noise = report["noise"]
    (row,) = noise["quantisation_floor"]
    assert row["applied"] and row["learned"] < floor  # the fit alone went below it
    assert row["step"] == pytest.approx(PRESS_STEP) and row["floor"] == pytest.approx(floor)
    assert row["output"] == "MotorCurrent"
    assert "PressFb_A.MotorCurrent" in row["source"] and "integer-coded" in row["source"]
    assert noise["R"] == [[pytest.approx(floor)]]
    assert noise["R_learned"] == [[row["learned"]]]
    assert all(c["passed"] for c in report["checks"] if c["gating"])
    line = next(ln for ln in res.stdout.splitlines() if "floored at its quantisation" in ln)
    assert "MotorCurrent" in line and "step 0.01" in line and "PressFb_A.MotorCurrent" in line


def test_a_float_coded_output_keeps_its_learned_r(tmp_path: Path) -> None:
    # servo.dbc's CurrentFb is float32 in mA: no fixed step, so no floor. Were it taken for an
    # integer signal, its step (1 mA) would floor R at 8.3e-8 A^2, above what the fit learns
    # from this quiet sensor.
    res, out, report = _identify_quiet(SERVO, tmp_path, level=12.0, amplitude=2.0,
                                       clock=0.05, duration=20.0, quiet=2e-3)
    noise = report["noise"]
    assert {"quantisation_floor", "R_learned"}.isdisjoint(noise)
    learned = noise["R"][0][0]
    assert learned < 1e-3 ** 2 / 12.0
    assert _written_r(out) == pytest.approx(learned, rel=1e-9, abs=0.0)
    assert "floored" not in res.stdout


def test_each_decoder_knows_its_outputs_step() -> None:
    press = build_decoder(load_rig(PRESS))
    (q,) = output_quantisation(press, 1)
    assert q is not None and q.step == pytest.approx(PRESS_STEP)
    # our own bus: ArmatureCurrent, 16-bit integer, scale 0.01 A, never scaled
    (ours,) = output_quantisation(load_database(), 0)
    assert ours is not None and ours.step == pytest.approx(0.01)
    assert "ArmatureCurrent" in ours.source
    # a CiA 402 drive: 0x606C is an INTEGER32 in 0.001 rpm (the rig's [bus.objects]),
    # read in rad/s
    (vel,) = output_quantisation(build_decoder(load_rig(CIA402)), 1)
    assert vel is not None and vel.step == pytest.approx(0.001 * 2.0 * math.pi / 60.0)
    assert "to the model's unit" in vel.source
    assert output_quantisation(build_decoder(load_rig(SERVO)), 1) == (None,)  # float32
    assert output_quantisation(press, 7) == ()  # no such node


def test_the_floor_raises_only_variances_below_it_and_keeps_r_positive_definite() -> None:
    R = np.array([[1e-16, 2e-17], [2e-17, 5.0]])
    out = quantisation_floor(R, [1e-6, 1e-3])
    assert out[0, 0] == pytest.approx(1e-12 / 12.0, rel=1e-12, abs=0.0)  # raised to the floor
    assert out[1, 1] == 5.0  # above its floor: kept
    assert out[0, 1] == out[1, 0] == 2e-17  # covariances kept
    np.linalg.cholesky(out)  # still positive definite
    assert np.array_equal(R, [[1e-16, 2e-17], [2e-17, 5.0]])  # the input untouched
    # no step known (a float-coded output, no rig): nothing changes
    assert np.array_equal(quantisation_floor(R, [None, None]), R)
    with pytest.raises(ValueError, match="2 output step"):
        quantisation_floor(np.eye(3), [1.0, None])
