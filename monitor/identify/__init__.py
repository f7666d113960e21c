"""Identification of a node's model from a healthy capture: arrays in, model and report out.

`identify(u, y, T)` fits either the Table-1 DC-motor structure (63)-(68) on its physical
parameters (`dcmotor`) or a black-box continuous-time state-space model (`blackbox`), with
the noise model (1)-(2) the estimator needs (process-noise intensity q and per-sample R,
chosen so the Kalman filter's normalised innovations are white with unit variance; R no
lower than the variance an output's known quantisation step adds, `quantisation_floor`), and
a report of what a practitioner checks before trusting it (`validate`): hold-out NRMSE by
simulation, innovation whiteness (Ljung-Box), input-innovation cross-correlation,
parameter standard deviations, R and Q, the mean NIS of the Kalman filter and of the
FuzzyUKF on the capture, the time taken. Captures that cannot give a trustworthy model are
refused with one line saying what to record instead (`IdentifyError`).

Libraries. scipy (and threadpoolctl, to keep BLAS on one thread: multithreaded OpenBLAS on
the many tiny matrices of a fit was 20 times slower on a loaded 2-core machine than one
thread; ruptures for the change points of an unmeasured load, `load`):
scipy.optimize.least_squares for the output-error and prediction-error fits, scipy.linalg
(QR, SVD, Schur, logm, expm, solve_discrete_are) for N4SID, the inverse zero-order hold
and the Kalman predictor, scipy.signal (cont2discrete, lfilter) for discretisation and
filtering, scipy.stats for the tests. The N4SID steps are a few calls of these
(`subspace`). Evaluated and rejected: nfoursid 1.0.2 (imports matplotlib and pandas at
module level, both would become hard dependencies of the daemon, and it takes the full SVD
of an (i p) x N matrix, whose N x N right factor is 29 GB for 60 s at 1 kHz); sippy-unipi
1.0.1 (pulls casadi, sympy, tf2ss and python-control, hence matplotlib, for the same
subspace method); python-control 0.10.2 and harold 1.0.3 (no identification at all, only
models and simulation that scipy has, and both require matplotlib; harold was last
released in 2022 and pins tabulate < 0.9); statsmodels (only for a Ljung-Box test, a
three-line formula with scipy.stats.chi2). scipy.signal.dlsim was too slow inside a fit (a
Python loop per sample), and so, at 2 kHz, was the recursion through the complex Schur form
with one lfilter per coordinate: `lti.dsim` is the recursion compiled (`monitor.jit`).
"""

from monitor.identify.core import (
    KINDS,
    Identification,
    identify,
    nis_calibrated,
    quantisation_floor,
)
from monitor.identify.errors import IdentifyError
from monitor.identify.excitation import RECORDING_ADVICE, prbs

__all__ = ["KINDS", "RECORDING_ADVICE", "Identification", "IdentifyError", "identify",
           "nis_calibrated", "prbs", "quantisation_floor"]
