"""Coulomb friction in the model (`monitor.estimation.friction`): a speed that reverses under
a torque of constant size against it. Without the friction in the model the estimator
reads every reversal as a change of the input's effect and gamma^ climbs to a false alarm
on a healthy drive (the rig zoo's friction seeds: gamma^ 0.25 to 0.64 on healthy captures);
with it gamma^ stays near 0, a real loss is still read, and the compiled loop of many
samples gives what the sample-by-sample step gives."""

from __future__ import annotations

import math

import numpy as np
import pytest

from monitor.estimation.friction import Friction
from monitor.estimation.fuzzy_ukf import FuzzyUKF
from monitor.estimation.model import ContinuousDescriptor, ModelError, zoh
from monitor.identify import prbs

T = 0.005
J, B_VISC, COULOMB = 0.01, 0.05, 0.15  # kg m^2, N m s, N m: a torque in, a speed out
WIDTH = 0.05  # rad/s
SIGMA = 0.01  # rad/s, the speed sensor's noise


def _model(friction: bool) -> ContinuousDescriptor:
    return ContinuousDescriptor(
        E=np.eye(1), A=np.array([[-B_VISC / J]]), B=np.array([[1.0 / J]]),
        C=np.array([[1.0]]), Qc=np.array([[1e-4]]), R=np.array([[SIGMA**2]]),
        state_names=("w",), input_names=("torque",), output_names=("speed",),
        friction=Friction(B=np.array([COULOMB / J]), speed="output", output=0, width=WIDTH)
        if friction else None)


def _capture(gamma_from: float | None = None, seconds: float = 40.0
             ) -> tuple[np.ndarray, np.ndarray]:
    """The drive under a torque PRBS around 0 (the speed reverses at every switch), its
    friction -T_c tanh(w / WIDTH) integrated on a grid 20 times finer; from `gamma_from` s
    on the actuator delivers 0.6 of its command."""
    u = prbs(seconds, T, level=0.0, amplitude=1.0, clock=0.4, seed=5)
    sub = 20
    h = T / sub
    w = 0.0
    ys = np.empty(u.shape[0])
    for k in range(u.shape[0]):
        ys[k] = w
        g = 0.4 if gamma_from is not None and k * T >= gamma_from else 0.0
        for _ in range(sub):
            w += h * (-B_VISC * w + (1.0 - g) * u[k + 1 if k + 1 < u.shape[0] else k, 0]
                      - COULOMB * math.tanh(w / WIDTH)) / J
    y = ys[:, None] + np.random.default_rng(3).normal(0.0, SIGMA, (u.shape[0], 1))
    # the step to sample k + 1 took u[k + 1]: the input held at the sample it ends at, as
    # the estimator's step with input delay 0 applies it
    return u, y


def _gamma(model: ContinuousDescriptor, u: np.ndarray, y: np.ndarray) -> np.ndarray:
    est = FuzzyUKF(model.discretize(T))
    return np.array([est.step(u[k], y[k], T).gamma[0] for k in range(u.shape[0])])


def test_friction_the_model_lacks_reads_as_a_loss_and_the_friction_model_holds() -> None:
    u, y = _capture()
    skip = round(2.0 / T)
    assert _gamma(_model(False), u, y)[skip:].max() > 0.15  # a false alarm
    assert _gamma(_model(True), u, y)[skip:].max() < 0.1


def test_a_loss_is_still_read_with_friction() -> None:
    u, y = _capture(gamma_from=20.0)
    g = _gamma(_model(True), u, y)
    after = g[round(21.0 / T):]
    assert np.median(after) == pytest.approx(0.4, abs=0.08)
    assert g[round(2.0 / T):round(20.0 / T)].max() < 0.1


def test_many_samples_at_once_as_one_by_one() -> None:
    u, y = _capture(gamma_from=20.0, seconds=25.0)
    one = FuzzyUKF(_model(True).discretize(T))
    g1 = np.array([one.step(u[k], y[k], T).gamma[0] for k in range(u.shape[0])])
    many = FuzzyUKF(_model(True).discretize(T))
    res = many.step_many(u, y, np.full(u.shape[0], T))
    np.testing.assert_allclose(res.gamma[:, 0], g1, rtol=0, atol=1e-12)


def test_the_friction_column_is_held_over_the_step_as_an_input() -> None:
    dm = _model(True).discretize(T)
    _, Fd = zoh(np.array([[-B_VISC / J]]), np.array([[COULOMB / J]]), 2 * T)
    np.testing.assert_allclose(dm.friction_at(2 * T), Fd[:, 0])
    np.testing.assert_array_equal(_model(False).discretize(T).friction_at(T), [0.0])


@pytest.mark.parametrize(("friction", "needle"), [
    (Friction(B=np.array([1.0]), speed="velocity", output=0, width=0.1),
     "speed must be one of output, rate"),
    (Friction(B=np.array([1.0]), speed="rate", output=1, width=0.1),
     "output must be an output index from 0 to 0"),
    (Friction(B=np.array([1.0]), speed="rate", output=0, width=0.0),
     "width must be a positive number"),
    (Friction(B=np.array([1.0, 2.0]), speed="rate", output=0, width=0.1),
     "B has 2 columns, A has 1 states"),
    (Friction(B=np.array([math.nan]), speed="rate", output=0, width=0.1),
     "B contains NaN"),
])
def test_a_wrong_friction_is_one_line(friction: Friction, needle: str) -> None:
    with pytest.raises(ModelError) as err:
        ContinuousDescriptor(
            E=np.eye(1), A=np.array([[-1.0]]), B=np.array([[1.0]]), C=np.array([[1.0]]),
            Qc=np.array([[1.0]]), R=np.array([[0.01]]), state_names=("x",),
            friction=friction)
    assert needle in str(err.value) and "\n" not in str(err.value)
    assert err.value.key == "friction"
