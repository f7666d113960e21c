"""`identify` replays its capture through the monitor with the learned rig before it writes
it: a model that keeps the capture fault-free, unflagged and with a consistent NIS is
written and its checks listed; one that does not is refused in one line (the report still
written) unless --force, which says so in the rig file. A rig without [model] is identify's
input, and nothing else's."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import can
import numpy as np
import pytest

from monitor.bus.codec import Decoded, load_database
from monitor.rig import RigError, load_rig
from sim_ecu.ecu import VirtualECU
from sim_ecu.scenario import scenario_from_dict
from tests.identify.test_identify_cli import PRESS, _capture, _identify
from tests.support import BIN

T0 = 1.7e9
GATING = {"replay_fault_free", "replay_gamma_margin", "replay_model_mismatch", "replay_mean_nis",
          "fault_detection"}
ADVISORY = {"holdout_fit", "whiteness", "cross_correlation", "consistency", "excitation"}


def _ours(path: Path, *, noisy_from: float | None = None) -> Path:
    """40 s of node 0 on our bus under a PRBS command; from `noisy_from` seconds on, the
    current sensor adds 1 A of noise (twice the model's sigma): the plant is the same,
    its noise is not."""
    db = load_database()
    sc = scenario_from_dict({"name": "prbs", "duration": 40.0, "voltage": {
        "prbs": {"level": 220.0, "amplitude": 20.0, "clock": 0.5, "seed": 3}}})
    rng = np.random.default_rng(7)
    with can.Logger(str(path)) as log:
        for m in VirtualECU(None, db, 0, sc, seed=5).frames(start_time=T0):
            d = db.decode_can(m)
            if (noisy_from is not None and isinstance(d, Decoded) and d.kind == "current"
                    and m.timestamp - T0 >= noisy_from):
                data = db.encode_current(d.node, d.value + float(rng.normal(0.0, 1.0)),
                                         int(d.counter or 0))
                m = can.Message(arbitration_id=m.arbitration_id, data=data,
                                timestamp=m.timestamp, is_extended_id=False)
            log(m)
    return path


def _checks(out: Path) -> dict[str, dict[str, object]]:
    report = json.loads(out.with_suffix(".identify.json").read_text())
    return {c["check"]: c for c in report["checks"]}


def test_a_healthy_capture_passes_every_gating_check(tmp_path: Path) -> None:
    cap = _ours(tmp_path / "healthy.log")
    out = tmp_path / "learned.toml"
    res = _identify(str(cap), "--out", str(out), cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    checks = _checks(out)
    assert set(checks) == GATING | ADVISORY
    for name in GATING:
        c = checks[name]
        assert c["gating"] and c["passed"], c
        assert f"PASS {name}:" in res.stdout
    assert not any(checks[n]["gating"] for n in ADVISORY)
    assert all({"check", "passed", "value", "limit", "advice"} <= set(c) for c in checks.values())
    assert checks["replay_fault_free"]["value"] == 0.0
    band, nis = checks["replay_mean_nis"]["limit"], checks["replay_mean_nis"]["value"]
    assert isinstance(band, list) and isinstance(nis, float)
    assert band[0] < nis < band[1]
    report = json.loads(out.with_suffix(".identify.json").read_text())
    assert set(report["replay"]["state_seconds"]) == {"fault_free"}
    assert report["replay"]["mismatch_seconds"] == 0.0
    assert "--force" not in out.read_text()
    load_rig(out)


def test_b_a_model_that_fails_the_replay_is_not_written_unless_forced(tmp_path: Path) -> None:
    # The sensor's noise doubles half way: one R cannot fit both halves, so the flag rises
    # on the capture the model was learned from (the fit's own refusals do not see it).
    cap = _ours(tmp_path / "noisy.log", noisy_from=20.0)
    out = tmp_path / "learned.toml"
    res = _identify(str(cap), "--out", str(out), cwd=tmp_path)
    assert res.returncode == 1, res.stdout + res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in res.stderr, res.stderr
    assert lines[0].startswith("motor-monitor: error: ") and "not written" in lines[0]
    assert "replay_model_mismatch" in lines[0] and "--force" in lines[0], lines[0]
    assert not out.exists()
    assert not list(tmp_path.glob(".learned.toml.*"))  # no temporary file left
    checks = _checks(out)  # the report says why
    assert not checks["replay_model_mismatch"]["passed"]
    assert checks["replay_model_mismatch"]["advice"]
    assert "FAIL replay_model_mismatch" in res.stdout

    res = _identify(str(cap), "--out", str(out), "--force", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "written with --force" in res.stderr
    head = out.read_text().splitlines()[:2]
    assert head[0].startswith("# identified by motor-monitor identify")
    assert head[1].startswith("# written with --force") and "replay_model_mismatch" in head[1]
    load_rig(out)  # the same model, loadable


def _bare_press(tmp_path: Path) -> Path:
    """tests/rigs/press.toml without its [model] (the last table), DBC by absolute path."""
    text = PRESS.read_text().split("[model]")[0]
    bare = tmp_path / "bare.toml"
    bare.write_text(text.replace('dbc = ["press.dbc"]', f'dbc = ["{PRESS.parent / "press.dbc"}"]'))
    return bare


def test_c_a_rig_without_model_is_identifys_input_only(tmp_path: Path) -> None:
    bare = _bare_press(tmp_path)
    with pytest.raises(RigError, match=r"model: missing.*identify"):
        load_rig(bare)
    rig = load_rig(bare, model_optional=True)
    assert rig.model is None and rig.rate is None
    cap = _capture(tmp_path / "healthy.log")
    out = tmp_path / "learned.toml"
    res = _identify(str(cap), "--rig", str(bare), "--node", "1", "--out", str(out),
                    cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert load_rig(out).rate == pytest.approx(100.0)
    rep = subprocess.run([str(BIN / "motor-monitor"), "replay", str(cap), "--rig", str(bare)],
                         capture_output=True, text=True, timeout=300)
    assert rep.returncode == 2
    lines = rep.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in rep.stderr, rep.stderr
    assert "model: missing" in lines[0] and "motor-monitor identify" in lines[0], lines[0]
