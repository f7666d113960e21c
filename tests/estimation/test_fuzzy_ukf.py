"""Fuzzy UKF (50)-(54) and the augmented KF baseline follow injected faults."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
import scipy.signal
from hypothesis import given, settings
from hypothesis import strategies as st

from experiments.akf import AugmentedKalmanFilter, AugmentedKFConfig
from monitor.estimation.fuzzy import FuzzyConfig
from monitor.estimation.fuzzy_ukf import FuzzyUKF, FuzzyUKFConfig, initial_covariance
from monitor.estimation.model import (
    ContinuousDescriptor,
    DCMotorParameters,
    DiscreteModel,
    dc_motor,
    van_loan,
)
from sim_ecu.plant import PlantSimulator, SimulatedRun, simulate, steady_state
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


# ---- general linear actuator models (issue 9): MIMO plants, discrete models, known inputs

def _mimo(**kw: object) -> ContinuousDescriptor:
    """A coupled 2x2 plant: each actuator drives both states, with a small feed-through."""
    base: dict[str, object] = dict(
        E=np.eye(2), A=[[-2.0, 0.5], [0.3, -3.0]], B=[[1.0, 0.2], [0.1, 1.0]], C=np.eye(2),
        D=[[0.05, 0.0], [0.0, 0.02]], Qc=np.eye(2) * 0.01, R=np.eye(2) * 0.01,
        state_names=("a", "b"), input_names=("u1", "u2"), output_names=("y1", "y2"),
    )
    base.update(kw)
    return ContinuousDescriptor(**base)  # type: ignore[arg-type]


def _simulate_inputs(model: ContinuousDescriptor, T: float, U: np.ndarray,
                     gamma: Callable[[float], np.ndarray], seed: int, sigma: float = 0.1,
                     ) -> np.ndarray:
    """Measured outputs of the plant under inputs U (one row per sample) and gamma(t),
    starting from the fault-free steady state of U[0]."""
    sim = PlantSimulator(model, T, seed=seed, current_sigma=sigma)
    sim.x = steady_state(sim, U[0])
    Y = np.empty((len(U), model.C.shape[0]))
    for k, u in enumerate(U):
        g = gamma(k * T)
        Y[k] = sim.output(u, g)
        sim.advance(u, g)
    return Y


@pytest.mark.parametrize("faulty", [0, 1])
def test_coupled_two_actuator_plant_finds_the_faulty_actuator(faulty: int) -> None:
    model = _mimo()
    T = 0.01

    def gamma(t: float) -> np.ndarray:
        g = np.zeros(2)
        g[faulty] = 0.4 if t >= 2.0 else 0.0
        return g

    U = np.tile([10.0, 6.0], (600, 1))
    Y = _simulate_inputs(model, T, U, gamma, seed=20 + faulty)
    est = FuzzyUKF(model.discretize(T))
    gs = np.array([est.step(U[k], Y[k], T).gamma.copy() for k in range(len(U))])
    before, after = gs[100:200], gs[-200:]
    # gamma is projected onto [0, 1], so noise biases a fault-free estimate slightly up
    assert np.all(before.mean(axis=0) < 0.05)
    assert after[:, faulty].mean() == pytest.approx(0.4, abs=0.04)
    assert after[:, 1 - faulty].mean() < 0.05
    assert est.repairs == 0


def test_discrete_model_gives_the_filter_of_its_continuous_model() -> None:
    # The same plant given at its sample period T: the inverse zero-order hold makes it the
    # continuous model again, so the filters agree to round-off at T and at 2 T.
    cont = dc_motor()
    T = 0.01
    ss = cont.standard_form()
    Ad, Bd, _, _, _ = scipy.signal.cont2discrete((ss.A, ss.B, ss.C, ss.D), T, method="zoh")
    Qd = van_loan(ss.A, cont.noise_standard_form(), T)
    disc = DiscreteModel.from_discrete(Ad, Bd, ss.C, Qd, cont.R, T, D=ss.D,
                                       state_names=ss.state_names)
    assert disc.observable_names == ("current", "speed")
    run = simulate(cont, load_scenario("fault-outage-recovery"), T, seed=9)
    for stride in (1, 2):
        a = FuzzyUKF(cont.discretize(T), x0=run.x[0])
        b = FuzzyUKF(disc, x0=run.x[0])
        for k in range(0, len(run.t), stride):
            oa = a.step(run.u[k], run.y[k], stride * T)
            ob = b.step(run.u[k], run.y[k], stride * T)
            assert ob.gamma == pytest.approx(oa.gamma, abs=1e-9)
            assert ob.x_hat == pytest.approx(oa.x_hat, rel=1e-9, abs=1e-9)
            assert ob.rules == oa.rules and ob.structure_event == oa.structure_event
        assert a.structure_events == b.structure_events >= 3


def _motor_with_load() -> ContinuousDescriptor:
    """The DC motor (68) with a second, known input: a measured load torque on the shaft."""
    m = dc_motor()
    return ContinuousDescriptor(
        E=m.E, A=m.A, B=np.hstack([m.B, [[0.0], [-1.0], [0.0]]]), C=m.C, Qc=m.Qc, R=m.R,
        state_names=m.state_names, input_names=("voltage", "load"),
        output_names=m.output_names, fault_inputs=("voltage",),
    )


def test_known_actuator_keeps_gamma_exactly_zero() -> None:
    # Two inputs, one output: allowed because only the voltage can lose effectiveness. The
    # known load torque varies; the filter is told it, so it is no fault.
    model = _motor_with_load()
    T = 0.01
    t = np.arange(800) * T
    U = np.column_stack([np.full(t.size, 220.0), 2.0 + 1.5 * np.sin(t)])
    Y = _simulate_inputs(model, T, U, lambda s: np.array([0.4 if s >= 4 else 0.0, 0.0]),
                         seed=3, sigma=0.5)
    est = FuzzyUKF(model.discretize(T))
    gs = np.array([est.step(U[k], Y[k], T).gamma.copy() for k in range(len(Y))])
    assert np.all(gs[:, 1] == 0.0)
    assert gs[100:400, 0].mean() < 0.05
    assert gs[-300:, 0].mean() == pytest.approx(0.4, abs=0.04)
    assert np.all(est.fuzzy.var[:, 1] == 0.0)
    assert est.structure_events >= 1
    healthy = _simulate_inputs(model, T, U, lambda s: np.zeros(2), seed=4, sigma=0.5)
    est = FuzzyUKF(model.discretize(T))
    gh = np.array([est.step(U[k], healthy[k], T).gamma.copy() for k in range(len(U))])
    assert np.max(np.abs(gh[100:, 0])) < 0.1 and np.all(gh[:, 1] == 0.0)


def test_two_actuator_plant_with_one_fault_input_leaves_the_other_at_zero() -> None:
    model = _mimo(fault_inputs=(1,))
    T = 0.01
    U = np.tile([10.0, 6.0], (600, 1))
    Y = _simulate_inputs(model, T, U, lambda t: np.array([0.0, 0.5 if t >= 2 else 0.0]),
                         seed=5)
    est = FuzzyUKF(model.discretize(T))
    gs = np.array([est.step(U[k], Y[k], T).gamma.copy() for k in range(len(U))])
    assert np.all(gs[:, 0] == 0.0)
    assert gs[-200:, 1].mean() == pytest.approx(0.5, abs=0.04)


# ---- the sound core: one rule is the augmented Kalman filter; stiff plants; start-up

def _servo_run(seed: int = 1) -> tuple[ContinuousDescriptor, SimulatedRun]:
    """The 24 V servo of tests/rigs/servo.toml at 1 kHz, sensor sigma 0.01 A: 40 % loss at
    2 s, outage at 4 s."""
    p = DCMotorParameters(J=2e-5, b=1e-5, Ke=0.03, Ki=0.03, Ra=1.0, La=1e-3)
    model = dc_motor(p, q=1e-4, r=0.01**2)
    sc = scenario_from_dict({
        "name": "servo", "duration": 6.0, "noise": {"current_sigma": 0.01},
        "voltage": {"steps": [[0.0, 24.0]]},
        "fault": [{"start": 2.0, "end": 4.0, "gamma": 0.4}, {"start": 4.0, "gamma": 1.0}],
    })
    return model, simulate(model, sc, 1e-3, seed=seed)


@pytest.mark.parametrize("plant", ["table1", "servo"])
def test_one_rule_is_the_augmented_kalman_filter(plant: str) -> None:
    # One rule, no structure learning, no projection, no random walk, the model's R: the
    # consequent's RLS with the two-stage coupling x^ += V dgamma is the augmented KF's
    # gamma update.
    if plant == "servo":
        model, run = _servo_run()
        T = 1e-3
    else:
        model = dc_motor()
        run = simulate(model, load_scenario("fault-outage-recovery"), 0.01, seed=11)
        T = 0.01
    cfg = FuzzyUKFConfig(q_gamma=0.0, var0=0.1, var_rule=0.0, nis_threshold=math.inf,
                         slow_window=0.0,
                         fuzzy=FuzzyConfig(initial_mf=((0.0,), (0.0,)), max_mf=1,
                                           lower=-10.0, upper=10.0), adaptive_noise=False,
                         bias="none")  # the AKF has no bias states (step 8)
    md = model.discretize(T)
    fz = FuzzyUKF(md, cfg, x0=run.x[0])
    akf = AugmentedKalmanFilter(md, AugmentedKFConfig(q_gamma=0.0, P0_gamma=0.1), x0=run.x[0])
    for k in range(len(run.t)):
        o = fz.step(run.u[k], run.y[k], T)
        g = akf.step(run.u[k], run.y[k], T)
        assert o.gamma[0] == pytest.approx(g[0], abs=1e-9)
        assert o.x_hat == pytest.approx(akf.x, rel=1e-9, abs=1e-9)
    assert fz.structure_events == 0


def test_stiff_plant_first_innovation_does_not_throw_the_state() -> None:
    # The first sample after the servo's 40 % loss is 600 sigma off. gamma^ must not jump
    # to an outage, the speed estimate must not jump to the outage's steady state, and the
    # NIS must come back to 1.
    model, run = _servo_run()
    est = FuzzyUKF(model.discretize(1e-3))
    g = np.empty(len(run.t))
    speed_err = np.empty(len(run.t))
    nis = np.empty(len(run.t))
    for k in range(len(run.t)):
        out = est.step(run.u[k], run.y[k], 1e-3)
        g[k] = out.gamma[0]
        speed_err[k] = out.x_hat[1] - run.x[k, 1]
        nis[k] = out.nis
    k = _at(run, 2.0)
    assert np.max(g[k:k + 100]) < 0.5
    assert np.mean(g[_at(run, 2.05):_at(run, 4.0)]) == pytest.approx(0.4, abs=0.01)
    assert np.mean(g[_at(run, 4.1):]) == pytest.approx(1.0, abs=0.01)
    assert np.max(np.abs(speed_err[_at(run, 0.5):])) < 30.0  # of 790 rad/s
    assert np.mean(nis[_at(run, 2.2):_at(run, 4.0)]) == pytest.approx(1.0, abs=0.15)
    assert est.structure_events == 2 and est.repairs == 0


def test_structure_event_relearns_from_the_onset() -> None:
    # A loss that builds up slowly in the output is detected some samples late; the event
    # goes back to the onset (the Willsky-Jones likelihood over the ring) and re-learns
    # from there, so gamma^ is right within a few samples of the detection.
    J, b, Ki = 1e-4, 1e-4, 0.05
    E = np.diag([J, 1.0])
    model = ContinuousDescriptor(E=E, A=np.array([[-b, 0.0], [1.0, 0.0]]),
                                 B=np.array([[Ki], [0.0]]), C=np.array([[1.0, 0.0]]),
                                 Qc=E @ (1e-4 * np.eye(2)) @ E, R=np.array([[0.04]]),
                                 state_names=("speed", "angle"))
    T = 0.002
    sc = scenario_from_dict({
        "name": "speed", "duration": 3.0, "noise": {"current_sigma": 0.2},
        "voltage": {"steps": [[0.0, 1.0]]}, "fault": [{"start": 1.0, "gamma": 0.4}],
    })
    run = simulate(model, sc, T, seed=3)
    est = FuzzyUKF(model.discretize(T))
    onsets: list[int] = []
    locate = est._onset

    def spy(k: int) -> tuple[int, np.ndarray, np.ndarray, float,
                             tuple[np.ndarray, np.ndarray, np.ndarray]]:
        found = locate(k)
        onsets.append(found[0])
        return found

    est._onset = spy  # type: ignore[method-assign]
    g = np.array([est.step(run.u[k], run.y[k], T).gamma[0] for k in range(len(run.t))])
    assert est.structure_events == 1
    true_onset = _at(run, 1.0) + 1  # the first sample the loss acts on
    assert abs(onsets[0] - true_onset) <= 2
    detected = int(np.argmax(g > 0.2))
    assert np.all(np.abs(g[detected + 5:] - 0.4) < 0.02)


def test_augmented_kf_starts_from_the_steady_state() -> None:
    # Without x0 the baseline starts where the fuzzy UKF does (the fault-free steady state
    # of the first input, coupled to the unknown gamma), not from x = 0 with P0 = 1.
    model, run = _servo_run()
    akf = AugmentedKalmanFilter(model.discretize(1e-3))
    g = np.array([akf.step(run.u[k], run.y[k], 1e-3)[0] for k in range(len(run.t))])
    assert np.max(np.abs(g[:_at(run, 2.0)])) < 0.05
    assert np.mean(g[_at(run, 2.2):_at(run, 4.0)]) == pytest.approx(0.4, abs=0.01)


def test_scale_aware_initial_covariance() -> None:
    # P0 = None: the stationary Kalman covariance, in the state's own units.
    model, _ = _servo_run()
    md = model.discretize(1e-3)
    P = initial_covariance(md)
    assert np.all(np.linalg.eigvalsh(P) > 0)
    assert P[0, 0] < 1e-3 ** 2 * 100  # the current, measured to 0.01 A, known to 1 mA or so
    est = FuzzyUKF(md)
    n = md.n  # the plant's states; the bias states (step 8) follow them
    assert np.array_equal(est.P[:n, :n], P)
    assert np.array_equal(FuzzyUKF(md, FuzzyUKFConfig(P0=1.0)).P[:n, :n], np.eye(2))


@pytest.mark.parametrize("chunk", [1, 37, 1000])
def test_step_many_is_step_row_by_row_with_events_and_loss(chunk: int) -> None:
    """step_many returns to Python for the structure events (onset search, re-processing)
    and must leave the estimator, and report every sample, exactly as step() does -- with
    lost samples (dt = k T) among them."""

    model = dc_motor()
    sc = scenario_from_dict({"name": "many", "duration": 6.0,
                             "fault": [{"start": 2.0, "end": 4.0, "gamma": 0.4}],
                             "noise": {"current_sigma": 0.5},
                             "voltage": {"steps": [[0.0, 220.0]]}})
    run = simulate(model, sc, 0.01, seed=4)
    keep = np.random.default_rng(4).random(len(run.t)) >= 0.2
    keep[0] = True
    idx = np.flatnonzero(keep)
    dt = np.diff(idx, prepend=-1) * 0.01
    u, y = run.u[idx], run.y[idx]
    disc = model.discretize(0.01)
    a, b = FuzzyUKF(disc), FuzzyUKF(disc)
    rows = [(o.gamma.copy(), o.gamma_sd.copy())
            for o in (a.step(u[k], y[k], float(dt[k])) for k in range(len(dt)))]
    g = np.array([r[0] for r in rows])
    gsd = np.array([r[1] for r in rows])
    parts = [b.step_many(u[s:s + chunk], y[s:s + chunk], dt[s:s + chunk])
             for s in range(0, len(dt), chunk)]
    assert a.structure_events > 0
    np.testing.assert_array_equal(np.concatenate([p.gamma for p in parts]), g)
    np.testing.assert_array_equal(np.concatenate([p.gamma_sd for p in parts]), gsd)
    assert sum(int(p.structure_event.sum()) for p in parts) == a.structure_events
    np.testing.assert_array_equal(a._st, b._st)
    assert a.steps == b.steps and a._time == b._time


def test_gamma_variance_does_not_wind_up_while_the_output_shows_nothing_of_it() -> None:
    # At 0 V the current carries no information on the loss (M = 0): the random walk (54)
    # may not widen gamma's variance for lack of evidence ("covariance windup"), or the
    # first noisy samples after the next command move gamma^ by as much as that variance
    # allows: a healthy motor idle for 30 s then restarted read 0.35-0.54 (seeds 0-3)
    model = dc_motor()
    run = simulate(model, scenario_from_dict({
        "name": "idle", "duration": 40.0,
        "voltage": {"steps": [[0.0, 220.0], [5.0, 0.0], [35.0, 220.0]]}}), 0.01, seed=0)
    est = FuzzyUKF(model.discretize(0.01), x0=run.x[0])
    held: list[float] = []
    g = np.zeros(len(run.t))
    for k in range(len(run.t)):
        g[k] = est.step(run.u[k], run.y[k], run.T).gamma[0]
        if k in (_at(run, 4.9), _at(run, 34.9)):
            held.append(float(est.common_var[0]))
    before, after = held
    assert after < 10 * before  # q_gamma * 30 s would add 0.15: 200 times
    k = _at(run, 35.0)
    assert np.max(np.abs(g[k:k + 100])) < 0.12  # the alarm threshold f1 is 0.15


def test_gamma_sd_is_the_consequents_spread_and_narrows_with_evidence() -> None:
    """The standard deviation the diagnosis weighs an alarm by: sqrt of the common
    variance plus the firing rules' own, wide after a structure event re-opens gamma and
    narrowing as the outputs show the loss; 0 for a known actuator."""
    model = dc_motor()
    sc = scenario_from_dict({"name": "sd", "duration": 4.0,
                             "fault": [{"start": 2.0, "gamma": 0.4}],
                             "noise": {"current_sigma": 0.5},
                             "voltage": {"steps": [[0.0, 220.0]]}})
    run = simulate(model, sc, 0.01, seed=5)
    est = FuzzyUKF(model.discretize(0.01), x0=run.x[0])
    sd = np.zeros(len(run.t))
    events = []
    for k in range(len(run.t)):
        out = est.step(run.u[k], run.y[k], run.T)
        sd[k] = out.gamma_sd[0]
        assert sd[k] >= np.sqrt(est.common_var[0]) - 1e-15
        if out.structure_event:
            events.append(k)
    assert events, "the loss fires the structure test"
    k = events[-1]
    assert sd[k] > 2.0 * sd[_at(run, 1.9)]  # re-opened
    assert sd[-1] < 0.5 * sd[k]  # the loss shows: evidence narrows it


def test_gamma_sd_at_a_start_from_the_first_output() -> None:
    """A start from what the first output says (no kernel call on that sample) gives
    gamma^'s spread of the start, sqrt(var_start), not a stale 0."""
    model = dc_motor().discretize(0.01)
    est = FuzzyUKF(model)
    out = est.step(np.array([220.0]), np.array([0.0]), 0.01)  # a motor at rest: no steady state
    assert out.gamma_sd[0] == pytest.approx(np.sqrt(est.config.var_start))
