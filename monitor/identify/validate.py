"""What a practitioner checks before trusting a model, and the refusals of bad captures.

Refusals (each an IdentifyError with one line saying what to record instead):

* non-finite samples, or u and y of different lengths;
* too short: fewer than MIN_SAMPLES samples, or (after the fit) a training part shorter
  than MIN_TIME_CONSTANTS of the model's slowest time constant that the fit resolves
  (`resolved_time_constant`: a pole whose distance from s = 0 is within RESOLVED_SD of
  its standard deviations is an integrator as far as the capture tells -- a sensor offset
  the black box carries as a near-integrating state, a position -- and asks for no
  length; the replay of the capture judges whether such a model serves);
* not exciting enough: an input that does not move (std below 1e-6 of its RMS), that
  changes fewer than MIN_CHANGES times in the training part or not at all in the held-out
  part (`check_holdout_changes`: its fit would judge a flat record), or that is not
  persistently exciting of the order the model needs (the smallest singular value of the
  block Hankel matrix of the centred inputs with 2 n + 1 rows below 1e-7 of the largest: a
  sine is exciting of order 2 only);
  and, after the fit, a training fit below MIN_FIT % (the input moves the output too
  little against the noise);
* an output that cannot show the response (`check_outputs`): stuck at one value,
  quantised to fewer than MIN_LEVELS values, or held at its largest or smallest value for
  more than SATURATED of the capture (clipped by a sensor, DBC or current limit);
* a fault or outage inside the capture: the same model structure fitted separately on the
  first and the second half must explain the other half nearly as well as its own: the
  simulation fit (NRMSE, each model with its own best initial state) of the other half's
  model may be at most CONSISTENCY_DROP points below the half's own (a healthy capture
  gives 0 to 4 points, whatever the noise, as the fit is relative to the output's
  variation; a 10 % loss of effectiveness in the middle gives well over 100). For a model
  with an integrator each simulation is compared after removing an offset and a ramp
  (a small gain error of an integrator drifts without any change in the plant). Also a
  hold-out fit more than HOLDOUT_DROP points below the training fit (a change inside the
  hold-out tail);
* a structure that does not fit: a training fit below MIN_FIT with residuals correlated
  with the input (and a halves drop below STRUCTURE_DROP: an order too small also fits
  the halves somewhat differently, a fault makes them differ by far more).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import scipy.stats
from numpy.typing import NDArray

from monitor.identify.errors import IdentifyError
from monitor.identify.excitation import RECORDING_ADVICE
from monitor.identify.lti import dsim

Array = NDArray[np.float64]

__all__ = [
    "CONFIDENCE",
    "check_capture",
    "check_excitation",
    "check_holdout_changes",
    "check_outputs",
    "consistency_drop",
    "cross_correlation_test",
    "fitted_x0_sim",
    "holdout_sim",
    "level_count",
    "nrmse",
    "resolved_time_constant",
    "whiteness_test",
]

MIN_SAMPLES = 1000
MIN_LEVELS = 16  # an output with fewer distinct values is quantised too coarsely
SATURATED = 0.05  # share of the capture at the output's extreme value: clipped
MIN_TIME_CONSTANTS = 10.0
RESOLVED_SD = 2.0  # a pole this many standard deviations from s = 0 is told from it
MIN_CHANGES = 4
"""The fewest changes of each input in the training part. Each change is a step response:
a few show a plant whose time constants are well inside the holds, and the checks after
the fit (halves, hold-out, the replay and its added losses) judge whether they were
enough. The rig zoo's seed 16 (a torque on two masses, a PRBS switching every 3 s: 6
changes in the training part) is diagnosed right; 10 refused it."""
#: Fewer distinct input levels than this check the model between them alone: two (a
#: binary PRBS) cannot tell a gain that changes with the level (an actuator that saturates
#: at one of them) from a smaller gain plus an offset.
MIN_INPUT_LEVELS = 3
LEVEL_RESOLUTION = 1e-3  # of an input's range: a smaller move is no change, and no other level
MIN_FIT = 30.0
CONSISTENCY_DROP = 10.0
STRUCTURE_DROP = 50.0
HOLDOUT_DROP = 25.0
CONFIDENCE = 0.99
LAGS = 25
MIN_PE_RATIO = 1e-7  # smallest/largest singular value of the input's Hankel matrix


def resolved_time_constant(poles: Sequence[Sequence[float]], real: Sequence[float] | None,
                           real_std: Sequence[float] | None) -> float:
    """The slowest time constant (s) among the stable continuous `poles` ([re, im] each)
    whose real part the fit tells from 0: the matching pole of the fit's invariants
    (nearest real part in `real`, with standard deviation `real_std`) lies more than
    RESOLVED_SD standard deviations from 0. Without invariants (None) every pole counts.
    inf when none does."""
    taus = []
    for re, _ in poles:
        if not re < 0.0:
            continue
        if real and real_std and len(real) == len(real_std):
            j = int(np.argmin(np.abs(np.asarray(real, float) - re)))
            sd = float(real_std[j])
            if math.isfinite(sd) and abs(float(real[j])) <= RESOLVED_SD * sd:
                continue
        taus.append(-1.0 / re)
    return max(taus, default=math.inf)


def check_capture(u: Array, y: Array, T: float, holdout: float) -> tuple[Array, Array]:
    """Shapes, finiteness and the minimum length; returns float (N, m) and (N, p) arrays."""
    if not (math.isfinite(T) and T > 0):
        raise IdentifyError(f"sample period must be a positive number of seconds, got {T!r}")
    if not 0.0 < holdout < 0.9:
        raise IdentifyError(f"holdout must be a fraction in (0, 0.9), got {holdout!r}")
    ua = np.asarray(u, dtype=float)
    ya = np.asarray(y, dtype=float)
    ua = ua[:, None] if ua.ndim == 1 else ua
    ya = ya[:, None] if ya.ndim == 1 else ya
    if ua.ndim != 2 or ya.ndim != 2 or ua.shape[0] != ya.shape[0]:
        raise IdentifyError(f"inputs {ua.shape} and outputs {ya.shape} must be (N, m) and "
                            "(N, p) arrays of the same N: resample both onto one clock")
    for name, arr in (("input", ua), ("output", ya)):
        bad = ~np.isfinite(arr)
        if bad.any():
            k = int(np.argwhere(bad)[0][0])
            raise IdentifyError(
                f"{int(bad.sum())} non-finite {name} samples (first at {k * T:.3f} s): "
                "record without gaps or cut the capture to a gap-free stretch")
    N = ua.shape[0]
    need = MIN_SAMPLES
    if need > N:
        raise IdentifyError(
            f"capture too short: {N * T:.3g} s ({N} samples at {1 / T:.4g} Hz); record at "
            f"least {need * T:.3g} s, better 60 s, with the input varying")
    return ua, ya


def _resolution(u: Array) -> Array:
    """The least move of an input that counts as a change, or sets two levels apart:
    LEVEL_RESOLUTION of its range over `u` (per column of (N, m), or of a column)."""
    return np.asarray(LEVEL_RESOLUTION * (np.ptp(u, axis=0) + 1e-300))


def level_count(col: Array) -> int:
    """How many distinct levels an input took: values LEVEL_RESOLUTION of its range apart
    are one level."""
    return int(np.unique(np.round((col - col.min()) / float(_resolution(col)))).size)


def _changes(col: Array, step: float) -> int:
    """How many times an input moves by more than `step` from one sample to the next."""
    return int(np.sum(np.abs(np.diff(col)) > step))


def check_holdout_changes(u: Array, ntr: int, names: Sequence[str]) -> None:
    """Refuse an input that does not change in the held-out rows u[ntr:] (a change is
    LEVEL_RESOLUTION of the input's range over the whole capture u; `check_excitation`
    takes the range over the training part it is given): the hold-out's fit would judge
    the model on a flat record."""
    step = _resolution(u)
    for j in range(u.shape[1]):
        if _changes(u[ntr:, j], float(step[j])) == 0:
            raise IdentifyError(
                f"input '{names[j]}' does not change in the last {u.shape[0] - ntr} samples, "
                f"which check the model: {RECORDING_ADVICE}")


def check_excitation(u: Array, order: int, names: Sequence[str]) -> dict[str, object]:
    """Refuse an input that cannot identify a model of `order` states; report PE and how
    many distinct levels each input took (`LEVEL_RESOLUTION`)."""
    rms = np.sqrt(np.mean(u**2, axis=0))
    sd = np.std(u, axis=0)
    step = _resolution(u)
    levels: list[int] = []
    for j in range(u.shape[1]):
        if sd[j] <= 1e-6 * max(float(rms[j]), 1e-300):
            raise IdentifyError(
                f"input '{names[j]}' is constant ({u[0, j]:.4g}) over the capture, so nothing "
                f"can be identified: {RECORDING_ADVICE}")
        changes = _changes(u[:, j], float(step[j]))
        if changes < MIN_CHANGES:
            raise IdentifyError(
                f"input '{names[j]}' changes only {changes} times: {RECORDING_ADVICE}")
        levels.append(level_count(u[:, j]))
    L = 2 * order + 1
    uc = (u - u.mean(axis=0)) / sd
    N, m = uc.shape
    H = np.lib.stride_tricks.sliding_window_view(uc, L, axis=0).reshape(N - L + 1, m * L)
    s = np.linalg.svd(H / math.sqrt(H.shape[0]), compute_uv=False)
    ratio = float(s[-1] / s[0])
    pe = int(np.sum(s > MIN_PE_RATIO * s[0]))
    if ratio < MIN_PE_RATIO:
        raise IdentifyError(
            f"the input is persistently exciting of order {pe // m} only, a {order}-state "
            f"model needs {L} (a sine gives 2): {RECORDING_ADVICE}")
    return {"persistent_excitation_rows": L, "hankel_singular_ratio": ratio,
            "input_levels": levels}


def check_outputs(y: Array, names: Sequence[str]) -> None:
    """Refuse an output that cannot show the plant's response: stuck at one value, taking
    fewer than MIN_LEVELS distinct values (quantised far coarser than its variation), or
    sitting at its largest or smallest value for more than SATURATED of the capture (a
    sensor, DBC or current limit clips it). A healthy output of a plant driven around its
    operating point varies continuously: its extremes are reached once or a few times."""
    N = y.shape[0]
    for i, name in enumerate(names):
        col = y[:, i]
        levels = np.unique(col)
        if levels.size == 1:
            raise IdentifyError(
                f"output '{name}' is stuck at {col[0]:.6g} over the whole capture: the sensor "
                "does not measure, or this is not the output the input drives; check the "
                "sensor and the rig's signals, then record again")
        if levels.size < MIN_LEVELS:
            step = float(np.min(np.diff(levels)))
            raise IdentifyError(
                f"output '{name}' takes only {levels.size} distinct values (steps of "
                f"{step:.4g}) over the capture: quantised far coarser than its variation, "
                "so its dynamics are lost; record the output at a finer resolution (the DBC "
                "signal's scale), or with larger input steps")
        for where, value in (("largest", levels[-1]), ("smallest", levels[0])):
            share = float(np.count_nonzero(col == value)) / N
            if share > SATURATED:
                raise IdentifyError(
                    f"output '{name}' sits at its {where} value {value:.6g} for "
                    f"{100 * share:.0f} % of the capture: saturated (a sensor, DBC or "
                    "current limit), where it no longer follows the input; record with "
                    "smaller input steps that keep it inside its range")


def nrmse(y: Array, yhat: Array) -> list[float]:
    """Fit per output, 100 (1 - ||y - yhat|| / ||y - mean(y)||) %."""
    num = np.linalg.norm(y - yhat, axis=0)
    den = np.linalg.norm(y - y.mean(axis=0), axis=0)
    return [float(100.0 * (1.0 - a / b)) if b > 0 else float("nan") for a, b in zip(num, den,
                                                                                     strict=True)]


def _acf(x: Array, lags: int) -> Array:
    x = x - x.mean()
    d = float(x @ x)
    return np.array([float(x[k:] @ x[:x.size - k]) / d for k in range(1, lags + 1)])


def whiteness_test(w: Array, lags: int = LAGS, dof_used: int = 0) -> dict[str, object]:
    """Autocorrelation of each normalised innovation with the CONFIDENCE band, and the
    Ljung-Box statistic Q = N (N+2) sum r_k^2 / (N - k), chi-square with lags - dof_used
    degrees of freedom. Passes when every output's p-value is above 1 - CONFIDENCE."""
    N, p = w.shape
    band = float(scipy.stats.norm.ppf(0.5 + CONFIDENCE / 2) / math.sqrt(N))
    acfs, qs, pv = [], [], []
    k = np.arange(1, lags + 1)
    for i in range(p):
        r = _acf(w[:, i], lags)
        q = float(N * (N + 2) * np.sum(r**2 / (N - k)))
        acfs.append(r.tolist())
        qs.append(q)
        pv.append(float(scipy.stats.chi2.sf(q, max(1, lags - dof_used))))
    return {
        "lags": lags,
        "confidence": CONFIDENCE,
        "band": band,
        "autocorrelation": acfs,
        "ljung_box_q": qs,
        "p_value": pv,
        "variance": [float(v) for v in np.var(w, axis=0)],
        "passed": bool(min(pv) > 1 - CONFIDENCE),
    }


