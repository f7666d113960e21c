"""The process noise refitted after the measurement noise R is fixed (its quantisation floor).

`identify` learns Q and R together by the likelihood of the steady-state Kalman filter's
innovations (`monitor.identify.blackbox.noise_ml`, the noise model (1)-(2) of Liu, Bao,
Xue, Du, Int. J. Fuzzy Syst. 22(1), 2020). Where a fit gives R below the variance its
output's rounding adds (`monitor.identify.core.quantisation_floor`), that rounding went to
Q: raising R alone leaves the process noise as large as it was, the innovation covariance
S = C P C' + R too large and the mean NIS below its p (0.89 on a first-order plant whose
learned R was 12 % under the floor), low enough to fail the replay's NIS band. The
refit keeps the fitted noise's shape (Qc up to a scale s) and R as floored and takes the
s of the largest likelihood of the innovations, as the fit would have with R held there.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.optimize
from numpy.typing import NDArray

from monitor.estimation.model import ContinuousDescriptor, ModelError
from monitor.identify.lti import kalman, predict

Array = NDArray[np.float64]

__all__ = ["SCALE_RANGE", "process_noise_scale"]

SCALE_RANGE = (1e-8, 1e2)
"""The scales of Qc the refit searches: R rises only, so the process noise that explains
the rest shrinks, down to nothing (an output whose only noise is its rounding); a little
above 1 covers what a coarser S's closure moves."""


def process_noise_scale(model: ContinuousDescriptor, u: Array, y: Array, T: float) -> float:
    """The scale s of `model`'s Qc (R as it is) that maximises the Gaussian likelihood of
    the steady-state Kalman filter's innovations of inputs `u` (N, m) and outputs `y`
    (N, p) sampled every T: N log det S + sum e' S^-1 e, over log s (Qd is linear in Qc,
    so the discrete noise scales with it). 1.0 where the model cannot be discretised or no
    scale gives a stabilising filter (the model is then kept as it is)."""
    try:
        dm = model.discretize(T)
    except ModelError:
        return 1.0
    A, B, Qd = dm.at(T)
    C, R = dm.C, np.asarray(dm.R, dtype=float)
    N = y.shape[0]

    def nll(log_s: float) -> float:
        try:
            kf = kalman(A, C, math.exp(log_s) * Qd, R)
            e = predict(A, B, C, kf.K, u, y)
            w = e @ np.linalg.inv(np.linalg.cholesky(kf.S)).T
        except (np.linalg.LinAlgError, ValueError):
            return math.inf
        value = float(N * np.linalg.slogdet(kf.S)[1] + np.sum(w * w))
        return value if math.isfinite(value) else math.inf

    lo, hi = (math.log(s) for s in SCALE_RANGE)
    # the likelihood is smooth in log s; a coarse grid first keeps the bounded search off
    # a flat end (a Q that vanishes against R changes the likelihood very little)
    grid = np.linspace(lo, hi, 23)
    values = [nll(float(g)) for g in grid]
    best = int(np.argmin(values))
    if not math.isfinite(values[best]):
        return 1.0
    a, b = float(grid[max(best - 1, 0)]), float(grid[min(best + 1, grid.size - 1)])
    res = scipy.optimize.minimize_scalar(nll, bounds=(a, b), method="bounded",
                                         options={"xatol": 1e-3})
    x = float(res.x) if res.success and res.fun <= values[best] else float(grid[best])
    return math.exp(x)
