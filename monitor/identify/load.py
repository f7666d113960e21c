"""Unmeasured load steps for `identify`: the load a capture's input does not hold, as a
piecewise-constant input bias d (y = G (u + d)), the way the monitor's bias states carry it
at run time (`monitor.estimation.bias`, kind "input").

A drive's load torque steps while the capture runs (a brake, a gravity load, a process
force). A linear fit that lacks it explains the steps with the plant: a slow or growing
mode, a gain that differs between the capture's halves; identify then refuses a healthy
capture as one whose plant changes. The load is not measured, but the model's filter sees
it. Given a model (A, B, C, Qd, R of (1)-(2), discretised):

1. The state is augmented with one input bias per input, a random walk of variance q_d per
   step (the disturbance model of offset-free estimation); q_d maximises the likelihood of
   the augmented steady-state Kalman predictor's innovations (`scipy.optimize`).
2. The steady-state Rauch-Tung-Striebel smoother gives d over the capture.
3. Its change points (`ruptures`' binary segmentation, nested for every count K) on a
   decimated copy, each placed at full rate where the split of its neighbourhood is best.
4. For each K the levels that minimise the innovations of the model's own predictor
   driven by u + d (linear in the levels: generalised least squares), together with a
   correction of the input's gain (a gain error and a constant load trade off where the
   input has a mean level), and K chosen by BIC on those innovations (a row and m levels
   per change).

`identify` alternates (as `monitor.identify.friction` does): the fit with u + d as its
input, d from the previous model, until d settles (`settled`) or the fit stops improving.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import ruptures
import scipy.linalg
import scipy.optimize
from numpy.typing import NDArray

from monitor.estimation.model import ContinuousDescriptor
from monitor.identify.errors import IdentifyError
from monitor.identify.lti import dsim, kalman, predict, steady_state_x0

Array = NDArray[np.float64]

__all__ = ["LOAD_ITERATIONS", "LoadSteps", "load_steps", "settled"]

LOAD_ITERATIONS = 6
"""At most this many refits of the load's fixed-point iteration. A first fit carries part
of each step on a slow mode, which gives way over the refits: on a first-order speed with
five steps the levels settle within 0.01 after four (the gain correction of step 4 is what
makes it few)."""

SETTLED = 0.02
"""The iteration stops once the change rows stay and no level moves by more than this
share of the largest level step."""

MIN_SEGMENT_S = 1.0
"""The shortest stretch a load holds: changes closer than this are one change (a load
that moves faster is a disturbance the process noise must carry, not a step)."""

DECIMATED_POINTS = 6000
"""The change points are searched on at most this many points of the smoothed load."""

_NUMERIC = (np.linalg.LinAlgError, ValueError, FloatingPointError, ZeroDivisionError)


@dataclass(frozen=True)
class LoadSteps:
    """A piecewise-constant input bias: `d` per row (N, m), its change rows and levels
    (K + 1 rows of m), and the bias's random-walk variance per step in the filter that
    placed them."""

    d: Array
    changes: list[int]
    levels: Array
    q_d: float


def _augmented(A: Array, B: Array, C: Array, Qd: Array, q_d: float
               ) -> tuple[Array, Array, Array, Array]:
    n, m = B.shape
    Aa = np.block([[A, B], [np.zeros((m, n)), np.eye(m)]])
    Ba = np.vstack([B, np.zeros((m, m))])
    Ca = np.hstack([C, np.zeros((C.shape[0], m))])
    Qa = scipy.linalg.block_diag(Qd, q_d * np.eye(m))
    return Aa, Ba, Ca, Qa


def _predictor(A: Array, B: Array, C: Array, K: Array, u: Array, y: Array) -> Array:
    """Prior states x^(k|k-1) of x^(k+1) = A x^ + B u + K (y - C x^) over the record,
    started at the steady state that explains the first sample."""
    x0 = steady_state_x0(A, B, C, u[0], y[0])
    n = A.shape[0]
    return dsim(A - K @ C, np.hstack([B, K]), np.eye(n), np.hstack([u, y]), x0)


def _neg_loglik(e: Array, S: Array) -> float:
    Si = np.linalg.inv(S)
    sign, logdet = np.linalg.slogdet(S)
    if sign <= 0:
        return math.inf
    return float(0.5 * (np.einsum("ki,ij,kj->", e, Si, e) + e.shape[0] * logdet))


def _smoothed_bias(A: Array, B: Array, C: Array, Qd: Array, R: Array, u: Array, y: Array
                   ) -> tuple[Array, float]:
    """The input bias over the record from the augmented model's steady-state RTS
    smoother, q_d chosen by the innovations' likelihood (steps 1-2)."""
    n, m = B.shape
    scale = float(np.mean(np.var(u, axis=0))) or 1.0

    def cost(log_q: float) -> float:
        try:
            Aa, Ba, Ca, Qa = _augmented(A, B, C, Qd, scale * 10.0 ** log_q)
            kf = kalman(Aa, Ca, Qa, R)
            value = _neg_loglik(predict(Aa, Ba, Ca, kf.K, u, y), kf.S)
        except _NUMERIC:
            return math.inf
        return value if math.isfinite(value) else math.inf

    best = scipy.optimize.minimize_scalar(cost, bounds=(-14.0, 0.0), method="bounded",
                                          options={"xatol": 0.05})
    log_q = float(best.x)
    if not math.isfinite(float(best.fun)):
        raise IdentifyError("the load's filter has no steady state (an input bias the "
                            "output cannot see: a plant whose output settles at zero)")
    Aa, Ba, Ca, Qa = _augmented(A, B, C, Qd, scale * 10.0 ** log_q)
    kf = kalman(Aa, Ca, Qa, R)
    xp = _predictor(Aa, Ba, Ca, kf.K, u, y)
    e = y - xp @ Ca.T
    Kf = kf.P @ Ca.T @ np.linalg.inv(kf.S)  # the filtered (posterior) gain
    xf = xp + e @ Kf.T
    Pf = kf.P - Kf @ kf.S @ Kf.T
    G = np.asarray(np.linalg.solve(kf.P.T, (Pf @ Aa.T).T).T, dtype=np.float64)  # Pf Aa' P^-1
    # backward: xs(k) = G xs(k+1) + xf(k) - G xp(k+1), from xs(N-1) = xf(N-1)
    w = xf[:-1] - xp[1:] @ G.T
    drive = np.vstack([w[::-1], np.zeros((1, n + m))])
    xs = dsim(G, np.eye(n + m), np.eye(n + m), drive, xf[-1])[::-1]
    return np.asarray(xs[:, n:]), scale * 10.0 ** log_q