def cross_correlation_test(w: Array, u: Array, lags: int = LAGS) -> dict[str, object]:
    """Correlation of each normalised innovation with past inputs (lags 0..lags) with the
    CONFIDENCE band, and the joint test: N R^2 of the regression of the innovation on the
    lagged centred inputs is chi-square with rank(regressors) degrees of freedom when the
    innovation is white and independent of the input (valid for a coloured input, unlike a
    sum of squared correlations). Passes when every output's p-value is above
    1 - CONFIDENCE."""
    N, p = w.shape
    m = u.shape[1]
    uc = u - u.mean(axis=0)
    band = float(scipy.stats.norm.ppf(0.5 + CONFIDENCE / 2) / math.sqrt(N))
    X = np.column_stack([uc[lags - k:N - k, j] for j in range(m) for k in range(lags + 1)])
    X = X / (np.std(X, axis=0) + 1e-300)
    values, stats, pv = [], [], []
    for i in range(p):
        e = w[:, i] - w[:, i].mean()
        per_u = []
        for j in range(m):
            uj = uc[:, j]
            den = math.sqrt(float(e @ e) * float(uj @ uj)) or 1.0
            per_u.append([float(e[k:] @ uj[:N - k]) / den for k in range(lags + 1)])
        values.append(per_u)
        ee = e[lags:]
        coef, _, rank, _ = np.linalg.lstsq(X, ee, rcond=1e-8)
        fit = X @ coef
        r2 = float(fit @ fit) / float(ee @ ee)
        stat = ee.size * r2
        stats.append(stat)
        pv.append(float(scipy.stats.chi2.sf(stat, max(1, int(rank)))))
    return {
        "lags": lags,
        "confidence": CONFIDENCE,
        "band": band,
        "correlation": values,
        "statistic": stats,
        "p_value": pv,
        "passed": bool(min(pv) > 1 - CONFIDENCE),
    }


