"""Estimators under comparison, behind one `step(u, y, dt) -> gamma^` interface, each with
the standard deviation of its latest gamma^ (`spread`), which the diagnosis weighs an
alarm by (`monitor.diagnosis.rules.cls_update`)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from experiments.akf import AugmentedKalmanFilter
from monitor.estimation.fuzzy_ukf import FuzzyUKF
from monitor.estimation.model import DiscreteModel

Array = NDArray[np.float64]


class GammaEstimator(Protocol):
    def step(self, u: Array, y: Array, dt: float) -> Array: ...

    def spread(self) -> Array: ...


class FuzzyUKFGamma:
    """The paper's method (this project)."""

    def __init__(self, model: DiscreteModel, x0: Sequence[float] | None) -> None:
        self.est = FuzzyUKF(model, x0=x0)

    def step(self, u: Array, y: Array, dt: float) -> Array:
        return self.est.step(u, y, dt).gamma

    def spread(self) -> Array:
        return self.est.out.gamma_sd


class FilterpyAugmentedUKF:
    """filterpy 2.0's UnscentedKalmanFilter on the augmented model [x; gamma].

    Merwe scaled sigma points with the usual alpha = 1e-3, beta = 2, kappa = 0 (the
    paper's alpha = 1e-4 is what the soak benchmark stresses). Same random-walk intensity
    on gamma as the augmented KF, so on this linear model both should agree.
    """

    def __init__(self, model: DiscreteModel, x0: Sequence[float] | None,
                 q_gamma: float = 0.05, alpha: float = 1e-3) -> None:
        from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

        self.model = model
        n, m, p = model.n, model.m, model.p
        self.n = n
        N = n + m
        pts = MerweScaledSigmaPoints(N, alpha=alpha, beta=2.0, kappa=0.0)
        self.ukf = UnscentedKalmanFilter(dim_x=N, dim_z=p, dt=model.T, hx=self._hx, fx=self._fx,
                                         points=pts)
        x = np.zeros(N)
        if x0 is not None:
            x[:n] = model.Wobs @ np.asarray(x0, dtype=float)
        self.ukf.x = x
        self.ukf.P = np.diag([1.0] * n + [0.1] * m)
        self.ukf.R = model.R.copy()
        self.q_gamma = q_gamma
        self._Q = np.zeros((N, N))

    def _fx(self, x: Array, dt: float, u: Array) -> Array:
        A, B, _ = self.model.at(dt)
        n = self.n
        g = x[n:]
        return np.concatenate([A @ x[:n] + B @ (u * (1.0 - g)), g])

    def _hx(self, x: Array, u: Array) -> Array:
        n = self.n
        return np.asarray(self.model.C @ x[:n] + self.model.D @ (u * (1.0 - x[n:])))

    def step(self, u: Array, y: Array, dt: float) -> Array:
        _, _, Q = self.model.at(dt)
        n = self.n
        self._Q[:n, :n] = Q
        self._Q[n:, n:] = np.eye(self._Q.shape[0] - n) * self.q_gamma * dt
        self.ukf.Q = self._Q
        self.ukf.predict(dt=dt, u=u)
        self.ukf.update(y, u=u)
        return np.asarray(self.ukf.x[n:])

    def spread(self) -> Array:
        return np.sqrt(np.maximum(np.diag(self.ukf.P)[self.n:], 0.0))


class AKFGamma:
    def __init__(self, model: DiscreteModel, x0: Sequence[float] | None) -> None:
        self.est = AugmentedKalmanFilter(model, x0=x0)

    def step(self, u: Array, y: Array, dt: float) -> Array:
        return self.est.step(u, y, dt)

    def spread(self) -> Array:
        n = self.est.P.shape[0] - self.est.model.m
        return np.sqrt(np.maximum(np.diag(self.est.P)[n:], 0.0))


METHODS: dict[str, Callable[[DiscreteModel, Sequence[float] | None], GammaEstimator]] = {
    "fuzzy_ukf": FuzzyUKFGamma,
    "augmented_kf": AKFGamma,
    "filterpy_ukf": FilterpyAugmentedUKF,
}
