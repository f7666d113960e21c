"""Baseline: the augmented-state Kalman filter on [x; gamma].

The honest competitor of the fuzzy UKF (Liu et al., Int. J. Fuzzy Syst. 22(1), 2020): the loss of
effectiveness is appended to the state as a random walk (11), (14),

    [x; gamma](k+1) = [[A, -B diag(u)], [0, I]] [x; gamma](k) + [B u; 0] + w,
    y = [C, -D diag(u)] [x; gamma] + D u + v,

and one Kalman filter estimates both. The model is linear in [x; gamma] for a known u, so
this is the optimal estimator for the random-walk fault model (equal to the optimal
two-stage Kalman filter of Hsieh & Chen 1999). It runs on the same compiled kernels as the
fuzzy UKF (`ukf_predict`/`ukf_update`: for a linear model the unscented transform is exact,
so they compute the Kalman filter's moments) so that the benchmark compares methods, not
implementations. gamma is not clipped: the KF does not know it is a fraction.

Start-up is the fuzzy UKF's, so that the two are compared on the estimation and not on
their first samples: without an x0 the filter starts from the fault-free steady state of
the first input with the cross-covariance that the unknown gamma gives it,
Pxg = V P0_gamma with V = d x_ss / d gamma (`monitor.estimation.start.steady_start`),
and the state block of the covariance is in the state's own units: the stationary
Kalman covariance (`initial_covariance`) unless P0 is given. An x = 0 start with P0 = 1
(the former default) reads a 24 V servo's 790 rad/s as a 40 % loss of effectiveness for
seconds: gamma^ was still 0.47 at t = 1.5 s of a healthy run.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import NDArray

from monitor.estimation.layout import UKF_SCRATCH, Table
from monitor.estimation.model import DiscreteModel
from monitor.estimation.start import initial_covariance, steady_start
from monitor.estimation.ukf import sigma_weights, ukf_predict, ukf_update

Array = NDArray[np.float64]

__all__ = ["AugmentedKFConfig", "AugmentedKalmanFilter"]

_SCRATCH = Table("AKF", UKF_SCRATCH, 0)  # in the order _akf_step takes them


@dataclass(frozen=True)
class AugmentedKFConfig:
    """q_gamma: random-walk intensity of gamma (gamma^2 per second); P0_gamma its prior;
    P0: initial state covariance (diagonal value), None: the stationary one."""

    q_gamma: float = 0.05
    P0: float | None = None
    P0_gamma: float = 0.1


@numba.njit(cache=True, nogil=True)
def _akf_step(A: Array, B: Array, Q: Array, C: Array, D: Array, R: Array, u: Array, y: Array,
              qg: float, delta: float, wi: float, x: Array, P: Array,
              scratch: tuple[Array, ...], Aa: Array, ba: Array, Qa: Array, Ca: Array,
              yoff: Array, out_nu: Array) -> int:
    """One sample of the Kalman filter on [x; gamma]; scratch: the UKF's
    (`layout.UKF_SCRATCH` of the augmented state, in its order)."""
    L, d, xp, Pp, Ls, s, dy, Pyy, Pyy_inv, Pxy, K, IKC, T1 = scratch
    n = A.shape[0]
    m = B.shape[1]
    p = C.shape[0]
    N = n + m
    for r in range(N):
        for c in range(N):
            Aa[r, c] = 0.0
            Qa[r, c] = 0.0
    for r in range(n):
        acc = 0.0
        for c in range(n):
            Aa[r, c] = A[r, c]
            Qa[r, c] = Q[r, c]
        for a in range(m):
            Aa[r, n + a] = -B[r, a] * u[a]
            acc += B[r, a] * u[a]
        ba[r] = acc
    for a in range(m):
        Aa[n + a, n + a] = 1.0
        Qa[n + a, n + a] = qg
        ba[n + a] = 0.0
    for r in range(p):
        acc = 0.0
        for c in range(n):
            Ca[r, c] = C[r, c]
        for a in range(m):
            Ca[r, n + a] = -D[r, a] * u[a]
            acc += D[r, a] * u[a]
        yoff[r] = acc
    rep = ukf_predict(x, P, Aa, ba, Qa, delta, wi, L, d, xp, Pp)
    rep += ukf_update(xp, Pp, Ca, yoff, R, y, delta, wi, L, Ls, s, dy, Pyy, Pyy_inv, Pxy, K,
                      out_nu, x, P, IKC, T1)
    for r in range(p):
        out_nu[r] = out_nu[r] / math.sqrt(Pyy[r, r])
    return rep


class AugmentedKalmanFilter:
    """Kalman filter on [x; gamma]; `step(u, y, dt)` returns gamma^ (a view, overwritten)."""

    def __init__(self, model: DiscreteModel, config: AugmentedKFConfig | None = None,
                 x0: Sequence[float] | None = None, alpha: float = 1e-4, beta: float = 2.0
                 ) -> None:
        cfg = config or AugmentedKFConfig()
        self.model = model
        self.config = cfg
        n, m, p = model.n, model.m, model.p
        N = n + m
        self.n, self.m = n, m
        self.state = np.zeros(N)
        if x0 is not None:
            x0a = np.asarray(x0, dtype=float)
            self.state[:n] = model.Wobs @ x0a if x0a.shape == (model.n_full,) else x0a
        self.P = np.zeros((N, N))
        self.P[:n, :n] = initial_covariance(model) if cfg.P0 is None else np.eye(n) * cfg.P0
        self.P[n:, n:] = np.eye(m) * cfg.P0_gamma
        self._needs_init = x0 is None
        w = sigma_weights(N, alpha, beta)
        self._delta, self._wi = w.delta, w.wi
        work = np.zeros(_SCRATCH.size(N, 0, p))
        self._scratch = tuple(_SCRATCH.view(work, f, N, 0, p) for f in _SCRATCH.names)
        self._Aa = np.zeros((N, N))
        self._ba = np.zeros(N)
        self._Qa = np.zeros((N, N))
        self._Ca = np.zeros((p, N))
        self._yoff = np.zeros(p)
        self.innovation = np.zeros(p)
        self._u = np.zeros(m)
        self._y = np.zeros(p)
        self.repairs = 0
        self.gamma = self.state[n:]
        self.x = self.state[:n]

    def step(self, u: Sequence[float] | Array | float, y: Sequence[float] | Array | float,
             dt: float) -> Array:
        if not dt > 0.0:
            raise ValueError(f"dt must be positive, got {dt}")
        self._u[:] = u
        self._y[:] = y
        if self._needs_init:
            self._init_from_sample()
        A, B, Q = self.model.at(dt)
        md = self.model
        self.repairs += _akf_step(A, B, Q, md.C, md.D, md.R, self._u, self._y,
                                  self.config.q_gamma * dt, self._delta, self._wi, self.state,
                                  self.P, self._scratch, self._Aa, self._ba, self._Qa,
                                  self._Ca, self._yoff, self.innovation)
        return self.gamma

    def _init_from_sample(self) -> None:
        """The fault-free steady state of the first input, coupled to the unknown gamma."""
        self._needs_init = False
        n = self.n
        x, V = steady_start(self.model, self._u, self._y)
        Pg = self.P[n:, n:].copy()
        self.state[:n] = x
        self.P[:n, n:] = V @ Pg
        self.P[n:, :n] = (V @ Pg).T
        self.P[:n, :n] += V @ Pg @ V.T
