"""`identify` replays its capture through the monitor with the learned rig before it writes
it: a model that keeps the capture fault-free, unflagged and with a consistent NIS is
written and its checks listed; one that does not is refused in one line (the report still
written) unless --force, which says so in the rig file. A rig without [model] is identify's
input, and nothing else's."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from monitor.rig import RigError, load_rig
from tests.support.identify import PRESS, our_capture, press_capture, run_identify, run_replay

GATING = {"replay_fault_free", "replay_gamma_margin", "replay_model_mismatch", "replay_mean_nis",
          "fault_detection"}
ADVISORY = {"holdout_fit", "whiteness", "cross_correlation", "consistency", "excitation",
            "input_levels", "steady_state_loss"}


def _checks(out: Path) -> dict[str, dict[str, object]]:
    report = json.loads(out.with_suffix(".identify.json").read_text())
    return {c["check"]: c for c in report["checks"]}


def test_a_healthy_capture_passes_every_gating_check(tmp_path: Path) -> None:
    cap = our_capture(tmp_path / "healthy.log")
    out = tmp_path / "learned.toml"
    res = run_identify(str(cap), "--out", str(out), cwd=tmp_path)
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
    cap = our_capture(tmp_path / "noisy.log", noisy_from=20.0)
    out = tmp_path / "learned.toml"
    res = run_identify(str(cap), "--out", str(out), cwd=tmp_path)
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

    res = run_identify(str(cap), "--out", str(out), "--force", cwd=tmp_path)
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
    cap = press_capture(tmp_path / "healthy.log")
    out = tmp_path / "learned.toml"
    res = run_identify(str(cap), "--rig", str(bare), "--node", "1", "--out", str(out),
                    cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert load_rig(out).rate == pytest.approx(100.0)
    rep = run_replay(str(cap), "--rig", str(bare))
    assert rep.returncode == 2
    lines = rep.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in rep.stderr, rep.stderr
    assert "model: missing" in lines[0] and "motor-monitor identify" in lines[0], lines[0]


def test_b2_forced_when_both_orders_fail_writes_the_order_the_data_chose(
        tmp_path: Path) -> None:
    # A black box on the capture whose noise doubles half way: the order the data chose and
    # the one above it both fail their replay; --force writes the first, as checked.
    cap = our_capture(tmp_path / "noisy.log", noisy_from=20.0)
    out = tmp_path / "learned.toml"
    res = run_identify(str(cap), "--out", str(out), "--model", "state_space", "--force",
                       cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    report = json.loads(out.with_suffix(".identify.json").read_text())
    retry = report["order_retry"]
    assert retry["order"] == report["order"] and retry["next_order_failed"], retry
    head = out.read_text().splitlines()[1]
    assert head.startswith("# written with --force") and retry["failed"][0] in head, head
    model = load_rig(out).model
    assert model is not None and len(model.matrices["A"]) == report["order"]
