"""Grey-box fit of the Table-1 DC motor (63)-(68) from voltage and current.

The current's transfer function is

    I(s)/U(s) = (J s + b) / (La J s^2 + (La b + Ra J) s + Ra b + Ke Ki),

four coefficients up to the common scale of (J, b, Ke Ki): from the current alone La, Ra,
b/J and Ke Ki/J are identifiable, J is not. J is fixed (to the template's) and La, Ra, b
and Ke = Ki = sqrt(Ke Ki) are fitted; a different J gives the same current, the same
filter and the same gamma^.

The fit is a prediction-error (PEM) fit of the steady-state Kalman predictor of the model
discretised by zero-order hold, with the noise model (1)-(2) of `dc_motor`: process-noise
intensity q Q0 on the standard-form states, Q0 = diag(1, kappa, kappa) (current, speed,
angle), and current-sensor variance r. `dc_motor` has kappa = 1; here kappa is fitted,
because fixing J fixes the unit of the speed state, and the speed noise's intensity in
that unit scales with it (without kappa, the wrong J would leave the innovations coloured).
The predictor's gain depends only on rho = q / r and kappa, so the parameters are
theta = log(La, Ra, b, Ke Ki, rho, kappa), least squares on the innovations
(scipy.optimize.least_squares), which for one output is the maximum-likelihood fit (the
likelihood concentrated over the common scale of (q, r)). Then r = mean(e^2) / S(r = 1):
the one-step innovation variance minus what the process noise explains (C P C'), and
q = rho r; so the mean NIS of the predictor is exactly 1 on the fitted data.

Initial guess: the order-2 subspace model, converted to continuous time and to physical
parameters, and the template; each is first refined as an output-error fit (simulation,
no noise model), the better one is kept. rho, then kappa, start from scans over 15 and 13
decades (the cost has a plateau at each end: pure simulation, and a predictor that trusts
the last sample), and the joint fit is bounded to +-4 decades around them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.optimize
import scipy.signal
from numpy.typing import NDArray

from monitor.estimation.model import DCMotorParameters, van_loan
from monitor.identify.lti import Kalman, c2d, d2c, dsim, kalman, predict, steady_state_x0
from monitor.identify.subspace import SubspaceModel

Array = NDArray[np.float64]

__all__ = ["DCMotorFit", "fit_dc_motor", "motor_matrices", "oe_refit"]

NAMES = ("La", "Ra", "b", "KeKi")


@dataclass(frozen=True)
class DCMotorFit:
    params: DCMotorParameters
    q: float
    r: float
    log_std: dict[str, float]  # standard deviation of log(parameter), from the Jacobian
    rho: float
    kappa: float  # speed-noise intensity relative to the current's
    nfev: int


def motor_matrices(th: Array, J: float) -> tuple[Array, Array, Array]:
    """Continuous (A, B, C) on the observable states [current, speed] for log-parameters."""
    La, Ra, b, kk = np.exp(th[:4])
    ke = math.sqrt(kk)
    A = np.array([[-Ra / La, -ke / La], [ke / J, -b / J]])
    B = np.array([[1.0 / La], [0.0]])
    C = np.array([[1.0, 0.0]])
    return A, B, C


class _Model:
    """Residuals of the motor model on one record (simulation or prediction errors)."""

    def __init__(self, u: Array, y: Array, J: float, T: float) -> None:
        self.u, self.y, self.J, self.T = u, y, J, T
        self.bad = np.full(y.shape[0], 1e3 * (float(np.std(y)) + 1e-12))

    def discrete(self, th: Array) -> tuple[Array, Array, Array, Array]:
        Ac, Bc, C = motor_matrices(th, self.J)
        if not (np.all(np.isfinite(Ac)) and np.abs(Ac).max() * self.T < 700.0):
            raise ValueError("parameters out of range")
        A, B = c2d(Ac, Bc, self.T)
        if not (np.all(np.isfinite(A)) and np.all(np.isfinite(B))):
            raise ValueError("parameters out of range")
        return Ac, A, B, C

    def kalman(self, th: Array) -> Kalman:
        Ac, A, _, C = self.discrete(th)
        Qd = van_loan(Ac, math.exp(th[4]) * np.diag([1.0, math.exp(th[5])]), self.T)
        return kalman(A, C, Qd, np.eye(1))

    def sim_error(self, th: Array) -> Array:
        try:
            _, A, B, C = self.discrete(th)
            x0 = steady_state_x0(A, B, C, self.u[0], self.y[0])
            e = (self.y - dsim(A, B, C, self.u, x0)).ravel()
        except (np.linalg.LinAlgError, ValueError, OverflowError):
            return self.bad
        return e if np.all(np.isfinite(e)) else self.bad

    def pred_error(self, th: Array) -> Array:
        try:
            _, A, B, C = self.discrete(th)
            kf = self.kalman(th)
            e = predict(A, B, C, kf.K, self.u, self.y).ravel()
        except (np.linalg.LinAlgError, ValueError, OverflowError):
            return self.bad
        return e if np.all(np.isfinite(e)) else self.bad


def _from_subspace(sub: SubspaceModel, T: float, J: float) -> Array | None:
    """log(La, Ra, b, KeKi) matching an order-2 discrete model's continuous tf, or None."""
    try:
        Ac, Bc = d2c(sub.A, sub.B, T)
    except ValueError:
        return None
    num, den = scipy.signal.ss2tf(Ac, Bc, sub.C, np.zeros((1, 1)))
    n0, n1 = float(num[0, -2]), float(num[0, -1])
    a1, a0 = float(den[1]), float(den[2])
    if not (n0 > 0 and a1 > 0 and a0 > 0):
        return None
    La = 1.0 / n0
    beta = n1 / n0 if n1 > 0 else 1e-3 * a1  # b / J
    beta = min(beta, 0.999 * a1)
    ra_la = a1 - beta
    kk = (a0 - ra_la * beta) * La * J
    if kk <= 0:
        kk = 0.5 * a0 * La * J
    return np.log([La, ra_la * La, beta * J, kk])


