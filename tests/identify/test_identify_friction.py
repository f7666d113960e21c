"""Coulomb friction on a speed or position output: where the linear model fails its replay,
identify fits the black box once more with the friction (`monitor.identify.friction`) and
writes `[model.friction]` where that passes every check. The rig zoo's seed 307 (a current
in, a position held by a return spring out, 500 Hz, Coulomb friction 6 % of the input's
swing): the linear model's gamma^ reached 0.25 on its own healthy capture, close to the
threshold 0.15, at order 2 and 3, and identify refused the rig; with the friction the fit
goes from 95 % to 98 % and gamma^ stays below 0.1. A fit with friction also comes straight
from `identify(..., friction=...)`: on a simulated drive it finds the friction's size."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from monitor.app.identify_check import FRICTION_SHOWN, ReplayFigures, report_checks
from monitor.identify import identify, prbs
from monitor.rig import build_model, load_rig
from tests.bench.rig_zoo import prepare
from tests.support.identify import identify_zoo_rig, run_identify


def test_a_position_with_friction_is_learned_with_it(tmp_path: Path) -> None:
    res, report = identify_zoo_rig(307, tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    assert report["friction_retry"]["speed"] == "rate"
    assert "replay_gamma_margin" in report["friction_retry"]["failed"]
    assert report["friction"]["speed"] == "rate"
    assert report["replay"]["gamma_max"] < 0.1
    learned = load_rig(tmp_path / "learned.toml")
    assert learned.model is not None and learned.model.friction is not None
    model = build_model(learned)
    assert model.friction is not None and model.friction.speed == "rate"
    assert "[model.friction]" in (tmp_path / "learned.toml").read_text()


T_SPEED = 0.005


def _speed_under_prbs(tc: float) -> tuple[np.ndarray, np.ndarray]:
    """A speed (J 0.01, b 0.05) under a +-1 PRBS, Coulomb friction `tc` (N*m), noise 0.01."""
    T, J, b, width = T_SPEED, 0.01, 0.05, 0.05
    u = prbs(40.0, T, level=0.0, amplitude=1.0, clock=0.4, seed=5)
    sub, w = 20, 0.0
    ys = np.empty(u.shape[0])
    for k in range(u.shape[0]):
        ys[k] = w
        for _ in range(sub):
            w += T / sub * (-b * w + u[min(k + 1, u.shape[0] - 1), 0]
                            - tc * math.tanh(w / width)) / J
    return u, ys[:, None] + np.random.default_rng(3).normal(0.0, 0.01, (u.shape[0], 1))


def test_identify_with_friction_finds_its_size() -> None:
    T, tc = T_SPEED, 0.15
    u, y = _speed_under_prbs(tc)
    ident = identify(u, y, T, kind="state_space", order=1, input_delay=0, friction="output")
    fr = ident.model.friction
    assert fr is not None and fr.speed == "output"
    # the friction in the input's unit: b_f / B, T_c / 1 N m of torque
    assert float(fr.B[0] / ident.model.B[0, 0]) == pytest.approx(tc, rel=0.25)
    assert ident.report["fuzzy_ukf"]["gamma_max_holdout"][0] < 0.1
    plain = identify(u, y, T, kind="state_space", order=1, input_delay=0)
    assert plain.model.friction is None  # the linear fit takes the friction in part
    assert ident.report["fit"]["nrmse_holdout_pct"][0] > \
        plain.report["fit"]["nrmse_holdout_pct"][0] + 1.0
    # the refit shows the friction: it removes most of the linear model's hold-out error
    assert ident.report["friction"]["holdout_error_cut"] > FRICTION_SHOWN


def test_a_friction_refit_of_a_plant_without_friction_shows_none() -> None:
    """Under two levels the friction's phi follows the input's sign, so the refit of a plant
    without friction splits the gain between the two: a friction of any size that fits no
    better, which the gate friction_levels does not count (the rig zoo's seed 87)."""
    u, y = _speed_under_prbs(0.0)
    ident = identify(u, y, T_SPEED, kind="state_space", order=1, input_delay=0,
                     friction="output")
    assert ident.report["excitation"]["input_levels"] == [2]
    assert ident.report["friction"]["holdout_error_cut"] < FRICTION_SHOWN
    replay = ReplayFigures([], 2.0, 100, 1.0, {"fault_free": 1.0}, 0.0, 1.0, (0.8, 1.2),
                           gamma_max=0.01, f1=0.15)
    checks = {c.check: c for c in report_checks(ident.report, replay)}
    assert checks["friction_levels"].passed and checks["friction_levels"].value == 0.0
    shown = dict(ident.report, friction=dict(ident.report["friction"], holdout_error_cut=0.5,
                                              response_noise_units=20.0))
    checks = {c.check: c for c in report_checks(shown, replay)}
    assert not checks["friction_levels"].passed and checks["friction_levels"].gating


def test_a_two_level_capture_of_a_one_signed_friction_is_refused(tmp_path: Path) -> None:
    """The rig zoo's seed 203 (a torque in, a speed out, friction 10 % of the input's level,
    the speed one-signed, a two-level PRBS): the friction is a constant the two levels
    cannot tell from an actuator limit at the larger level (`test_limit_ambiguity`); the
    linear fit carried it on a slow growing mode, the friction's refit on its constant
    term, and a run at other levels would meet a limit, if it is one, wrong. Refused in one
    line before the friction's refit (which fitted order 1 and passed every check on the
    capture)."""
    res, _ = identify_zoo_rig(203, tmp_path, binary_prbs=True)
    assert res.returncode != 0
    last = res.stderr.strip().splitlines()[-1]
    assert "two levels alone" in last and "friction" in last and "several levels" in last


def test_a_two_level_capture_of_a_friction_that_matters_is_refused(tmp_path: Path) -> None:
    """The rig zoo's seed 84 (a voltage in, a free position out, Coulomb friction, a PRBS
    of +-6.65 V): the linear model passed every check on its capture, and fresh runs of
    random steps inside the same band met the friction's other shares as false alarms (4
    in the healthy run; 147 with the friction's refit, which passed every check too). The
    friction's refit, probed because the input took two levels, moves the output by 52
    noise units: refused in one line, whichever model, saying to record several levels.
    Seed 94 (a spring-held position, friction of 4.3 noise units) is accepted."""
    for seed in (84, 94):
        (tmp_path / str(seed)).mkdir()
    res, report = identify_zoo_rig(84, tmp_path / "84", binary_prbs=True)
    assert res.returncode == 1
    last = res.stderr.strip().splitlines()[-1]
    assert "friction_levels" in last and "several levels" in last
    assert report["friction_probe"]["response_noise_units"] > 10.0
    assert report["friction_probe"]["holdout_error_cut"] > FRICTION_SHOWN
    assert not (tmp_path / "84" / "learned.toml").exists()
    res, report = identify_zoo_rig(94, tmp_path / "94", binary_prbs=True)
    assert res.returncode == 0, res.stdout + res.stderr
    assert report["friction_probe"]["response_noise_units"] < 10.0
    assert {c["check"]: c["passed"] for c in report["checks"]}["friction_levels"]


def test_a_friction_probe_refused_or_fitted_weighs_the_friction(
        tmp_path: Path) -> None:
    """The rig zoo's seed 59 (a torque in, a free position out, Coulomb friction, a PRBS):
    the friction's refit, probed because the input took two levels, is refused after it
    measured the friction (for a slow mode the capture does not span, or for halves that fit
    differently) or fitted: the fit's floating point decides, which differs between CPUs
    (refused on some, fitted on others, as for seed 98 below). Either
    way what it measured (over 100 noise units, most of the linear model's hold-out error)
    stands, and friction_levels refuses the rig. Left silent, the linear model passed
    every check and a fresh run of random steps met the friction's other shares as 16
    false alarms."""
    # as the zoo writes it: the DBC's scale spans its fresh runs too
    prepare(59, tmp_path, binary_prbs=True)
    res = run_identify("identify.log", "--rig", "rig.toml", "--out", "learned.toml",
                       cwd=tmp_path)
    assert res.returncode == 1
    last = res.stderr.strip().splitlines()[-1]
    assert "friction_levels" in last and "several levels" in last
    report = json.loads((tmp_path / "learned.identify.json").read_text())
    probe = report["friction_probe"]
    if "refused" in probe:
        assert "capture too short" in probe["refused"] \
            or "fit different models" in probe["refused"], probe
    else:
        assert probe["order"] >= 1, probe
    assert probe["response_noise_units"] > 10.0 and probe["holdout_error_cut"] > FRICTION_SHOWN


def test_a_three_level_capture_of_a_large_friction_keeps_the_linear_model_out(
        tmp_path: Path) -> None:
    """The rig zoo's seed 98 (a torque in, a free position out at 2 kHz, Coulomb friction,
    a dead time, an offset and a quantum, a PRBS of -A, 0 and +A): the linear model fitted
    97 % and passed every check on its capture, then a healthy run of random steps in the
    same band raised 24 false alarms. The probe's friction moves the output by some 200
    noise units: the linear model fails friction_levels. The friction's refit, which three
    levels do resolve (it cuts the linear model's hold-out error by 98 %), is checked as
    any model: on some machines it passes every check and is written (the zoo's runs with
    it are right), on others the floating point takes its iterations elsewhere and it fails
    its gamma margin, and the refusal says to record more levels."""
    res, report = identify_zoo_rig(98, tmp_path)
    assert report["excitation"]["input_levels"] == [3]
    assert "friction_levels" in report["friction_retry"]["failed"]  # the linear model's
    learned = tmp_path / "learned.toml"
    if res.returncode == 0:
        assert report["friction"]["holdout_error_cut"] > 0.9
        assert all(c["passed"] for c in report["checks"] if c["gating"])
        assert "[model.friction]" in learned.read_text()
        return
    assert res.returncode == 1
    last = res.stderr.strip().splitlines()[-1]
    assert "friction_levels" in last and "3 levels" in last and "more levels" in last
    assert report["friction_probe"]["response_noise_units"] > 100.0
    assert report["friction_probe"]["holdout_error_cut"] > FRICTION_SHOWN
    # the model with friction is not gated by its size under three levels
    assert "friction_levels" not in report["friction_retry"]["friction_failed"]
    assert not learned.exists()
