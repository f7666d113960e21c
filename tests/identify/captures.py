"""Seeded, noisy captures of simulated plants (sim_ecu.plant) for the identification tests."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from monitor.estimation.model import ContinuousDescriptor, DCMotorParameters
from sim_ecu.plant import PlantSimulator, steady_state

Array = NDArray[np.float64]

# A small 24 V servo-class motor (sampled at 1 kHz in the tests).
SMALL_MOTOR = DCMotorParameters(J=2e-5, b=1e-5, Ke=0.03, Ki=0.03, Ra=1.0, La=1e-3)


def capture(model: ContinuousDescriptor, T: float, u: Array, *, seed: int = 1,
            sigma: float = 0.5, process: float = 1.0, gamma: Array | None = None) -> Array:
    """Outputs (N, p) of the plant under u (N, m), started at the steady state of u[0];
    u[k] is applied from t[k] (zero-order hold), y[k] is measured at t[k]. `gamma` (N, m):
    loss of effectiveness per sample."""
    sim = PlantSimulator(model, T, seed=seed, process=process, current_sigma=sigma)
    sim.x = steady_state(sim, u[0])
    N = u.shape[0]
    Y = np.empty((N, sim.C.shape[0]))
    g = np.zeros((N, u.shape[1])) if gamma is None else gamma
    for k in range(N):
        Y[k] = sim.output(u[k], g[k])
        sim.advance(u[k], g[k])
    return Y


def two_by_two() -> ContinuousDescriptor:
    """A 3-state, 2-input, 2-output plant with a lightly damped pair and a real pole."""
    A = np.array([[-1.0, 2.0, 0.0], [-2.0, -1.0, 0.5], [0.0, 0.0, -4.0]])
    B = np.array([[1.0, 0.0], [0.0, 0.5], [0.3, 1.0]])
    C = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    return ContinuousDescriptor(E=np.eye(3), A=A, B=B, C=C, Qc=1e-3 * np.eye(3),
                                R=1e-4 * np.eye(2), state_names=("a", "b", "c"),
                                input_names=("u1", "u2"), output_names=("y1", "y2"))


def frequency_response(model: ContinuousDescriptor, w: Array) -> Array:
    """(len(w), p, m) of C (jw I - A)^-1 B on the standard form; w = 0 is the DC gain of
    the observable part (the motor angle's integrator does not reach the current)."""
    dm = model.discretize(1e-3)
    ss = model.standard_form()
    W = dm.Wobs
    A, B, C = W @ ss.A @ W.T, W @ ss.B, ss.C @ W.T
    n = A.shape[0]
    return np.array([C @ np.linalg.solve(1j * wi * np.eye(n) - A, B) for wi in w])


def step_response(model: ContinuousDescriptor, t_end: float, T: float) -> Array:
    """Response (N, p) of the observable part to a unit step of the first input from rest."""
    dm = model.discretize(T)
    A, B, _ = dm.at(T)
    N = round(t_end / T)
    x = np.zeros(A.shape[0])
    out = np.empty((N, dm.C.shape[0]))
    for k in range(N):
        out[k] = dm.C @ x
        x = A @ x + B[:, 0]
    return out
