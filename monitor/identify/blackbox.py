"""Black-box continuous-time state-space model of a chosen or selected order.

1. N4SID (`subspace`) on the training record, mean-removed for the projections, B and the
   initial state re-fitted on the raw record (the model maps raw u to raw y: the monitor's
   model has no offsets).
2. Order: the given one, else the one of 1..6 with the smallest BIC of the one-step
   predictor's innovations, N log det(cov e) + d log N with d = n (m + 2 p) free parameters
   (BIC rather than AIC: consistent, it does not drift to larger orders on long captures).
3. Prediction-error refinement of (A, B, C, K) in full parametrisation by
   scipy.optimize.least_squares on the innovations whitened by the subspace estimate of
   their covariance (the directions of similarity transforms are flat; the damped
   Gauss-Newton step and the pseudo-inverse covariance handle them, and the covariance of
   invariants -- DC gain, poles -- is the right one, Ljung 1999 section 9.6).
4. Continuous time by the inverse zero-order hold (`lti.d2c`), E = I.
5. Noise (1)-(2) for the filter: a diagonal process-noise intensity Qc in the subspace's
   state coordinates (normalised by the singular values of the projection, so the states
   have comparable scales) and R = diag(r_i), by maximum likelihood of the steady-state
   Kalman filter's innovations (Nelder-Mead on the logarithms); q = trace(Qc) / n and
   Q0 = Qc / q. At the optimum the mean NIS equals p: the likelihood is stationary along
   (c Qc, c R). (q I was tried and left the innovations coloured; the innovation form's
   K Re K' as the shape of Q already contains the sensor noise, and the likelihood then
   drives R to 0.)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.optimize
from numpy.typing import NDArray

from monitor.estimation.model import van_loan
from monitor.identify.errors import IdentifyError
from monitor.identify.lti import d2c, kalman, predict
from monitor.identify.subspace import N4SID, SubspaceModel, horizon, output_error_b

Array = NDArray[np.float64]

__all__ = ["StateSpaceFit", "continuous_intensity", "fit_state_space", "subspace_model"]

MAX_ORDER = 6


@dataclass(frozen=True)
class StateSpaceFit:
    A: Array  # discrete
    B: Array
    C: Array
    K: Array
    Ac: Array  # continuous
    Bc: Array
    Qc: Array  # q Q0
    q: float
    R: Array
    order: int
    bic: dict[int, float]
    singular_values: list[float]
    invariants: dict[str, object]  # dc gain, poles with standard deviations
    nfev: int


def subspace_model(u: Array, y: Array, n: int, s: int | None = None) -> tuple[SubspaceModel,
                                                                                   N4SID]:
    """Order-n N4SID model of a raw record (projections on the mean-removed data, B and x0
    re-fitted on the raw data)."""
    ud, yd = u - u.mean(axis=0), y - y.mean(axis=0)
    dec = N4SID(ud, yd, s or horizon(ud, yd))
    return _raw(dec.model(n), u, y), dec


def _raw(sub: SubspaceModel, u: Array, y: Array) -> SubspaceModel:
    B, x0, _ = output_error_b(sub.A, sub.C, u, y)
    return SubspaceModel(A=sub.A, B=B, C=sub.C, K=sub.K, Re=sub.Re, x0=x0)


def continuous_intensity(Ac: Array, Qd: Array, T: float) -> Array:
    """Qc with van_loan(Ac, Qc, T) = Qd (the linear map vec Qd = [int e^{(A+A)s} ds] vec Qc
    inverted), symmetrised and projected on the positive semi-definite cone."""
    n = Ac.shape[0]
    Ks = np.kron(Ac, np.eye(n)) + np.kron(np.eye(n), Ac)
    M = np.zeros((2 * n * n, 2 * n * n))
    M[:n * n, :n * n] = Ks
    M[:n * n, n * n:] = np.eye(n * n)
    G = scipy.linalg.expm(M * T)[:n * n, n * n:]
    Qc = np.linalg.solve(G, Qd.reshape(-1)).reshape(n, n)
    w, V = np.linalg.eigh(0.5 * (Qc + Qc.T))
    return np.asarray((V * np.clip(w, 0.0, None)) @ V.T)


def _bic(sub: SubspaceModel, u: Array, y: Array) -> float:
    e = predict(sub.A, sub.B, sub.C, sub.K, u, y)
    N, p = e.shape
    m = u.shape[1]
    sign, logdet = np.linalg.slogdet(e.T @ e / N)
    d = sub.n * (m + 2 * p)
    return float(N * logdet + d * math.log(N)) if sign > 0 else math.inf


def _pem(sub: SubspaceModel, u: Array, y: Array, max_nfev: int) -> tuple[
        Array, Array, Array, Array, Array, Array, int]:
    """(A, B, C, K, theta covariance, innovations, nfev) of the PEM refinement."""
    n, m, p = sub.n, sub.B.shape[1], sub.C.shape[0]
    W = np.linalg.inv(np.linalg.cholesky(sub.Re + 1e-12 * np.trace(sub.Re) * np.eye(p)))
    sizes = (n * n, n * m, p * n, n * p)

    def unpack(th: Array) -> tuple[Array, Array, Array, Array]:
        o = np.cumsum((0, *sizes))
        return (th[o[0]:o[1]].reshape(n, n), th[o[1]:o[2]].reshape(n, m),
                th[o[2]:o[3]].reshape(p, n), th[o[3]:o[4]].reshape(n, p))

    bad = np.full(y.size, 1e3)

    def resid(th: Array) -> Array:
        A, B, C, K = unpack(th)
        if np.max(np.abs(np.linalg.eigvals(A - K @ C))) >= 1.0:
            return bad  # the predictor must be stable
        try:
            e = predict(A, B, C, K, u, y)
        except (np.linalg.LinAlgError, ValueError):
            return bad
        r = (e @ W.T).ravel()
        return r if np.all(np.isfinite(r)) else bad

    th0 = np.concatenate([sub.A.ravel(), sub.B.ravel(), sub.C.ravel(), sub.K.ravel()])
    res = scipy.optimize.least_squares(resid, th0, method="trf", x_scale="jac",
                                       max_nfev=max_nfev)
    th = res.x if res.cost <= 0.5 * float(np.sum(resid(th0) ** 2)) else th0
    A, B, C, K = unpack(th)
    r = resid(th)
    Jac = np.asarray(res.jac)
    s2 = float(r @ r) / max(1, r.size - th.size)
    cov = s2 * np.linalg.pinv(Jac.T @ Jac, rtol=1e-10)
    e = predict(A, B, C, K, u, y)
    return A, B, C, K, cov, e, int(res.nfev)


def _invariants(th_fn: Callable[[Array], tuple[Array, Array, Array]], th: Array, cov: Array,
                T: float) -> dict[str, object]:
    """DC gain and continuous poles with standard deviations by the delta method."""

    def feats(t: Array) -> Array:
        A, B, C = th_fn(t)
        g = C @ np.linalg.solve(np.eye(A.shape[0]) - A, B)
        lam = np.sort_complex(np.log(np.linalg.eigvals(A).astype(complex)) / T)
        return np.concatenate([g.ravel(), lam.real, lam.imag])

    f0 = feats(th)
    h = 1e-6 * np.maximum(1.0, np.abs(th))
    G = np.empty((f0.size, th.size))
    for i in range(th.size):
        t = th.copy()
        t[i] += h[i]
        G[:, i] = (feats(t) - f0) / h[i]
    sd = np.sqrt(np.clip(np.einsum("ij,jk,ik->i", G, cov, G), 0.0, None))
    A, B, C = th_fn(th)
    p, m = C.shape[0], B.shape[1]
    n = A.shape[0]
    k = p * m
    return {
        "dc_gain": f0[:k].reshape(p, m).tolist(),
        "dc_gain_std": sd[:k].reshape(p, m).tolist(),
        "poles_real": f0[k:k + n].tolist(),
        "poles_real_std": sd[k:k + n].tolist(),
        "poles_imag": f0[k + n:].tolist(),
        "poles_imag_std": sd[k + n:].tolist(),
    }


def noise_ml(A: Array, B: Array, C: Array, Ac: Array, u: Array, y: Array, T: float,
             R0: Array) -> tuple[Array, Array]:
    """(Qc diagonal, R diagonal) maximising the Gaussian likelihood of the steady-state
    Kalman filter's innovations (Nelder-Mead on the logarithms)."""
    N, p = y.shape
    n = A.shape[0]

    def nll(phi: Array) -> float:
        Qd = van_loan(Ac, np.diag(np.exp(phi[:n])), T)
        R = np.diag(np.exp(phi[n:]))
        try:
            kf = kalman(A, C, Qd, R)
            e = predict(A, B, C, kf.K, u, y)
            Li = np.linalg.inv(np.linalg.cholesky(kf.S))
        except (np.linalg.LinAlgError, ValueError):
            return 1e300
        w = e @ Li.T
        return float(N * np.linalg.slogdet(kf.S)[1] + np.sum(w * w))

    # Start: the innovation variance split half and half; r is kept above 1e-9 of the
    # innovation variance (a sensor without noise is not a model the filter can use).
    r0 = 0.5 * np.diag(R0)
    q0 = math.log(float(np.mean(r0)) / T)
    phi0 = np.concatenate([np.full(n, q0), np.log(r0)])
    lo = np.concatenate([np.full(n, q0 - 30.0), np.log(1e-9 * np.diag(R0))])
    hi = np.concatenate([np.full(n, q0 + 30.0), np.log(10.0 * np.diag(R0))])
    res = scipy.optimize.minimize(nll, phi0, method="Nelder-Mead",
                                  bounds=list(zip(lo, hi, strict=True)),
                                  options={"xatol": 1e-3, "fatol": 1e-2, "maxfev": 300 * (n + p),
                                           "adaptive": True})
    return np.diag(np.exp(res.x[:n])), np.diag(np.exp(res.x[n:]))


