"""A stateful wrapper around the compiled UKF kernels of `monitor.estimation.ukf`, for tests.

The monitor itself calls the kernels from `monitor.estimation.fuzzy_ukf`, which owns its
work arrays; the tests check the kernels against a textbook Kalman filter through this
small object instead.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from monitor.estimation.ukf import sigma_weights, ukf_predict, ukf_update

Array = NDArray[np.float64]

__all__ = ["UnscentedKalmanFilter"]


class _Work:
    """Preallocated work arrays for one filter of state size n and p outputs."""

    def __init__(self, n: int, p: int) -> None:
        self.L = np.zeros((n, n))
        self.Ls = np.zeros((p, p))
        self.d = np.zeros(n)
        self.s = np.zeros(n)
        self.dy = np.zeros(p)
        self.Pyy = np.zeros((p, p))
        self.Pyy_inv = np.zeros((p, p))
        self.Pxy = np.zeros((n, p))
        self.K = np.zeros((n, p))
        self.nu = np.zeros(p)
        self.IKC = np.zeros((n, n))
        self.T1 = np.zeros((n, n))
        self.xp = np.zeros(n)
        self.Pp = np.zeros((n, n))


class UnscentedKalmanFilter:
    """UKF (30)-(49) for x(k+1) = A x + b_k + w, y = C x + yoff_k + v.

    >>> f = UnscentedKalmanFilter(x0, P0, alpha=1e-4, beta=2.0)
    >>> f.predict(A, b, Q); f.update(C, yoff, R, y)

    `x`, `P` hold the posterior; `x_prior`, `P_prior` the prior; `nu`, `S` the last
    innovation and its covariance; `repairs` counts clamped Cholesky pivots.
    """

    def __init__(self, x0: Array, P0: Array, *, alpha: float = 1e-4, beta: float = 2.0,
                 outputs: int = 1) -> None:
        self.x = np.array(x0, dtype=float)
        self.P = np.array(P0, dtype=float)
        n = self.x.shape[0]
        if self.P.shape != (n, n):
            raise ValueError(f"P0 must be {n}x{n}")
        self.weights = sigma_weights(n, alpha, beta)
        self._w = _Work(n, outputs)
        self.repairs = 0

    @property
    def x_prior(self) -> Array:
        return self._w.xp

    @property
    def P_prior(self) -> Array:
        return self._w.Pp

    @property
    def nu(self) -> Array:
        return self._w.nu

    @property
    def S(self) -> Array:
        return self._w.Pyy

    @property
    def K(self) -> Array:
        return self._w.K

    def predict(self, A: Array, b: Array, Q: Array) -> None:
        w = self._w
        self.repairs += ukf_predict(self.x, self.P, A, b, Q, self.weights.delta, self.weights.wi,
                                    w.L, w.d, w.xp, w.Pp)
        self.x[:] = w.xp
        self.P[:] = w.Pp

    def update(self, C: Array, yoff: Array, R: Array, y: Array) -> None:
        w = self._w
        self.repairs += ukf_update(w.xp, w.Pp, C, yoff, R, y, self.weights.delta, self.weights.wi,
                                   w.L, w.Ls, w.s, w.dy, w.Pyy, w.Pyy_inv, w.Pxy, w.K, w.nu,
                                   self.x, self.P, w.IKC, w.T1)
