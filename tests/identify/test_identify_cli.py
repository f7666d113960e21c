"""`motor-monitor identify` on captures a virtual twin recorded: it writes a rig that loads
and runs, a report beside it, and refuses a capture it cannot use in one line."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import can
import pytest

from monitor.bus.rigcodec import RigCodec
from monitor.rig import build_decoder, load_rig
from sim_ecu.rig_ecu import RigECU
from sim_ecu.scenario import load_scenario
from tests.support import BIN
from tests.support.identify import PRESS, press_capture, run_identify


def test_identify_writes_a_rig_that_runs(tmp_path: Path) -> None:
    cap = press_capture(tmp_path / "healthy.log")
    out = tmp_path / "learned.toml"
    res = run_identify(str(cap), "--rig", str(PRESS), "--node", "1", "--out", str(out),
                    cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "hold-out fit" in res.stdout
    rig = load_rig(out)  # every key checked
    assert rig.rate == pytest.approx(100.0)
    report = json.loads(out.with_suffix(".identify.json").read_text())
    assert {"fit", "whiteness", "cross_correlation"} <= set(report)
    # run --rig RIG_OUT works at once: the learned rig replays a capture
    rep = subprocess.run([str(BIN / "motor-monitor"), "replay", str(cap), "--rig", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert rep.returncode == 0, rep.stderr
    assert "0 rejected" in rep.stderr


def test_identify_refuses_a_capture_without_excitation(tmp_path: Path) -> None:
    cap = press_capture(tmp_path / "steady.log", steady=True)
    res = run_identify(str(cap), "--rig", str(PRESS), "--node", "1", "--out",
                    str(tmp_path / "x.toml"), cwd=tmp_path)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in res.stderr, res.stderr
    assert "record" in lines[0], lines[0]
    assert not (tmp_path / "x.toml").exists()


def test_identify_wants_a_node_when_the_capture_has_several(tmp_path: Path) -> None:
    rig = load_rig(PRESS)
    codec = build_decoder(rig)
    assert isinstance(codec, RigCodec)
    cap = tmp_path / "two.log"
    scenario = load_scenario(PRESS.parent / "press_excite.toml")
    with can.Logger(str(cap)) as log:
        for node in (1, 2):
            for msg in RigECU(None, codec, rig, node, scenario, seed=node).frames(10.0, 1.7e9):
                log(msg)
    res = run_identify(str(cap), "--rig", str(PRESS), "--out", str(tmp_path / "x.toml"),
                    cwd=tmp_path)
    assert res.returncode == 2 and "--node" in res.stderr, res.stderr