def fitted_x0_sim(A: Array, B: Array, C: Array, u: Array, y: Array, rows: int | None = None,
                  trend: bool = False) -> Array:
    """Simulated output of (A, B, C) on a record from the initial state that fits the first
    `rows` samples best (least squares; all samples by default). `trend` also removes an
    offset and a ramp per output: a model with an integrator drifts by the integral of a
    small gain error, which says nothing about whether the plant changed."""
    n = A.shape[0]
    N, p = y.shape
    k = N if rows is None else rows
    ys = dsim(A, B, C, u)
    cols = [dsim(A, np.zeros((n, 1)), C, np.zeros((N, 1)), np.eye(n)[i]) for i in range(n)]
    if trend:
        t = np.linspace(-1.0, 1.0, N)
        for i in range(p):
            for f in (np.ones(N), t):
                col = np.zeros((N, p))
                col[:, i] = f
                cols.append(col)
    Phi = np.column_stack([c.ravel() for c in cols])
    coef, *_ = np.linalg.lstsq(Phi[:k * p], (y[:k] - ys[:k]).ravel(), rcond=None)
    return np.asarray(ys + (Phi @ coef).reshape(N, p))


def holdout_sim(A: Array, B: Array, C: Array, u: Array, y: Array, ntr: int) -> Array:
    """Simulated output (N - ntr, p) of (A, B, C) on the hold-out u[ntr:], from the state
    that fits the last stretch of the training part (so the hold-out samples are not
    used): the simulation fit that chooses a black box's order."""
    w = min(ntr, max(200, ntr // 10))
    return fitted_x0_sim(A, B, C, u[ntr - w:], y[ntr - w:], rows=w)[w:]


def consistency_drop(first: tuple[Array, Array, Array], second: tuple[Array, Array, Array],
                     halves: tuple[tuple[Array, Array], tuple[Array, Array]],
                     trend: bool = False) -> list[float]:
    """Per half: how many NRMSE points the other half's model fits it worse than its own
    (the largest over the outputs); `trend` as `fitted_x0_sim` (for integrating plants)."""
    out = []
    for own, other, (u, y) in ((first, second, halves[0]), (second, first, halves[1])):
        f_own = nrmse(y, fitted_x0_sim(*own, u, y, trend=trend))
        f_other = nrmse(y, fitted_x0_sim(*other, u, y, trend=trend))
        out.append(max(a - b for a, b in zip(f_own, f_other, strict=True)))
    return out
