"""Fuzzy UKF (50)-(54) and the augmented KF baseline follow injected faults."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from experiments.akf import AugmentedKalmanFilter
from monitor.estimation.fuzzy_ukf import FuzzyUKF
from monitor.estimation.model import ContinuousDescriptor, DCMotorParameters, dc_motor
from sim_ecu.plant import SimulatedRun, simulate
from sim_ecu.scenario import load_scenario, scenario_from_dict


def _run(run: SimulatedRun, est: FuzzyUKF, skip: set[int] | None = None) -> np.ndarray:
    g = np.full(len(run.t), np.nan)
    last = -1
    for k in range(len(run.t)):
        if skip and k in skip:
            continue
        dt = (k - last) * run.T if last >= 0 else run.T
        out = est.step(run.u[k], run.y[k], dt)
        g[k] = out.gamma[0]
        last = k
    return g


def _at(run: SimulatedRun, t: float) -> int:
    return round(t / run.T)


def test_gamma_follows_fault_outage_recovery() -> None:
    model = dc_motor()
    run = simulate(model, load_scenario("fault-outage-recovery"), 0.01, seed=11)
    est = FuzzyUKF(model.discretize(0.01), x0=run.x[0])
    g = _run(run, est)
    assert abs(np.mean(g[_at(run, 1):_at(run, 4)])) < 0.03  # fault-free
    assert np.mean(g[_at(run, 5):_at(run, 8)]) == pytest.approx(0.4, abs=0.03)
    assert np.mean(g[_at(run, 9):_at(run, 11)]) == pytest.approx(1.0, abs=0.03)
    assert abs(np.mean(g[_at(run, 12):])) < 0.03  # recovered
    # detection: halfway to the new value within 0.1 s of the 40 % loss
    k = _at(run, 4.0)
    assert np.any(g[k:k + 10] > 0.2)
    assert est.repairs == 0
    assert est.structure_events >= 3  # fault, outage, recovery each restructure
    assert est.out.rules >= 2


def test_no_structure_learning_without_fault() -> None:
    model = dc_motor()
    run = simulate(model, load_scenario("healthy"), 0.01, seed=5)
    est = FuzzyUKF(model.discretize(0.01), x0=run.x[0])
    g = _run(run, est)
    assert est.structure_events <= 1
    assert np.max(np.abs(g[100:])) < 0.1


def test_missed_samples_are_predicted_through() -> None:
    model = dc_motor()
    run = simulate(model, load_scenario("fault-outage-recovery"), 0.01, seed=3)
    rng = np.random.default_rng(0)
    skip = {int(k) for k in rng.choice(len(run.t), size=len(run.t) // 5, replace=False)}
    skip |= set(range(_at(run, 6.0), _at(run, 6.5)))  # a 0.5 s gap of lost frames
    est = FuzzyUKF(model.discretize(0.01), x0=run.x[0])
    g = _run(run, est, skip)
    ok = ~np.isnan(g)
    assert np.all(np.isfinite(est.P)) and est.repairs == 0
    sel = ok & (run.t > 5) & (run.t < 8)
    assert np.mean(g[sel]) == pytest.approx(0.4, abs=0.05)


def test_singular_E_motor_is_estimated() -> None:
    model = dc_motor(DCMotorParameters(La=0.0))
    run = simulate(model, load_scenario("fault-outage-recovery"), 0.01, seed=4)
    est = FuzzyUKF(model.discretize(0.01))
    g = _run(run, est)
    assert np.mean(g[_at(run, 5):_at(run, 8)]) == pytest.approx(0.4, abs=0.05)
    assert abs(np.mean(g[_at(run, 13):])) < 0.05


def test_augmented_kf_follows_the_same_fault() -> None:
    model = dc_motor()
    run = simulate(model, load_scenario("fault-outage-recovery"), 0.01, seed=11)
    akf = AugmentedKalmanFilter(model.discretize(0.01), x0=run.x[0])
    g = np.array([akf.step(run.u[k], run.y[k], 0.01)[0] for k in range(len(run.t))])
    assert np.mean(g[_at(run, 5):_at(run, 8)]) == pytest.approx(0.4, abs=0.03)
    assert np.mean(g[_at(run, 9):_at(run, 11)]) == pytest.approx(1.0, abs=0.03)


def test_two_actuators_two_outputs() -> None:
    # Two independent first-order drives measured separately: each loss is estimated.
    m = ContinuousDescriptor(
        E=np.eye(2), A=np.diag([-2.0, -5.0]), B=np.eye(2), C=np.eye(2),
        Qc=np.eye(2) * 0.01, R=np.eye(2) * 0.01, state_names=("a", "b"),
        input_names=("u1", "u2"), output_names=("y1", "y2"),
    )
    sc = scenario_from_dict({
        "name": "two", "duration": 6.0, "actuators": 2, "noise": {"current_sigma": 0.1},
        "voltage": {"steps": [[0.0, 10.0]]},
        "fault": [{"start": 2.0, "gamma": 0.5, "actuator": 1}],
    })
    run = simulate(m, sc, 0.01, seed=1)
    est = FuzzyUKF(m.discretize(0.01), x0=run.x[0])
    gs = np.array([est.step(run.u[k], run.y[k], 0.01).gamma.copy() for k in range(len(run.t))])
    assert np.mean(gs[-100:, 0]) == pytest.approx(0.0, abs=0.05)
    assert np.mean(gs[-100:, 1]) == pytest.approx(0.5, abs=0.05)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), T=st.sampled_from([0.001, 0.01, 0.05]))
def test_random_motors_stay_finite_and_psd(seed: int, T: float) -> None:
    rng = np.random.default_rng(seed)
    params = DCMotorParameters(
        J=rng.uniform(0.001, 0.1), b=rng.uniform(0.01, 0.5), Ke=rng.uniform(0.05, 1),
        Ki=rng.uniform(0.05, 1), Ra=rng.uniform(0.2, 5), La=float(rng.choice([0.0, 0.5, 2.0])),
    )
    model = dc_motor(params, q=float(rng.uniform(0, 5)), r=float(rng.uniform(0.01, 1)))
    est = FuzzyUKF(model.discretize(T))
    for _ in range(300):
        u = rng.uniform(-300, 300)
        y = rng.normal(0, 100)
        out = est.step([u], [y], T * int(rng.integers(1, 4)))
        assert np.all(np.isfinite(out.gamma)) and 0.0 <= out.gamma[0] <= 1.0
    assert np.all(np.isfinite(est.P))
    assert np.min(np.linalg.eigvalsh(est.P)) > 0
    assert np.array_equal(est.P, est.P.T)


def test_bad_dt_is_rejected() -> None:
    est = FuzzyUKF(dc_motor().discretize(0.01))
    with pytest.raises(ValueError, match="dt"):
        est.step([220.0], [0.0], 0.0)