def fit_state_space(u: Array, y: Array, T: float, order: int | None,
                    max_nfev: int = 400) -> StateSpaceFit:
    """Subspace + PEM black-box fit on a training record (see the module docstring)."""
    ud, yd = u - u.mean(axis=0), y - y.mean(axis=0)
    dec = N4SID(ud, yd, horizon(ud, yd))
    orders = [order] if order is not None else list(range(1, min(MAX_ORDER,
                                                                  dec.max_order) + 1))
    bic: dict[int, float] = {}
    subs: dict[int, SubspaceModel] = {}
    for n in orders:
        if n > dec.max_order:
            raise IdentifyError(
                f"order {n} is more than the capture supports ({dec.max_order}): record a "
                "longer capture with a richer input, or ask for a smaller order")
        sub = _raw(dec.model(n), u, y)
        try:
            d2c(sub.A, sub.B, T)
        except IdentifyError:
            if order is not None:
                raise
            continue
        subs[n] = sub
        bic[n] = _bic(sub, u, y)
    if not bic:
        raise IdentifyError("no model order gives a continuous-time model: record at a lower "
                            "sample rate, with an anti-aliased output")
    n = min(bic, key=lambda k: bic[k])
    A, B, C, K, cov, e, nfev = _pem(subs[n], u, y, max_nfev)
    Ac, Bc = d2c(A, B, T)
    m, p = B.shape[1], C.shape[0]

    def abc(th: Array) -> tuple[Array, Array, Array]:
        return (th[:n * n].reshape(n, n), th[n * n:n * n + n * m].reshape(n, m),
                th[n * n + n * m:n * n + n * m + p * n].reshape(p, n))

    th = np.concatenate([A.ravel(), B.ravel(), C.ravel(), K.ravel()])
    inv = _invariants(abc, th, cov, T)
    Re = e.T @ e / e.shape[0]
    Qc, R = noise_ml(A, B, C, Ac, u, y, T, Re)
    q = float(np.trace(Qc)) / n  # Qc = q Q0 with Q0 = Qc / q (trace n)
    return StateSpaceFit(A=A, B=B, C=C, K=K, Ac=Ac, Bc=Bc, Qc=Qc, q=q, R=R, order=n,
                         bic=bic, singular_values=[float(v) for v in dec.singular_values[:12]],
                         invariants=inv, nfev=nfev)
