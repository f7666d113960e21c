"""The structure test's slow average (`monitor.estimation.kernel`, step 5): a loss whose
effect on the output grows over many samples is found sooner with it than with the short
average alone, the per-frame and columnar paths give the same samples with it, and a jump
it cannot tell from zero starts no event; its spread does not learn the change it is
building up to find."""

from __future__ import annotations

import numpy as np

from monitor.diagnosis import DEFAULT_THRESHOLDS, HealthState, OnlineClassifier
from monitor.estimation.fuzzy_ukf import FuzzyUKF, FuzzyUKFConfig
from monitor.estimation.model import dc_motor
from sim_ecu.plant import simulate
from sim_ecu.scenario import scenario_from_dict
from tests.bench.realistic_identify import excitation

T = 0.01
ONSET = 3.0


def _delay(volts: float, seed: int, cfg: FuzzyUKFConfig, onset: float = ONSET,
           steps: list[list[float]] | None = None) -> float:
    """Onset to the first fault report of a loss of 0.3 on the paper's motor at `volts`
    (or under the voltage `steps`, [time, volts] each)."""
    model = dc_motor()
    sc = scenario_from_dict({"name": "slow", "duration": onset + 3.0,
                             "fault": [{"start": onset, "gamma": 0.3}],
                             "noise": {"current_sigma": 0.5},
                             "voltage": {"steps": steps or [[0.0, volts]]}})
    run = simulate(model, sc, T, seed=seed)
    est = FuzzyUKF(model.discretize(T), cfg)
    clf = OnlineClassifier(DEFAULT_THRESHOLDS, dwell_s=0.03, hysteresis=0.02)
    for k in range(run.t.size):
        out = est.step(run.u[k], run.y[k], T)
        clf.update(float(run.t[k]), float(out.gamma[0]))
        if clf.state in (HealthState.FAULT, HealthState.OUTAGE):
            assert run.t[k] >= onset, "a false alarm before the loss"
            return float(run.t[k]) - onset
    return np.inf


def test_a_loss_that_shows_slowly_is_found_sooner_with_the_slow_average() -> None:
    # At 100 V a loss of 0.3 takes 30 V from an armature whose current answers in La/Ra =
    # 1 s: the innovations' mean moves by about one noise unit a sample, which no 50 ms
    # window of the short average holds above its threshold, and gamma^'s own recursive
    # least squares takes part of it up as it comes (the accuracy benchmark's
    # low-voltage-fault: 0.38 s without the slow average)
    with_slow = [_delay(100.0, s, FuzzyUKFConfig()) for s in range(16)]
    without = [_delay(100.0, s, FuzzyUKFConfig(slow_window=0.0)) for s in range(16)]
    assert np.all(np.isfinite(with_slow)) and np.all(np.isfinite(without))
    assert sum(d > 0.3 for d in with_slow) < sum(d > 0.3 for d in without)  # 6 against 8
    assert np.median(with_slow) < np.median(without)  # 0.25 s against 0.29 s
    # where the short average finds the loss first, the slow one changes nothing
    fast = [_delay(220.0, s, FuzzyUKFConfig()) for s in range(4)]
    assert fast == [_delay(220.0, s, FuzzyUKFConfig(slow_window=0.0)) for s in range(4)]


def test_the_columnar_path_runs_the_slow_average_as_the_per_frame_one() -> None:
    model = dc_motor()
    sc = scenario_from_dict({"name": "slow", "duration": 6.0,
                             "fault": [{"start": ONSET, "gamma": 0.3}],
                             "noise": {"current_sigma": 0.5},
                             "voltage": {"steps": [[0.0, 100.0]]}})
    run = simulate(model, sc, T, seed=2)
    one = FuzzyUKF(model.discretize(T))
    gamma = np.array([float(one.step(run.u[k], run.y[k], T).gamma[0])
                      for k in range(run.t.size)])
    many = FuzzyUKF(model.discretize(T))
    got = many.step_many(run.u, run.y, np.full(run.t.size, T))
    assert one.structure_events >= 1
    assert many.structure_events == one.structure_events
    np.testing.assert_array_equal(got.gamma[:, 0], gamma)


def test_a_jump_the_slow_average_cannot_tell_from_zero_starts_no_event() -> None:
    # the gate of structure.py: the located jump less one posterior standard deviation
    # must reach slow_min_jump; a jump of 0.3 located to +-0.05 does, one of 0.12 does not
    est = FuzzyUKF(dc_motor().discretize(T))
    zero = np.zeros(1)
    least = est.config.slow_min_jump
    assert not est._negligible(zero, np.array([0.3]), least, np.array([0.05]))
    assert est._negligible(zero, np.array([0.12]), least, np.array([0.05]))
    # the bounds of (28) first: a jump that would take gamma^ below 0 moves it by 0.02
    assert est._negligible(np.array([0.02]), np.array([-0.5]), least, np.array([0.01]))
    # the short average's events keep the plain least jump
    assert not est._negligible(zero, np.array([0.05]), est.config.min_jump)


def test_the_spread_does_not_learn_a_change_that_builds_up() -> None:
    # Under a stepping input gamma^ follows part of a loss at each step, and the slow
    # average builds up over several of its windows. Its statistic is in units of its own
    # long-run spread; while the spread learnt from every sample the short test passed, it
    # grew with the change and the statistic stayed under its threshold: these two losses
    # were reported after 0.49 s and 1.41 s, now 0.27 s and 0.22 s (the true model, so a
    # fit's error plays no part; the voltage steps as the realistic runs after identify
    # record a healthy minute)
    for seed, onset in ((3, 5.0), (5, 7.0)):
        delay = _delay(0.0, seed, FuzzyUKFConfig(), onset, excitation(220.0, onset + 3.0, seed))
        assert delay <= 0.3, (seed, onset, delay)