def _change_rows(d: Array, T: float, k_max: int) -> list[list[int]]:
    """The nested change rows for K = 0..k_max (step 3)."""
    N = d.shape[0]
    step = max(1, math.ceil(N / DECIMATED_POINTS))
    coarse = d[::step]
    min_size = max(2, round(MIN_SEGMENT_S / (T * step)))
    k_max = min(k_max, coarse.shape[0] // min_size - 1)
    if k_max < 1:
        return [[]]
    algo = ruptures.Binseg(model="l2", min_size=min_size, jump=1).fit(coarse)
    out: list[list[int]] = [[]]
    for k in range(1, k_max + 1):
        try:
            coarse_rows = algo.predict(n_bkps=k)[:-1]
        except ruptures.exceptions.BadSegmentationParameters:
            break
        out.append([_refined(d, r * step, step) for r in coarse_rows])
    return out


def _refined(d: Array, row: int, step: int) -> int:
    """The full-rate row near `row` (within two decimation steps) that splits its
    neighbourhood best (least squares of two levels)."""
    lo, hi = max(1, row - 2 * step), min(d.shape[0] - 1, row + 2 * step)
    span = d[max(0, lo - 4 * step):min(d.shape[0], hi + 4 * step)]
    base = max(0, lo - 4 * step)
    best, best_cost = row, math.inf
    c1 = np.cumsum(span, axis=0)
    c2 = np.cumsum(span * span, axis=0)
    L = span.shape[0]
    for r in range(lo, hi):
        i = r - base
        if not 0 < i < L:
            continue
        left = c2[i - 1] - c1[i - 1] ** 2 / i
        right = (c2[-1] - c2[i - 1]) - (c1[-1] - c1[i - 1]) ** 2 / (L - i)
        cost = float(np.sum(left + right))
        if cost < best_cost:
            best, best_cost = r, cost
    return best


def load_steps(model: ContinuousDescriptor, u: Array, y: Array, T: float) -> LoadSteps:
    """The load over the fit rows (u (N, m), y (N, p) as `fit_rows` pairs them) as a
    piecewise-constant input bias, from `model`'s filter (steps 1-4)."""
    dm = model.discretize(T)
    A, Bm, Qd = dm.at(T)
    m = u.shape[1]
    B = Bm[:, :m]
    C, R = dm.C, dm.R
    N = y.shape[0]
    try:
        d_s, q_d = _smoothed_bias(A, B, C, Qd, R, u, y)
        kf = kalman(A, C, Qd, R)
    except _NUMERIC as exc:
        raise IdentifyError(f"the load's filter failed ({exc})") from None
    nested = _change_rows(d_s, T, k_max=int(N * T / MIN_SEGMENT_S))
    rows = sorted({r for cand in nested for r in cand})
    # the predictor's response to a unit step of each input from each change row (and from
    # row 0: the level before the first change); innovations are linear in the levels
    Ap = A - kf.K @ C
    e0 = predict(A, B, C, kf.K, u, y)
    L = np.linalg.cholesky(np.linalg.inv(kf.S))  # whitening: e' S^-1 e = |L' e|^2
    # with a column per input for a correction of the input's gain: the model's gain error
    # and a constant load trade off where the input has a mean level, which an alternation
    # alone crosses slowly
    keys = [(r, j) for r in [-1, 0, *rows] for j in range(m)]
    X = np.empty((N * y.shape[1], len(keys)))
    for i, (r, j) in enumerate(keys):
        step = np.zeros((N, m))
        if r < 0:
            step[:, j] = u[:, j]
        else:
            step[r:, j] = 1.0
        X[:, i] = (dsim(Ap, B, C, step) @ L).ravel()
    target = (e0 @ L).ravel()
    # every candidate set is a subset of these columns: least squares on the Gram matrix
    gram, moment, energy = X.T @ X, X.T @ target, float(target @ target)
    bic: dict[int, float] = {}
    fits: dict[int, tuple[list[int], Array]] = {}
    for k, cand in enumerate(nested):
        idx = [keys.index((r, j)) for r in [-1, 0, *sorted(cand)] for j in range(m)]
        G, b = gram[np.ix_(idx, idx)], moment[idx]
        theta, *_ = np.linalg.lstsq(G, b, rcond=None)
        rss = energy - 2.0 * float(theta @ b) + float(theta @ G @ theta)
        bic[k] = rss + (m + 1) * k * math.log(N)
        fits[k] = (sorted(cand), np.asarray(theta, dtype=np.float64).reshape(-1, m))
    k_best = min(bic, key=lambda k: bic[k])
    changes, steps = fits[k_best]
    # u (1 + g) + d' = (1 + g) (u + d): d in the input's units of a model of gain (1 + g)
    gain = 1.0 + steps[0]
    levels = np.cumsum(steps[1:], axis=0) / np.where(np.abs(gain) > 1e-6, gain, 1.0)
    d = np.zeros((N, m))
    for i, r in enumerate([0, *changes]):
        d[r:] = levels[i]
    return LoadSteps(d=d, changes=changes, levels=levels, q_d=q_d)


def settled(before: LoadSteps, after: LoadSteps) -> bool:
    """Whether the iteration has settled from `before` to `after` (SETTLED)."""
    if before.changes != after.changes:
        return False
    steps = np.abs(np.diff(after.levels, axis=0))
    scale = float(np.max(steps)) if steps.size else float(np.max(np.abs(after.levels)))
    return bool(np.max(np.abs(after.levels - before.levels)) <= SETTLED * max(scale, 1e-300))
