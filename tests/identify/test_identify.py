"""identify(): accuracy against the true plant, the report, the refusals (issue 9, part 2).

Captures are simulated by sim_ecu.plant with the paper's noise (1)-(2) and a PRBS of the
voltage command around the operating point, as a test bench would record them.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import scipy.signal

from monitor.errors import MonitorError
from monitor.estimation.fuzzy_ukf import FuzzyUKF
from monitor.estimation.model import ContinuousDescriptor, DCMotorParameters, dc_motor
from monitor.identify import Identification, IdentifyError, identify, prbs
from monitor.identify import validate as V
from monitor.identify.lti import d2c, dsim
from sim_ecu.plant import SimulatedRun, simulate
from sim_ecu.scenario import BUILTIN_SCENARIOS, FaultSegment, Scenario
from tests.identify.captures import (
    SMALL_MOTOR,
    capture,
    frequency_response,
    step_response,
    two_by_two,
)

T1 = 0.01  # Table-1 motor at 100 Hz
TS = 0.001  # small motor at 1 kHz


Table1 = tuple[Identification, np.ndarray, np.ndarray]


@pytest.fixture(scope="module")
def table1() -> Table1:
    u = prbs(60.0, T1, level=220.0, amplitude=40.0, clock=0.3, seed=3)
    y = capture(dc_motor(), T1, u, seed=3)
    return identify(u, y, T1), u, y


@pytest.fixture(scope="module")
def small() -> Identification:
    u = prbs(60.0, TS, level=24.0, amplitude=2.4, clock=0.03, seed=3)
    y = capture(dc_motor(SMALL_MOTOR, r=0.02**2), TS, u, seed=3, sigma=0.02)
    return identify(u, y, TS, kind="dc_motor", template=DCMotorParameters(J=SMALL_MOTOR.J))


@pytest.fixture(scope="module")
def mimo() -> Identification:
    u = prbs(60.0, T1, level=np.array([1.0, -0.5]), amplitude=np.array([1.0, 1.0]),
             clock=0.3, seed=4)
    y = capture(two_by_two(), T1, u, seed=4, sigma=0.01)
    return identify(u, y, T1)


def _rel_freq_error(true: ContinuousDescriptor, est: ContinuousDescriptor,
                    w: list[float]) -> np.ndarray:
    gt = frequency_response(true, np.array(w))
    ge = frequency_response(est, np.array(w))
    return np.asarray(np.abs(ge - gt) / np.abs(gt))


def _rel_step_error(true: ContinuousDescriptor, est: ContinuousDescriptor, t_end: float,
                    T: float) -> float:
    st, se = step_response(true, t_end, T), step_response(est, t_end, T)
    return float(np.max(np.abs(se - st)) / np.max(np.abs(st)))


# ---- accuracy against the true plant


def test_table1_motor_transfer_function_within_a_few_percent(table1: Table1) -> None:
    ident, _, _ = table1
    assert ident.kind == "dc_motor"  # "auto" on one input and one output, good fit
    assert ident.report["auto"]["reason"].startswith("dc_motor")
    err = _rel_freq_error(dc_motor(), ident.model, [0.0, 1.0, 2.0, 4.0, 8.0])
    assert err[0] < 0.01, err  # DC gain
    assert np.all(err < 0.05), err
    assert _rel_step_error(dc_motor(), ident.model, 3.0, T1) < 0.03


def test_small_motor_at_1khz_parameters_and_transfer_function(small: Identification) -> None:
    assert small.kind == "dc_motor"
    m = small.motor
    assert m is not None and m.J == SMALL_MOTOR.J
    for name in ("La", "Ra", "b", "Ke"):
        assert getattr(m, name) == pytest.approx(getattr(SMALL_MOTOR, name), rel=0.02), name
        par = small.report["parameters"][name]
        assert 0 < par["std"] < 0.02 * par["value"]
    truth = dc_motor(SMALL_MOTOR)
    err = _rel_freq_error(truth, small.model, [0.0, 10.0, 50.0, 200.0, 1000.0])
    assert np.all(err < 0.02), err
    assert _rel_step_error(truth, small.model, 0.2, TS) < 0.02
    # The noise (1)-(2): true q = 1.44 per second, sensor sigma 0.02 A.
    assert small.R[0, 0] == pytest.approx(0.02**2, rel=0.1)
    assert small.report["identifiable"] == ["La", "Ra", "b/J", "Ke*Ki/J"]
    assert small.report["fixed"] == {"J": SMALL_MOTOR.J}


def test_wrong_inertia_gives_the_same_current_model() -> None:
    """J is not identifiable from current: fixing it wrong scales b and Ke*Ki with it and
    leaves the transfer function (and so the filter) unchanged."""
    u = prbs(20.0, TS, level=24.0, amplitude=2.4, clock=0.03, seed=5)
    y = capture(dc_motor(SMALL_MOTOR, r=0.02**2), TS, u, seed=5, sigma=0.02)
    ident = identify(u, y, TS, kind="dc_motor", template=DCMotorParameters(J=0.01),
                     run_filter=False)
    m = ident.motor
    assert m is not None and m.J == 0.01
    scale = 0.01 / SMALL_MOTOR.J
    assert m.b == pytest.approx(SMALL_MOTOR.b * scale, rel=0.03)
    assert m.Ke * m.Ki == pytest.approx(SMALL_MOTOR.Ke * SMALL_MOTOR.Ki * scale, rel=0.03)
    err = _rel_freq_error(dc_motor(SMALL_MOTOR), ident.model, [0.0, 10.0, 100.0, 1000.0])
    assert np.all(err < 0.02), err
    assert ident.report["whiteness"]["passed"]


def test_two_by_two_black_box(mimo: Identification) -> None:
    assert mimo.kind == "state_space"
    assert mimo.order == 3
    assert mimo.report["order_selection"]["given"] is False
    truth = two_by_two()
    err = _rel_freq_error(truth, mimo.model, [0.0, 0.5, 2.0, 5.0])
    assert np.all(err < 0.05), err
    lam = np.sort_complex(np.linalg.eigvals(mimo.model.A))
    assert np.allclose(lam, np.sort_complex(np.linalg.eigvals(truth.A)), rtol=0.05, atol=0.05)
    gain = np.array(mimo.report["dc_gain"])
    sd = np.array(mimo.report["parameters"]["dc_gain_std"])
    assert np.all(sd > 0) and np.all(sd < 0.1 * np.abs(gain))
    assert mimo.model.E.tolist() == np.eye(3).tolist()
    assert mimo.model.input_names == ("u1", "u2")


def test_black_box_of_a_given_order() -> None:
    u = prbs(30.0, T1, level=np.array([1.0, -0.5]), amplitude=np.array([1.0, 1.0]),
             clock=0.3, seed=6)
    y = capture(two_by_two(), T1, u, seed=6, sigma=0.01)
    ident = identify(u, y, T1, kind="state_space", order=3, run_filter=False)
    assert ident.order == 3 and ident.model.A.shape == (3, 3)
    assert ident.report["order_selection"]["given"] is True
    # Too small an order for this plant: refused as a structure that does not fit.
    msg = _refusal(u, y, T1, kind="state_space", order=1)
    assert "larger order" in msg


# ---- the report


def test_report_is_json_with_the_practitioner_checks(table1: Table1) -> None:
    ident, _, _ = table1
    rep = json.loads(ident.to_json())
    for key in ("fit", "whiteness", "cross_correlation", "parameters", "noise",
                "mean_nis_kalman_holdout", "fuzzy_ukf", "seconds", "timing_s", "consistency",
                "excitation", "identifiable", "fixed", "dc_gain", "poles_continuous"):
        assert key in rep, key
    assert 50.0 < rep["fit"]["nrmse_holdout_pct"][0] < 100.0
    assert set(rep["parameters"]) == {"La", "Ra", "b", "Ke", "Ki", "J"}
    assert rep["noise"]["R"] == ident.R.tolist()
    assert rep["noise"]["q"] == ident.q
    assert ident.Qc.shape == (3, 3)
    assert rep["seconds"] > 0


@pytest.mark.parametrize("which", ["table1", "small", "mimo"])
def test_innovations_are_white_with_unit_variance(which: str,
                                                  request: pytest.FixtureRequest) -> None:
    got = request.getfixturevalue(which)
    ident = got[0] if isinstance(got, tuple) else got
    rep = ident.report
    assert rep["whiteness"]["passed"], rep["whiteness"]["p_value"]
    assert rep["cross_correlation"]["passed"], rep["cross_correlation"]["p_value"]
    p = len(rep["outputs"])
    assert rep["mean_nis_kalman_holdout"] == pytest.approx(p, rel=0.1)
    for v in rep["whiteness"]["variance"]:
        assert v == pytest.approx(1.0, rel=0.1)
    # The monitor's own filter sees no fault in the healthy capture. Its NIS divides by
    # S plus the consequents' variance (gamma^ is uncertain too), so it sits below p.
    assert 0.5 * p < rep["fuzzy_ukf"]["mean_nis_holdout"] < 1.2 * p
    assert max(rep["fuzzy_ukf"]["gamma_mean_holdout"]) < 0.05


def test_png(table1: Table1, tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    ident, _, _ = table1
    out = tmp_path / "ident.png"
    ident.to_png(out)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ---- the identified model in the estimator


def _gamma_rmse(model: ContinuousDescriptor, run: SimulatedRun, T: float) -> float:
    est = FuzzyUKF(model.discretize(T))
    # u[k] is applied from t[k]; the filter applies its input over the interval ending at
    # the sample, so y[k] goes with u[k-1].
    g = np.array([est.step(run.u[max(k - 1, 0)], run.y[k], T).gamma[0]
                  for k in range(len(run.t))])
    return float(np.sqrt(np.mean((g - run.gamma[:, 0]) ** 2)))


def test_fuzzy_ukf_diagnoses_as_well_as_with_the_true_model(table1: Table1,
                                                             small: Identification) -> None:
    ident, _, _ = table1
    run = simulate(dc_motor(), BUILTIN_SCENARIOS["fault-outage-recovery"], T1, seed=7)
    true_rmse = _gamma_rmse(dc_motor(), run, T1)
    assert _gamma_rmse(ident.model, run, T1) <= 1.2 * true_rmse
    sc = Scenario(name="small", duration=4.0, voltage_steps=((0.0, 24.0),),
                  faults=(FaultSegment(1.0, 2.0, gamma=0.4), FaultSegment(2.0, 3.0, gamma=1.0)),
                  current_sigma=0.02)
    truth = dc_motor(SMALL_MOTOR, r=0.02**2)
    run = simulate(truth, sc, TS, seed=8)
    assert _gamma_rmse(small.model, run, TS) <= 1.2 * _gamma_rmse(truth, run, TS)


# ---- refusals


def _refusal(u: np.ndarray, y: np.ndarray, T: float, **kw: Any) -> str:
    with pytest.raises(IdentifyError) as info:
        identify(u, y, T, run_filter=False, **kw)
    msg = str(info.value)
    assert "\n" not in msg
    assert isinstance(info.value, MonitorError) and isinstance(info.value, ValueError)
    return msg


def test_refuses_a_constant_voltage() -> None:
    u = np.full((3000, 1), 220.0)
    msg = _refusal(u, capture(dc_motor(), T1, u), T1)
    assert "constant" in msg and "record with the input varying" in msg


def test_refuses_a_sine_for_want_of_persistent_excitation() -> None:
    t = np.arange(3000) * T1
    u = (220.0 + 20.0 * np.sin(2 * np.pi * 0.5 * t))[:, None]
    msg = _refusal(u, capture(dc_motor(), T1, u), T1, kind="dc_motor")
    assert "persistently exciting of order" in msg and "needs 5" in msg


def test_refuses_a_short_capture_and_says_how_long() -> None:
    u = prbs(5.0, T1, level=220.0, amplitude=40.0, clock=0.3, seed=1)
    msg = _refusal(u, capture(dc_motor(), T1, u), T1)
    assert "too short" in msg and "at least 10 s" in msg


def test_refuses_a_capture_with_a_fault_in_the_middle(table1: Table1) -> None:
    _, u, _ = table1
    gamma = np.zeros_like(u)
    gamma[u.shape[0] // 2:] = 0.5  # abrupt 50 % loss of effectiveness
    y = capture(dc_motor(), T1, u, seed=3, gamma=gamma)
    msg = _refusal(u, y, T1)
    assert "fit different models" in msg and "a fault" in msg and "healthy node only" in msg


def test_refuses_non_finite_samples(table1: Table1) -> None:
    _, u, y = table1
    y = y.copy()
    y[250] = np.nan
    msg = _refusal(u, y, T1)
    assert "non-finite" in msg and "2.500 s" in msg


def test_refuses_bad_arguments(table1: Table1) -> None:
    _, u, y = table1
    assert "kind" in _refusal(u, y, T1, kind="arx")
    assert "state_space" in _refusal(np.hstack([u, u]), np.hstack([y, y]), T1,
                                     kind="dc_motor")
    assert "same N" in _refusal(u[:-1], y, T1)


# ---- building blocks


def test_dsim_equals_scipy_dlsim_with_repeated_poles() -> None:
    rng = np.random.default_rng(0)
    A = np.array([[0.9, 1.0, 0.0], [0.0, 0.9, 0.3], [0.0, 0.0, -0.5]])
    B = rng.standard_normal((3, 2))
    C = rng.standard_normal((2, 3))
    u = rng.standard_normal((500, 2))
    x0 = rng.standard_normal(3)
    _, ref, _ = scipy.signal.dlsim((A, B, C, np.zeros((2, 2)), 1.0), u, x0=x0)
    assert np.allclose(dsim(A, B, C, u, x0), ref, atol=1e-10)


def test_inverse_zero_order_hold() -> None:
    model = replace(two_by_two())
    ss = model.standard_form()
    T = 0.05
    Ad = scipy.linalg.expm(ss.A * T)
    Bd = np.linalg.solve(ss.A, (Ad - np.eye(3)) @ ss.B)
    Ac, Bc = d2c(Ad, Bd, T)
    assert np.allclose(Ac, ss.A, atol=1e-9) and np.allclose(Bc, ss.B, atol=1e-9)
    with pytest.raises(IdentifyError, match="negative real axis"):
        d2c(np.array([[-0.5]]), np.array([[1.0]]), T)
    assert math.isfinite(float(Ac[0, 0]))


def test_the_capture_spans_only_time_constants_the_fit_resolves() -> None:
    """A pole at -0.0034 1/s (a 290 s time constant: a sensor offset carried as a
    near-integrating state) whose standard deviation reaches s = 0 asks for no capture of
    ten times 290 s; the same pole well determined does, and a resolved faster pole sets
    the length when the slow one is not."""
    poles = [[-0.0034, 0.0], [-0.8, 0.0], [-160.0, 0.0]]
    real = [-160.0, -0.8, -0.0034]
    unresolved = [5.0, 0.01, 0.004]
    resolved = [5.0, 0.01, 0.0005]
    assert V.resolved_time_constant(poles, real, unresolved) == pytest.approx(1 / 0.8)
    assert V.resolved_time_constant(poles, real, resolved) == pytest.approx(1 / 0.0034)
    assert V.resolved_time_constant(poles, None, None) == pytest.approx(1 / 0.0034)
    assert V.resolved_time_constant([[0.0, 0.0]], None, None) == math.inf
