"""Seeded plant simulator: the faulty descriptor plant (6-7) the virtual ECU runs.

    x(k+1) = A x(k) + B (I - diag(gamma_k)) u(k) + w(k),   y(k) = C x(k) + D u_F(k) + v(k)

with A, B the exact ZOH discretisation of the continuous model (not the paper's Euler
step (69), which is unstable at its T = 1 s), w ~ N(0, Qd) from Van Loan's method and
v ~ N(0, sigma^2). All states, including the unobservable angle, are simulated.

Optionally an external input the monitor's model lacks (a load torque, Coulomb friction)
enters through a continuous-time column `disturbance` of the standard form, held over the
sample like u: x(k+1) += B_d d(k), d(k) = load(t_k, x_k) in `simulate`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.signal
from numpy.typing import NDArray

from monitor.estimation.model import ContinuousDescriptor, ModelError, van_loan
from sim_ecu.scenario import Scenario

Array = NDArray[np.float64]

__all__ = ["PlantSimulator", "SimulatedRun", "simulate", "steady_state"]


class PlantSimulator:
    """Steps the plant one sample period at a time, reproducibly from `seed`.

    `process` scales the model's process-noise intensity; `current_sigma` is the standard
    deviation of the measurement noise on every output. `disturbance`: the continuous-time
    column (one entry per state of the standard form) through which an external scalar
    input d enters (`advance(u, gamma, d)`), e.g. -1/J on the speed for a load torque.
    """

    def __init__(
        self,
        model: ContinuousDescriptor,
        T: float,
        *,
        seed: int = 0,
        x0: Sequence[float] | None = None,
        process: float = 1.0,
        current_sigma: float = 0.5,
        disturbance: Sequence[float] | None = None,
    ) -> None:
        if not T > 0:
            raise ModelError(f"sample period must be positive, got {T}")
        ss = model.standard_form()
        self.state_names = ss.state_names
        Ad, Bd, _, _, _ = scipy.signal.cont2discrete((ss.A, ss.B, ss.C, ss.D), T, method="zoh")
        self.A = np.asarray(Ad)
        self.B = np.asarray(Bd)
        self.B_d = np.zeros(ss.n)
        if disturbance is not None:
            col = np.asarray(disturbance, dtype=float).reshape(ss.n, 1)
            Bw = scipy.signal.cont2discrete((ss.A, col, ss.C, np.zeros((ss.C.shape[0], 1))), T,
                                            method="zoh")[1]
            self.B_d = np.asarray(Bw)[:, 0]
        self.C = ss.C
        self.D = ss.D
        self.T = float(T)
        Qd = van_loan(ss.A, model.noise_standard_form() * process, T)
        w, V = np.linalg.eigh(Qd)
        self._Lq = V @ np.diag(np.sqrt(np.clip(w, 0.0, None)))
        self.sigma = float(current_sigma)
        self.rng = np.random.default_rng(seed)
        n = ss.n
        self.x = np.zeros(n) if x0 is None else np.asarray(x0, dtype=float)[:n].copy()
        if self.x.shape != (n,):
            raise ModelError(f"x0 must have {n} entries")

    def output(self, u: Array, gamma: Array) -> Array:
        """Noisy measurement of the current state, y = C x + D u_F + v (7)."""
        uf = u * (1.0 - gamma)
        y: Array = self.C @ self.x + self.D @ uf
        return y + self.sigma * self.rng.standard_normal(y.shape)

    def true_output(self, u: Array, gamma: Array) -> Array:
        return np.asarray(self.C @ self.x + self.D @ (u * (1.0 - gamma)))

    def advance(self, u: Array, gamma: Array, d: float = 0.0) -> None:
        """x(k+1) = A x + B u (I - gamma) + B_d d + w (6), d the external input."""
        uf = u * (1.0 - gamma)
        w = self._Lq @ self.rng.standard_normal(self.x.shape[0])
        self.x = self.A @ self.x + self.B @ uf + self.B_d * d + w


@dataclass
class SimulatedRun:
    """A whole run sampled at period T: row k holds the sample taken at t[k]."""

    t: Array
    u: Array  # (N, m) voltage command
    y: Array  # (N, p) measured outputs
    y_true: Array  # (N, p) noise-free outputs
    x: Array  # (N, n) true states
    gamma: Array  # (N, m) true loss of effectiveness
    scenario: Scenario
    T: float


def steady_state(plant: PlantSimulator, u0: Array) -> Array:
    """Fault-free steady state of `plant` under constant input u0.

    Pure integrators (a zero column in I - A: the angle) feed nothing back and start at 0.
    """
    n = plant.A.shape[0]
    M = np.eye(n) - plant.A
    settling = [j for j in range(n) if np.linalg.norm(M[:, j]) > 1e-12]
    xs = np.zeros(n)
    xs[settling] = np.linalg.solve(M[np.ix_(settling, settling)], (plant.B @ u0)[settling])
    return xs


def simulate(
    model: ContinuousDescriptor,
    scenario: Scenario,
    T: float,
    *,
    seed: int = 0,
    x0: Sequence[float] | None = None,
    settle: bool = True,
    disturbance: Sequence[float] | None = None,
    load: Callable[[float, Array], float] | None = None,
) -> SimulatedRun:
    """Simulate a scenario; with `settle` the plant starts at its fault-free steady state.

    `load(t, x)`: the external input d at time t in state x, entering through the column
    `disturbance` (see `PlantSimulator`); with `settle` the plant then starts where the
    noise-free plant settles under the first input and load (d may depend on x: friction).
    """
    sim = PlantSimulator(
        model, T, seed=seed, x0=x0, process=scenario.process, current_sigma=scenario.current_sigma,
        disturbance=disturbance,
    )
    m = sim.B.shape[1]
    if settle and x0 is None:
        u0 = np.full(m, scenario.voltage_at(0.0))
        sim.x = steady_state(sim, u0)
        if load is not None:
            for _ in range(round(20.0 / T)):  # noise-free settling under the load
                sim.x = sim.A @ sim.x + sim.B @ u0 + sim.B_d * load(0.0, sim.x)
    N = round(scenario.duration / T)
    p = sim.C.shape[0]
    t = np.arange(N, dtype=np.float64) * T
    U = np.empty((N, m))
    Y = np.empty((N, p))
    Yt = np.empty((N, p))
    X = np.empty((N, sim.x.shape[0]))
    G = np.empty((N, m))
    for k in range(N):
        g = np.asarray(scenario.gamma_at(t[k])[:m])
        u = np.full(m, scenario.voltage_at(t[k]))
        X[k] = sim.x
        Yt[k] = sim.true_output(u, g)
        Y[k] = sim.output(u, g)
        U[k] = u
        G[k] = g
        sim.advance(u, g, 0.0 if load is None else load(float(t[k]), sim.x))
    return SimulatedRun(t=t, u=U, y=Y, y_true=Yt, x=X, gamma=G, scenario=scenario, T=T)
