"""Black-box continuous-time state-space model of a chosen or selected order.

1. N4SID (`subspace`) on the training record, mean-removed for the projections, B and the
   initial state re-fitted on the raw record (the model maps raw u to raw y: the monitor's
   model has no offsets).
2. A continuous-time form of each order: the subspace model itself when the inverse
   zero-order hold has one (`lti.d2c`), else a continuous-time output-error fit (below).
3. Order: the given one, else the lowest of 1..MAX_ORDER whose hold-out fit (simulation
   NRMSE on the hold-out part, which no fit sees, from the state that fits the end of the
   training part) is within ORDER_MARGIN points of the best order's. Each order's report
   also gives whether its hold-out simulation error is independent of the input
   (`residual_input_p`: the error and the input prewhitened by the error's own
   autoregression, then `validate`'s joint cross-correlation test; Ljung 1999 section
   16.6): a mode the fit leaves out (a shaft resonance, a sensor filter) costs a point of
   NRMSE where a slow mode dominates the output's swing, yet its error follows every input
   step. It is advice, not the rule: the lowest order that passes it served the monitor
   worse on a zoo rig (a 5th order for a 3rd-order plant) than the lowest near the best
   fit. The one-step
   predictor's BIC is reported too, but does not choose: it rewards orders that model
   the noise's colour or a nonlinearity's effect on the next sample, whose simulation of
   the plant is worse (a first-order plant fitting 89 % at order 1 got 74 % at BIC's 6).
4. Prediction-error refinement of (A, B, C, K) in full parametrisation by
   scipy.optimize.least_squares on the innovations whitened by the subspace estimate of
   their covariance (the directions of similarity transforms are flat; the damped
   Gauss-Newton step and the pseudo-inverse covariance handle them, and the covariance of
   invariants -- DC gain, poles -- is the right one, Ljung 1999 section 9.6). Kept when it
   has a continuous-time form and simulates the hold-out about as well as the start.
   Continuous time by the inverse zero-order hold, E = I.
   The continuous-time output-error fit, for a discrete model with a pole on the negative
   real axis (a sign flip every sample: no zero-order-hold sample of a continuous plant
   has one; it comes from friction, quantisation or load steps the linear model absorbs
   as fast noise): (Ac, Bc, C, x0) in full parametrisation, discretised by
   scipy.signal.cont2discrete, minimising the simulation error of the training part with
   scipy.optimize.least_squares, started from the discrete model with those poles moved
   to the positive real axis (real Schur form). Its poles are continuous by construction.
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
import scipy.signal
from numpy.typing import NDArray

from monitor.estimation.model import van_loan
from monitor.identify import validate as V
from monitor.identify.errors import IdentifyError
from monitor.identify.lti import c2d, d2c, dsim, integrating, kalman, predict
from monitor.identify.subspace import N4SID, SubspaceModel, horizon, output_error_b

Array = NDArray[np.float64]

__all__ = ["StateSpaceFit", "continuous_intensity", "fit_state_space", "subspace_model"]

MAX_ORDER = 6
ORDER_MARGIN = 1.5  # NRMSE points of hold-out fit a lower order may lose against the best
SCREEN_SAMPLES = 10_000  # training samples of each order's screening fit (5 s at 2 kHz)
SCREEN_NFEV = 20
WHITEN_ORDER = 20  # autoregression that whitens a simulation error before the input test


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
    holdout_fit: dict[int, float]  # mean hold-out NRMSE % per order tried
    holdout_input_p: dict[int, float]  # per order, `residual_input_p` of its hold-out error
    form: str  # "prediction error" or "continuous output error"
    singular_values: list[float]
    invariants: dict[str, object]  # dc gain, poles with standard deviations
    nfev: int


def subspace_model(u: Array, y: Array, n: int, s: int | None = None) -> tuple[SubspaceModel,
                                                                                   N4SID]:
    """Order-n N4SID model of a raw record (projections on the mean-removed data, B and x0
    re-fitted on the raw data)."""
    ud, yd = u - u.mean(axis=0), y - y.mean(axis=0)
    dec = N4SID(ud, yd, s or horizon(ud, yd))
    return dec.model(n, u, y), dec


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
    # ftol: a relative cost change below 1e-6 changes no figure of the report, and the
    # flat similarity directions keep the default tolerances crawling for hundreds of steps.
    res = scipy.optimize.least_squares(resid, th0, method="trf", x_scale="jac", ftol=1e-6,
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
                T: float, has_dc_gain: bool) -> dict[str, object]:
    """DC gain (None for a model with an integrator) and continuous poles with standard
    deviations by the delta method."""

    def feats(t: Array) -> Array:
        A, B, C = th_fn(t)
        g = C @ np.linalg.solve(np.eye(A.shape[0]) - A, B) if has_dc_gain else np.zeros((0,))
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
    k = p * m if has_dc_gain else 0
    return {
        "dc_gain": f0[:k].reshape(p, m).tolist() if has_dc_gain else None,
        "dc_gain_std": sd[:k].reshape(p, m).tolist() if has_dc_gain else None,
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
    # Nelder-Mead from the best of a few splits of the innovation variance between the
    # process and the sensor: from the even split alone it can stall on the plateau where
    # R is far above the noise and Q vanishes (a mean NIS of 0.1 on the capture).
    starts = [phi0, *(np.concatenate([np.full(n, q0 + dq), np.log(r0 * fr)])
                      for dq in (-12.0, -6.0, 0.0, 3.0) for fr in (0.05, 0.3, 1.0))]
    phi_start = min(starts, key=nll)
    res = scipy.optimize.minimize(nll, phi_start, method="Nelder-Mead",
                                  bounds=list(zip(lo, hi, strict=True)),
                                  options={"xatol": 1e-3, "fatol": 1e-2, "maxfev": 300 * (n + p),
                                           "adaptive": True})
    Qc, R = np.diag(np.exp(res.x[:n])), np.diag(np.exp(res.x[n:]))
    # The Kalman gain does not change when Q and R are scaled together, so the scale is
    # the one direction the likelihood gives in closed form: s = mean NIS / p makes the
    # innovations' mean NIS p on the capture (the band the monitor's flag reads), whatever
    # split the search stopped at.
    try:
        kf = kalman(A, C, van_loan(Ac, Qc, T), R)
        w = predict(A, B, C, kf.K, u, y) @ np.linalg.inv(np.linalg.cholesky(kf.S)).T
    except (np.linalg.LinAlgError, ValueError):
        return Qc, R
    scale = float(np.mean(np.sum(w * w, axis=1))) / p
    if math.isfinite(scale) and scale > 0.0:
        Qc, R = Qc * scale, R * scale
    return Qc, R


@dataclass(frozen=True)
class _Form:
    """A continuous-time model of one order: discrete (A, B, C), their (Ac, Bc), the
    parameters and their covariance (output error: [Ac, Bc, C, x0]; prediction error:
    [A, B, C, K]) and the evaluations spent. `sub`: the subspace model a prediction-error
    refinement starts from (None when it has no continuous-time form)."""

    A: Array
    B: Array
    C: Array
    Ac: Array
    Bc: Array
    sub: SubspaceModel | None = None
    theta: Array | None = None
    cov: Array | None = None
    nfev: int = 0


def _positive_poles(A: Array, floor: float = 1e-3) -> Array:
    """A with each real pole below `floor` (those on the closed negative real axis) moved
    to the positive real axis (|z|, at least `floor`) and the others kept: the diagonal of
    the real Schur form (orthogonal, so no eigenvector conditioning)."""
    Ts, Z = scipy.linalg.schur(A, output="real")
    n = A.shape[0]
    for i in range(n):
        alone = (i == 0 or Ts[i, i - 1] == 0.0) and (i == n - 1 or Ts[i + 1, i] == 0.0)
        if alone and Ts[i, i] < floor:
            Ts[i, i] = max(abs(Ts[i, i]), floor)
    return np.asarray(Z @ Ts @ Z.T)


def _oe_unpack(th: Array, n: int, m: int, p: int) -> tuple[Array, Array, Array, Array]:
    o = np.cumsum((0, n * n, n * m, p * n, n))
    return (th[o[0]:o[1]].reshape(n, n), th[o[1]:o[2]].reshape(n, m),
            th[o[2]:o[3]].reshape(p, n), th[o[3]:o[4]])


def _continuous_oe(A: Array, B: Array, C: Array, u: Array, y: Array, T: float,
                   max_nfev: int) -> _Form:
    """Continuous-time output-error fit (see the module docstring) started from the discrete
    (A, B, C) with its negative real poles moved to the positive real axis."""
    n, m, p = A.shape[0], u.shape[1], y.shape[1]
    A1 = _positive_poles(A)
    B1, x01, _ = output_error_b(A1, C, u, y)
    Ac0, Bc0 = d2c(A1, B1, T)
    # Each output in units of its own variation, so outputs of different units count alike.
    wy = 1.0 / (np.std(y, axis=0) + 1e-300)
    bad = np.full(y.size, 1e3)

    def resid(th: Array) -> Array:
        Ac, Bc, Cc, x0 = _oe_unpack(th, n, m, p)
        if not (np.all(np.isfinite(th)) and np.abs(Ac).max() * T < 700.0):
            return bad
        Ad, Bd = c2d(Ac, Bc, T)
        r = ((y - dsim(Ad, Bd, Cc, u, x0)) * wy).ravel()
        return r if np.all(np.isfinite(r)) else bad

    th0 = np.concatenate([Ac0.ravel(), Bc0.ravel(), C.ravel(), x01])
    res = scipy.optimize.least_squares(resid, th0, method="trf", x_scale="jac", ftol=1e-6,
                                       max_nfev=max_nfev)
    th = res.x if res.cost <= 0.5 * float(np.sum(resid(th0) ** 2)) else th0
    r = resid(th)
    if r is bad:
        raise IdentifyError("the continuous-time output-error fit found no stable simulation: "
                            "record at a lower sample rate, with an anti-aliased output")
    Ac, Bc, Cc, _ = _oe_unpack(th, n, m, p)
    Ad, Bd = c2d(Ac, Bc, T)
    Jac = np.asarray(res.jac)
    s2 = float(r @ r) / max(1, r.size - th.size)
    cov = s2 * np.linalg.pinv(Jac.T @ Jac, rtol=1e-10)
    return _Form(A=Ad, B=Bd, C=Cc, Ac=Ac, Bc=Bc, theta=th, cov=cov, nfev=int(res.nfev))


def _holdout_fit(A: Array, B: Array, C: Array, u: Array, y: Array, ntr: int) -> float:
    """Mean hold-out simulation NRMSE % over the outputs (`validate.holdout_sim`); -inf for
    a simulation that blows up."""
    return _holdout(A, B, C, u, y, ntr)[0]


def _holdout(A: Array, B: Array, C: Array, u: Array, y: Array, ntr: int) -> tuple[float, float]:
    """(`_holdout_fit`, `residual_input_p` of the hold-out simulation error); (-inf, 0) for
    a simulation that blows up."""
    ysim = V.holdout_sim(A, B, C, u, y, ntr)
    f = float(np.mean(V.nrmse(y[ntr:], ysim)))
    if not math.isfinite(f):
        return -math.inf, 0.0
    return f, residual_input_p(y[ntr:] - ysim, u[ntr:])


def residual_input_p(r: Array, u: Array, ar: int = WHITEN_ORDER) -> float:
    """The least over the outputs of the p-value that a simulation error r (N, p) is
    independent of the input u (N, m): both filtered by the error's own autoregression of
    order `ar` (Yule-Walker, scipy.linalg.solve_toeplitz), which leaves the error about
    white, then `validate.cross_correlation_test`. A model error follows the input through
    any such filter; noise independent of the input stays independent of it. 1 for an
    error without variation."""
    pv = 1.0
    for i in range(r.shape[1]):
        e = r[:, i] - r[:, i].mean()
        n = e.size
        acf = np.array([float(e[:n - k] @ e[k:]) for k in range(ar + 1)]) / n
        if not acf[0] > 0.0:
            continue
        try:
            a = scipy.linalg.solve_toeplitz(acf[:ar], acf[1:ar + 1])
        except np.linalg.LinAlgError:
            continue
        whiten = np.concatenate([[1.0], -a])
        w = scipy.signal.lfilter(whiten, [1.0], e)[ar:, None]
        uf = scipy.signal.lfilter(whiten, [1.0], u - u.mean(axis=0), axis=0)[ar:]
        p_values = V.cross_correlation_test(w, uf)["p_value"]
        assert isinstance(p_values, list)
        pv = min(pv, *map(float, p_values))
    return pv


def _screen(sub: SubspaceModel, u: Array, y: Array, ntr: int, T: float) -> _Form:
    """The model of one order whose hold-out fit chooses the order: the output-error fit
    started from the subspace model, on the last SCREEN_SAMPLES of the training part and
    for a few steps (the subspace model alone can simulate far worse than its order
    allows: an integrator's pole a hair off z = 1 drifts). `sub` is kept when it has a
    continuous-time form, for the prediction-error refinement."""
    k = max(0, ntr - SCREEN_SAMPLES)
    f = _continuous_oe(sub.A, sub.B, sub.C, u[k:ntr], y[k:ntr], T, SCREEN_NFEV)
    try:
        d2c(sub.A, sub.B, T)
    except IdentifyError:
        return f
    return _Form(A=f.A, B=f.B, C=f.C, Ac=f.Ac, Bc=f.Bc, sub=sub, theta=f.theta, cov=f.cov,
                 nfev=f.nfev)


def fit_state_space(u: Array, y: Array, T: float, order: int | None, ntr: int,
                    max_nfev: int = 100) -> StateSpaceFit:
    """Black-box fit on the training part u[:ntr], y[:ntr]; the rest of the record only
    chooses the order (see the module docstring)."""
    utr, ytr = u[:ntr], y[:ntr]
    ud, yd = utr - utr.mean(axis=0), ytr - ytr.mean(axis=0)
    dec = N4SID(ud, yd, horizon(ud, yd))
    orders = [order] if order is not None else list(range(1, min(MAX_ORDER,
                                                                  dec.max_order) + 1))
    bic: dict[int, float] = {}
    hold: dict[int, float] = {}
    indep: dict[int, float] = {}
    forms: dict[int, _Form] = {}
    failed = ""
    for n in orders:
        if n > dec.max_order:
            raise IdentifyError(
                f"order {n} is more than the capture supports ({dec.max_order}): record a "
                "longer capture with a richer input, or ask for a smaller order")
        try:
            sub = dec.model(n, utr, ytr)
            forms[n] = _screen(sub, u, y, ntr, T)
        except (IdentifyError, np.linalg.LinAlgError, ValueError) as exc:
            failed = str(exc)
            continue
        bic[n] = _bic(sub, utr, ytr)
        hold[n], indep[n] = _holdout(forms[n].A, forms[n].B, forms[n].C, u, y, ntr)
    if not forms:
        # each failure's own line says what to record instead
        raise IdentifyError(f"no model of order {', '.join(map(str, orders))} is usable, the "
                            f"last because {failed}")
    best = max(hold.values())
    n = min(k for k in hold if hold[k] >= best - ORDER_MARGIN)
    screened = forms[n]
    m, p = screened.B.shape[1], screened.C.shape[0]
    nfev = screened.nfev
    fit: _Form | None = None
    if screened.sub is not None:
        pem = _pem_form(screened.sub, utr, ytr, T, max_nfev)
        nfev += pem[0].nfev
        if pem[0].theta is not None and \
                _holdout_fit(pem[0].A, pem[0].B, pem[0].C, u, y, ntr) >= hold[n] - ORDER_MARGIN:
            fit, K, e = pem
    if fit is None:
        # The refinement has a pole on the negative real axis, or simulates worse than the
        # screening fit (it weighs the next sample, not the response): the output-error
        # fit on the whole training part, from the screening fit.
        fit = _continuous_oe(screened.A, screened.B, screened.C, utr, ytr, T, max_nfev)
        nfev += fit.nfev
    if fit.sub is None:  # the output-error form: no noise model of its own
        K = np.zeros((n, p))
        e = ytr - V.fitted_x0_sim(fit.A, fit.B, fit.C, utr, ytr)
    form = "prediction error" if fit.sub is not None else "continuous output error"
    assert fit.theta is not None and fit.cov is not None
    poles = np.linalg.eigvals(fit.Ac).astype(complex)
    has_dc_gain = not np.any(integrating(poles, ntr * T))
    inv = _invariants(_abc_pem(n, m, p) if fit.sub is not None else _abc_oe(n, m, p, T),
                      fit.theta, fit.cov, T, has_dc_gain)
    Re = e.T @ e / e.shape[0]
    Qc, R = noise_ml(fit.A, fit.B, fit.C, fit.Ac, utr, ytr, T, Re)
    q = float(np.trace(Qc)) / n  # Qc = q Q0 with Q0 = Qc / q (trace n)
    return StateSpaceFit(A=fit.A, B=fit.B, C=fit.C, K=K, Ac=fit.Ac, Bc=fit.Bc, Qc=Qc, q=q, R=R,
                         order=n, bic=bic, holdout_fit=hold, holdout_input_p=indep, form=form,
                         singular_values=[float(v) for v in dec.singular_values[:12]],
                         invariants=inv, nfev=nfev)


def _pem_form(sub: SubspaceModel, u: Array, y: Array, T: float, max_nfev: int
              ) -> tuple[_Form, Array, Array]:
    """(form, K, innovations) of the prediction-error refinement of `sub`; the form has no
    theta when the refinement has no continuous-time counterpart."""
    A, B, C, K, cov, e, nfev = _pem(sub, u, y, max_nfev)
    try:
        Ac, Bc = d2c(A, B, T)
    except IdentifyError:
        return _Form(A=A, B=B, C=C, Ac=A, Bc=B, sub=sub, nfev=nfev), K, e
    theta = np.concatenate([A.ravel(), B.ravel(), C.ravel(), K.ravel()])
    return _Form(A=A, B=B, C=C, Ac=Ac, Bc=Bc, sub=sub, theta=theta, cov=cov, nfev=nfev), K, e


def _abc_pem(n: int, m: int, p: int) -> Callable[[Array], tuple[Array, Array, Array]]:
    """Discrete (A, B, C) of the prediction-error parameters [A, B, C, K]."""
    def abc(th: Array) -> tuple[Array, Array, Array]:
        return (th[:n * n].reshape(n, n), th[n * n:n * n + n * m].reshape(n, m),
                th[n * n + n * m:n * n + n * m + p * n].reshape(p, n))
    return abc


def _abc_oe(n: int, m: int, p: int, T: float) -> Callable[[Array], tuple[Array, Array, Array]]:
    """Discrete (A, B, C) of the output-error parameters [Ac, Bc, C, x0]."""
    def abc(th: Array) -> tuple[Array, Array, Array]:
        Ac, Bc, C, _ = _oe_unpack(th, n, m, p)
        return (*c2d(Ac, Bc, T), C)
    return abc