def fit_dc_motor(
    u: Array, y: Array, T: float, template: DCMotorParameters, sub: SubspaceModel | None
) -> DCMotorFit:
    """PEM fit of the motor on (u, y) sampled at T (see the module docstring)."""
    J = template.J
    mdl = _Model(u, y, J, T)
    starts = [np.log([template.La if template.La > 0 else 1e-3, template.Ra, template.b,
                      template.Ke * template.Ki])]
    if sub is not None:
        guess = _from_subspace(sub, T, J)
        if guess is not None:
            starts.insert(0, guess)
    best: scipy.optimize.OptimizeResult | None = None
    for th0 in starts:
        res = scipy.optimize.least_squares(
            lambda th: mdl.sim_error(np.append(th, [0.0, 0.0])), th0, method="lm", max_nfev=200
        )
        if best is None or res.cost < best.cost:
            best = res
    assert best is not None
    th4 = best.x
    nfev = int(best.nfev)
    # rho, then kappa: scans, then a joint PEM fit bounded to +-4 decades around them.
    dec = math.log(10.0)
    grid = dec * np.arange(-8.0, 7.5, 1.0) - math.log(T)
    costs = [float(np.sum(mdl.pred_error(np.append(th4, [g, 0.0])) ** 2)) for g in grid]
    g0 = float(grid[int(np.argmin(costs))])
    kgrid = dec * np.arange(-6.0, 6.5, 1.0)
    costs = [float(np.sum(mdl.pred_error(np.append(th4, [g0, k])) ** 2)) for k in kgrid]
    k0 = float(kgrid[int(np.argmin(costs))])
    lo = np.array([-np.inf] * 4 + [g0 - 4 * dec, k0 - 4 * dec])
    hi = np.array([np.inf] * 4 + [g0 + 4 * dec, k0 + 4 * dec])
    res = scipy.optimize.least_squares(mdl.pred_error, np.append(th4, [g0, k0]),
                                       bounds=(lo, hi), method="trf", x_scale=1.0,
                                       max_nfev=300)
    th = res.x
    e = mdl.pred_error(th)
    kf = mdl.kalman(th)
    N = e.size
    r = float(np.mean(e**2) / kf.S[0, 0])
    rho = math.exp(th[4])
    # Asymptotic covariance of the PEM estimate: sigma^2 (J'J)^-1 (white innovations).
    Jac = np.asarray(res.jac)
    s2 = float(e @ e) / max(1, N - th.size)
    cov = s2 * np.linalg.pinv(Jac.T @ Jac)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    La, Ra, b, kk = np.exp(th[:4])
    ke = math.sqrt(kk)
    params = DCMotorParameters(J=J, b=float(b), Ke=ke, Ki=ke, Ra=float(Ra), La=float(La))
    log_std = {"La": float(sd[0]), "Ra": float(sd[1]), "b": float(sd[2]),
               "Ke": float(0.5 * sd[3]), "Ki": float(0.5 * sd[3]), "rho": float(sd[4]),
               "kappa": float(sd[5])}
    return DCMotorFit(params=params, q=rho * r, r=r, log_std=log_std, rho=rho,
                      kappa=math.exp(th[5]), nfev=nfev + int(res.nfev) + len(grid) + len(kgrid))


def oe_refit(u: Array, y: Array, T: float, params: DCMotorParameters) -> tuple[Array, Array,
                                                                                  Array]:
    """Discrete (A, B, C) of an output-error fit started at `params` (J kept)."""
    mdl = _Model(u, y, params.J, T)
    th0 = np.log([params.La, params.Ra, params.b, params.Ke * params.Ki])
    res = scipy.optimize.least_squares(lambda th: mdl.sim_error(np.append(th, [0.0, 0.0])), th0,
                                       method="lm", max_nfev=100)
    _, A, B, C = mdl.discrete(np.append(res.x, [0.0, 0.0]))
    return A, B, C
