"""A stateful wrapper around the compiled UKF kernels of `monitor.estimation.ukf`, for tests.

The monitor itself calls the kernels from `monitor.estimation.fuzzy_ukf`, which owns its
work arrays; the tests check the kernels against a textbook Kalman filter through this
small object instead.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from numpy.typing import NDArray

from monitor.estimation.layout import UKF_SCRATCH, Table
from monitor.estimation.ukf import sigma_weights, ukf_predict, ukf_update

Array = NDArray[np.float64]

__all__ = ["UnscentedKalmanFilter"]


_WORK = Table("UKF", (*UKF_SCRATCH, ("nu", "p")), 0)
"""The kernels' scratch arrays and the innovation, in one buffer (n states, p outputs)."""


class UnscentedKalmanFilter:
    """UKF (30)-(49) for x(k+1) = A x + b_k + w, y = C x + yoff_k + v.

    >>> f = UnscentedKalmanFilter(x0, P0, alpha=1e-4, beta=2.0)
    >>> f.predict(A, b, Q); f.update(C, yoff, R, y)

    `x`, `P` hold the posterior; `repairs` counts clamped Cholesky pivots.
    """

    def __init__(self, x0: Array, P0: Array, *, alpha: float = 1e-4, beta: float = 2.0,
                 outputs: int = 1) -> None:
        self.x = np.array(x0, dtype=float)
        self.P = np.array(P0, dtype=float)
        n = self.x.shape[0]
        if self.P.shape != (n, n):
            raise ValueError(f"P0 must be {n}x{n}")
        self.weights = sigma_weights(n, alpha, beta)
        work = np.zeros(_WORK.size(n, 0, outputs))
        self._w = SimpleNamespace(**{f: _WORK.view(work, f, n, 0, outputs)
                                     for f in _WORK.names})
        self.repairs = 0

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
