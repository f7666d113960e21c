"""Linear time-invariant building blocks of the identification, on scipy and one compiled loop.

* `dsim`: x(k+1) = A x(k) + B u(k), y(k) = C x(k) for a whole record, compiled
  (`monitor.jit`): the fits simulate the record thousands of times (a finite-difference
  Jacobian is one simulation per parameter), so at 2 kHz this recursion is most of
  identify's time. scipy has it only as scipy.signal.dlsim's Python loop (hundreds of times
  slower), and a complex Schur form with one scipy.signal.lfilter per coordinate runs 7-8
  times slower than the compiled loop at the orders identify fits.
* `kalman`: the steady-state Kalman predictor of the noise model (1)-(2) with the
  process-noise intensity discretised by Van Loan's method (scipy.linalg.solve_discrete_are).
* `predict`: its one-step innovations e(k) = y(k) - C x^(k|k-1) on a record.
* `d2c`: the inverse of the zero-order hold, logm([[A, B], [0, I]]) / T (scipy.linalg.logm).
* `c2d`: the zero-order hold itself (scipy.signal.cont2discrete).
* `integrating`: which continuous poles a record cannot tell from s = 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.signal
from numpy.typing import NDArray

from monitor.estimation.model import van_loan
from monitor.identify.errors import IdentifyError
from monitor.jit import njit

Array = NDArray[np.float64]

__all__ = ["Kalman", "c2d", "d2c", "dsim", "integrating", "kalman", "predict",
           "steady_state_x0"]

# A pole whose time constant exceeds this many records is an integrator as far as the
# record tells (a position from a speed, a speed from a torque without friction).
INTEGRATING_RECORDS = 10.0


def dsim(A: Array, B: Array, C: Array, u: Array, x0: Array | None = None) -> Array:
    """Outputs (N, p) of x(k+1) = A x(k) + B u(k), y(k) = C x(k), x(0) = x0 (zero if None)."""
    n = A.shape[0]
    if B.shape[0] != n or C.shape[1] != n or u.ndim != 2 or u.shape[1] != B.shape[1]:
        # the compiled loop does not check its indices: a mismatch would read past an array
        raise ValueError(f"dsim: A {A.shape}, B {B.shape}, C {C.shape} and u {u.shape} do "
                         "not fit together")
    f64 = np.float64
    x = np.zeros(n) if x0 is None else np.ascontiguousarray(x0, dtype=f64).reshape(n)
    y = np.empty((u.shape[0], C.shape[0]))
    _simulate(np.ascontiguousarray(A, dtype=f64), np.ascontiguousarray(B, dtype=f64),
              np.ascontiguousarray(C, dtype=f64), np.ascontiguousarray(u, dtype=f64), x, y)
    return y


@njit
def _simulate(A: Array, B: Array, C: Array, u: Array, x0: Array, y: Array) -> None:
    """Fill y with the record of (A, B, C) from x0 under the inputs u (N, m)."""
    n = A.shape[0]
    m = B.shape[1]
    p = C.shape[0]
    x = x0.copy()
    nxt = np.empty(n)
    for k in range(u.shape[0]):
        for i in range(p):
            acc = 0.0
            for j in range(n):
                acc += C[i, j] * x[j]
            y[k, i] = acc
        for i in range(n):
            acc = 0.0
            for j in range(n):
                acc += A[i, j] * x[j]
            for j in range(m):
                acc += B[i, j] * u[k, j]
            nxt[i] = acc
        for i in range(n):
            x[i] = nxt[i]


def c2d(Ac: Array, Bc: Array, T: float) -> tuple[Array, Array]:
    """Zero-order hold of x' = Ac x + Bc u at period T."""
    n, m = Bc.shape
    Ad, Bd, *_ = scipy.signal.cont2discrete((Ac, Bc, np.zeros((1, n)), np.zeros((1, m))), T,
                                            method="zoh")
    return np.asarray(Ad), np.asarray(Bd)


