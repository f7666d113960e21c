"""A load that steps while the capture runs can read as a mode too slow for the capture, not
only as halves that fit differently: the paper's motor on our bus, load steps of 2, 5 and
1 N m over its healthy minute, fitted a mode of 5.9 s and identify refused it as "capture
too short for this plant", which says nothing of the load. That refusal gets the load refit
too; here the refit fits and then fails its own capture (the monitor reads each load step
as a loss until the input changes, with the true model as well), so the refusal stands
with what the refit found."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from tests.bench.realistic_identify import (
    BUILTIN_RIG,
    CAPTURE_S,
    excitation,
    motors,
    simulated,
    write_log,
)
from tests.support.identify import run_identify


def test_a_slow_mode_gets_the_load_refit(tmp_path: Path) -> None:
    motor = next(m for m in motors() if m.name == "load-steps")
    healthy = dataclasses.replace(motor.extras, faults=())
    t, u, y, _ = simulated(motor, healthy, CAPTURE_S, excitation(motor.volts, CAPTURE_S, 7),
                           seed=17)
    write_log(tmp_path / "capture.log", t, u, y)
    res = run_identify("capture.log", "--rig", str(BUILTIN_RIG), "--out", "learned.toml",
                       cwd=tmp_path)
    assert res.returncode != 0 and "Traceback" not in res.stderr, res.stderr
    lines = [x for x in res.stderr.strip().splitlines() if "WARNING" not in x]
    assert len(lines) == 1, res.stderr
    assert "capture too short for this plant" in lines[0]
    assert "(a refit with load steps" in lines[0]
    assert "its load steps by up to" in lines[0] and "record at one load" in lines[0]
    assert not (tmp_path / "learned.toml").exists()
