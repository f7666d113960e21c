"""Coulomb friction for `identify`: the friction's input phi of (1) on a capture, as the
monitor's estimator will compute it (`monitor.estimation.friction`).

A linear fit of a drive with Coulomb friction misses a term of constant size that follows
the sign of the speed; the monitor then reads each reversal as a change of the input's
effect (gamma^ 0.25 to 0.64 on healthy captures of the rig zoo). phi is not measured: it
depends on the speed, which the model estimates. So the fit alternates (a fixed-point
iteration, as output-error fits of Hammerstein-type models do): the capture's phi from the
current model's steady-state Kalman filter, stepped the way the monitor steps (the held
input of sample k - d over the step to sample k, phi from the estimate at the step's start
by `friction_speed`, the kernel's own rule), then the black box refitted with phi as a second,
known input. `width` is the sample-to-sample noise of the first model's speed estimate:
within it the estimate does not know the speed's sign.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from monitor.estimation.friction import friction_code, friction_speed, speed_row
from monitor.estimation.model import ContinuousDescriptor
from monitor.identify.lti import kalman, steady_state_x0
from monitor.pipeline.samples import delayed, no_past

Array = NDArray[np.float64]

__all__ = ["FRICTION_ITERATIONS", "filtered_states", "friction_column", "speed_estimate"]

FRICTION_ITERATIONS = 4
"""Refits of the friction's fixed-point iteration: on the rig zoo's friction seeds the
hold-out fit settles within 0.5 points after three."""


def _filter(model: ContinuousDescriptor, m: int, held: Array, y: Array, T: float,
            delay: int, speed: str, width: float) -> tuple[Array, Array, Array]:
    """The speed v (`friction_speed`), phi of every step and the filtered states x(k|k),
    from the model's steady-state Kalman filter over the rows (held inputs, outputs)
    paired with input delay `delay`; phi[k] acts over the step to sample k (phi[0] = 0).
    The friction is the model's own (`model.friction`: its speed and width then replace
    the arguments), else its inputs beyond the first m (a model of a refit), else none."""
    dm = model.discretize(T)
    A, Bm, Qd = dm.at(T)
    C = dm.C
    kf = kalman(A, C, Qd, dm.R)
    # the filtered (posterior) gain of the predictor's: K_f = P C' S^-1
    Kf = kf.P @ C.T @ np.linalg.inv(kf.S)
    B = Bm[:, :m]
    F = Bm[:, m] if Bm.shape[1] > m else dm.friction_at(T)
    output = 0
    if model.friction is not None:
        speed, width, output = model.friction.speed, model.friction.width, \
            model.friction.output
    u, _ = delayed(held[:, :m], delay, no_past(m))
    N = y.shape[0]
    S = speed_row(C, output, A.shape[0])
    code = friction_code(speed)
    x = steady_state_x0(A, B, C, u[0], y[0])
    x = x + Kf @ (y[0] - C @ x)
    v = np.zeros(N)
    phi = np.zeros(N)
    X = np.empty((N, A.shape[0]))
    X[0] = x
    for k in range(1, N):
        b = B @ u[k]
        v[k] = friction_speed(A, b, x, S, code, T)
        phi[k] = -math.tanh(v[k] / width)
        x = A @ x + b + F * phi[k]
        x = x + Kf @ (y[k] - C @ x)
        X[k] = x
    return v, phi, X


def filtered_states(model: ContinuousDescriptor, held: Array, y: Array, T: float,
                    delay: int) -> Array:
    """x(k|k) of the model with its friction over the rows: the trajectory a loss is
    added to (`monitor.app.identify_check.loss_effect`)."""
    fr = model.friction
    return _filter(model, held.shape[1], held, y, T, delay,
                   fr.speed if fr else "output", fr.width if fr else 1.0)[2]


def speed_estimate(model: ContinuousDescriptor, held: Array, y: Array, T: float, delay: int,
                   speed: str) -> tuple[Array, float]:
    """The linear model's speed over each step (`friction_speed`) and the friction's
    width: the standard deviation of its sample-to-sample changes."""
    v, _, _ = _filter(model, held.shape[1], held, y, T, delay, speed, 1.0)
    width = float(np.std(np.diff(v[1:]))) if v.size > 2 else 0.0
    return v, width if math.isfinite(width) and width > 0 else 1.0


def friction_column(model: ContinuousDescriptor, m: int, held: Array, y: Array, T: float,
                    delay: int, speed: str, width: float) -> Array:
    """phi of (1) on the capture from `model` (its inputs beyond m: a friction already
    fitted) as a held input column: row i holds the phi of the step to sample i + delay,
    so that `fit_rows` (which pairs row j + 1 - delay with the step from j to j + 1) gives
    every step its own phi, undelayed."""
    _, phi, _ = _filter(model, m, held, y, T, delay, speed, width)
    N = phi.size
    idx = np.clip(np.arange(N) + delay, 0, N - 1)
    return np.asarray(phi[idx], dtype=np.float64)