def integrating(poles: NDArray[np.complex128] | Array, duration: float) -> NDArray[np.bool_]:
    """Mask of the continuous poles that act as integrators over a record of `duration`
    seconds: |s| below 1 / (INTEGRATING_RECORDS duration). Such a model has no DC gain,
    and its slowest time constant says nothing about how long a capture must be."""
    return np.asarray(np.abs(np.asarray(poles)) * duration * INTEGRATING_RECORDS < 1.0)


def d2c(A: Array, B: Array, T: float) -> tuple[Array, Array]:
    """Continuous (Ac, Bc) whose zero-order hold at T is (A, B).

    logm of [[A, B], [0, I]] is real only when A has no eigenvalue on the closed negative
    real axis: such a pole (a sign flip every sample) has no continuous-time counterpart.
    """
    n, m = B.shape
    lam = np.linalg.eigvals(A)
    bad = [z for z in lam if abs(z.imag) <= 1e-9 * max(1.0, abs(z)) and z.real <= 1e-9]
    if bad:
        raise IdentifyError(
            f"the fitted discrete model has a pole at z = {bad[0].real:.3g} on the negative "
            "real axis, which no continuous system sampled with a zero-order hold has: record "
            "at a lower sample rate or a smaller order, with the output not aliased"
        )
    M = np.zeros((n + m, n + m))
    M[:n, :n] = A
    M[:n, n:] = B
    M[n:, n:] = np.eye(m)
    L = np.asarray(scipy.linalg.logm(M)) / T
    return np.ascontiguousarray(L[:n, :n].real), np.ascontiguousarray(L[:n, n:].real)


@dataclass(frozen=True)
class Kalman:
    """Steady-state Kalman predictor: gain K (A P C' S^-1), prior covariance P, innovation
    covariance S = C P C' + R."""

    K: Array
    P: Array
    S: Array


def kalman(A: Array, C: Array, Qd: Array, R: Array) -> Kalman:
    """The steady-state predictor of x(k+1) = A x + w, y = C x + v, w ~ (0, Qd), v ~ (0, R)
    (the noise model (1)-(2)). Raises LinAlgError/ValueError if the Riccati equation has no
    stabilising solution."""
    P = scipy.linalg.solve_discrete_are(A.T, C.T, Qd, R)
    P = 0.5 * (P + P.T)
    S = C @ P @ C.T + R
    K = np.linalg.solve(S.T, (A @ P @ C.T).T).T
    return Kalman(K=K, P=P, S=0.5 * (S + S.T))


def discrete_noise(Ac: Array, Qc: Array, T: float) -> Array:
    """Qd of a continuous intensity Qc over one period (Van Loan, as the estimator does)."""
    return van_loan(Ac, Qc, T)


def steady_state_x0(A: Array, B: Array, C: Array, u0: Array, y0: Array) -> Array:
    """The state closest to steady state under u0 that explains y0 (least squares on
    [I - A; C] x = [B u0; y0]): where a healthy capture starts."""
    n = A.shape[0]
    M = np.vstack([np.eye(n) - A, C])
    rhs = np.concatenate([B @ u0, y0])
    x, *_ = np.linalg.lstsq(M, rhs, rcond=None)
    return np.asarray(x)


def predict(A: Array, B: Array, C: Array, K: Array, u: Array, y: Array,
            x0: Array | None = None) -> Array:
    """One-step innovations e(k) = y(k) - C x^(k|k-1) of the predictor
    x^(k+1) = A x^ + B u + K e (the innovation form), started at x0 (default: the
    steady state that explains the first sample)."""
    if x0 is None:
        x0 = steady_state_x0(A, B, C, u[0], y[0])
    Ap = A - K @ C
    yhat = dsim(Ap, np.hstack([B, K]), C, np.hstack([u, y]), x0)
    return np.asarray(y - yhat)
