"""Fuzzy c-means clustering of the fault information, eqs (55)-(62), and the thresholds
F1 < F2 read off its clusters (see the package docstring for the exact equations)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from monitor.diagnosis.thresholds import DiagnosisError, Thresholds

Array = NDArray[np.float64]

__all__ = ["FCMResult", "calibrate", "fcm_memberships", "fuzzy_c_means",
           "thresholds_from_clusters"]




@dataclass(frozen=True)
class FCMResult:
    """Result of `fuzzy_c_means`.

    centres: shape (c,), sorted ascending.
    memberships: shape (c, N); row i belongs to centres[i]; every column sums to 1 (59).
    iterations: alternations of (58) and (57) run for the chosen initialisation.
    objective: J_m = sum_ik u_ik^m d_ik^2 (56)/(61) at the returned centres/memberships,
        in data units squared.
    converged: False if max_iter was reached before the centres settled.
    m: the fuzzifier used.
    """

    centres: Array
    memberships: Array
    iterations: int
    objective: float
    converged: bool
    m: float


def _check_fuzzifier(m: float) -> float:
    m = float(m)
    if not (math.isfinite(m) and m > 1.0):
        raise DiagnosisError(f"fuzzifier m must be a finite number > 1, got {m!r}")
    return m


def _memberships(x: Array, centres: Array, m: float) -> Array:
    """Eq (58) for 1-D data, in log space; a zero distance gives full membership."""
    d = np.abs(x[np.newaxis, :] - centres[:, np.newaxis])  # (c, N)
    zero = d == 0.0
    with np.errstate(divide="ignore"):
        # log of d_ik^(-2/(m-1)), without squaring (no overflow/underflow); +inf at d = 0
        logw = np.log(d) * (-2.0 / (m - 1.0))
    if zero.any():
        zero_cols = zero.any(axis=0)
        logw[:, zero_cols] = 0.0
    else:
        zero_cols = None
    logw -= logw.max(axis=0, keepdims=True)
    w = np.exp(logw)
    u: Array = w / w.sum(axis=0, keepdims=True)
    if zero_cols is not None:
        z = zero[:, zero_cols].astype(np.float64)
        u[:, zero_cols] = z / z.sum(axis=0, keepdims=True)
    return u


def fcm_memberships(points: ArrayLike, centres: ArrayLike, m: float = 2.0) -> Array:
    """Memberships (58) of arbitrary points to given 1-D centres: shape (c, N), columns sum to 1.

    A point equal to a centre has membership 1 to it (0 elsewhere).
    """
    m = _check_fuzzifier(m)
    x = np.atleast_1d(np.asarray(points, dtype=np.float64)).ravel()
    c = np.atleast_1d(np.asarray(centres, dtype=np.float64)).ravel()
    if c.size == 0:
        raise DiagnosisError("need at least one centre")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(c))):
        raise DiagnosisError("points and centres must be finite")
    return _memberships(x, c, m)


def _objective(x: Array, centres: Array, u: Array, m: float) -> float:
    d2 = (x[np.newaxis, :] - centres[:, np.newaxis]) ** 2
    return float(np.sum(u**m * d2))


def _run_fcm(
    x: Array, init: Array, m: float, tol_abs: float, max_iter: int
) -> tuple[Array, Array, int, bool]:
    c = init.copy()
    converged = False
    iterations = 0
    while iterations < max_iter:
        iterations += 1
        u = _memberships(x, c, m)  # (58)
        w = u**m
        den = w.sum(axis=1)
        num = w @ x
        # (57); a cluster with no weight at all (underflow for m near 1) keeps its centre.
        c_new = np.where(den > 0.0, num / np.where(den > 0.0, den, 1.0), c)
        shift = float(np.max(np.abs(c_new - c)))
        c = c_new
        if shift <= tol_abs:
            converged = True
            break
    return c, _memberships(x, c, m), iterations, converged


def _initial_centres(
    x: Array, unique: Array, n_clusters: int, restarts: int, seed: int
) -> list[Array]:
    """Deterministic initialisations, plus `restarts` seeded k-means++-style ones."""
    levels = (np.arange(n_clusters) + 0.5) / n_clusters
    inits: list[Array] = []
    q = np.quantile(x, levels)
    if np.all(np.diff(q) > 0.0):
        inits.append(q)  # quantiles: robust to outliers
    lo, hi = float(unique[0]), float(unique[-1])
    inits.append(lo + levels * (hi - lo))  # evenly over the range: robust to imbalance
    rng = np.random.default_rng(seed)
    for _ in range(restarts):
        chosen = [float(unique[rng.integers(unique.size)])]
        while len(chosen) < n_clusters:
            d2 = np.min((unique[:, np.newaxis] - np.asarray(chosen)[np.newaxis, :]) ** 2, axis=1)
            total = float(d2.sum())
            if total <= 0.0:
                break
            chosen.append(float(unique[rng.choice(unique.size, p=d2 / total)]))
        if len(chosen) == n_clusters:
            inits.append(np.sort(np.asarray(chosen)))
    return inits


def fuzzy_c_means(
    data: ArrayLike,
    n_clusters: int = 3,
    m: float = 2.0,
    tol: float = 1e-9,
    max_iter: int = 500,
    seed: int = 0,
    *,
    restarts: int = 2,
    init_centres: Sequence[float] | None = None,
) -> FCMResult:
    """Fuzzy c-means (56)-(62) on 1-D data; returns sorted centres and memberships.

    Alternates the membership update (58) and the centre update (57) until no centre moves
    by more than ``tol * (max(data) - min(data))`` (a scale-free tolerance) or `max_iter`
    alternations have run. The result is self-consistent: the memberships are (58) at the
    returned centres, so each column sums to 1 (59).

    FCM has local minima. Unless `init_centres` is given, it is run from the data quantiles
    at (i + 1/2)/c, from centres spaced evenly over the data range, and from `restarts`
    k-means++-style initialisations drawn with `numpy.random.default_rng(seed)`; the run
    with the lowest objective J_m wins (first on ties). Results are reproducible for a
    given seed. Internally the data are divided by a power of two so that they lie in
    [-1, 1] (exact; FCM is scale-equivariant), which keeps distances finite for any units.

    Raises DiagnosisError for empty or non-finite data, data that is not 1-D, fewer
    distinct values than clusters, or bad parameters.
    """
    x = np.asarray(data, dtype=np.float64)
    if x.ndim != 1:
        raise DiagnosisError(f"data must be 1-D, got an array of shape {x.shape}")
    if x.size == 0:
        raise DiagnosisError("cannot cluster empty data")
    if not np.all(np.isfinite(x)):
        bad = int(np.count_nonzero(~np.isfinite(x)))
        raise DiagnosisError(f"data contains {bad} non-finite value(s) (NaN or inf)")
    if isinstance(n_clusters, bool) or int(n_clusters) != n_clusters or n_clusters < 2:
        raise DiagnosisError(f"n_clusters must be an integer >= 2, got {n_clusters!r}")
    n_clusters = int(n_clusters)
    m = _check_fuzzifier(m)
    if not (math.isfinite(tol) and tol > 0.0):
        raise DiagnosisError(f"tol must be a finite number > 0, got {tol!r}")
    if int(max_iter) != max_iter or max_iter < 1:
        raise DiagnosisError(f"max_iter must be an integer >= 1, got {max_iter!r}")
    if int(restarts) != restarts or restarts < 0:
        raise DiagnosisError(f"restarts must be an integer >= 0, got {restarts!r}")
    # FCM is scale-equivariant: work on x / 2^k in [-1, 1] (exact, a power of two) so that
    # squared distances can neither overflow nor underflow, whatever the data's units.
    scale = math.ldexp(1.0, math.frexp(float(np.max(np.abs(x))))[1])
    z = x / scale
    unique = np.unique(z)
    if unique.size < n_clusters:
        raise DiagnosisError(
            f"data has {unique.size} distinct value(s), fewer than n_clusters={n_clusters}"
        )
    tol_abs = tol * float(unique[-1] - unique[0])

    if init_centres is not None:
        init = np.sort(np.asarray(init_centres, dtype=np.float64).ravel())
        if init.size != n_clusters or not np.all(np.isfinite(init)):
            raise DiagnosisError(f"init_centres must be {n_clusters} finite numbers")
        init = init / scale
        if np.any(np.diff(init) <= 0.0):
            raise DiagnosisError("init_centres must be distinct")
        inits = [init]
    else:
        inits = _initial_centres(z, unique, n_clusters, int(restarts), seed)

    best: tuple[float, Array, Array, int, bool] | None = None
    for init in inits:
        c, u, iterations, converged = _run_fcm(z, init, m, tol_abs, int(max_iter))
        objective = _objective(z, c, u, m)
        if best is None or objective < best[0]:
            best = (objective, c, u, iterations, converged)
    assert best is not None
    objective, c, u, iterations, converged = best
    order = np.argsort(c, kind="stable")
    return FCMResult(
        centres=c[order] * scale,
        memberships=u[order],
        iterations=iterations,
        objective=objective * scale * scale,
        converged=converged,
        m=m,
    )




def thresholds_from_clusters(result: FCMResult, quantity: str = "gamma") -> Thresholds:
    """F1, F2 = midpoints of adjacent sorted centres (the equal-membership points of (58)).

    u_i / u_j = (d_j / d_i)^(2/(m-1)), so u_i = u_j iff d_i = d_j iff x = (c_i + c_j)/2,
    for every m > 1 and regardless of the third centre. Needs exactly three clusters.
    """
    c = np.sort(np.asarray(result.centres, dtype=np.float64))
    if c.size != 3:
        raise DiagnosisError(f"need 3 clusters (fault-free, fault, outage), got {c.size}")
    return Thresholds(
        f1=float(0.5 * (c[0] + c[1])),
        f2=float(0.5 * (c[1] + c[2])),
        quantity=quantity,
        centres=tuple(float(v) for v in c),
    )


def calibrate(
    gamma_hat_samples: ArrayLike,
    *,
    m: float = 2.0,
    min_separation: float = 0.1,
    min_fraction: float = 0.01,
    quantity: str = "gamma",
    seed: int = 0,
) -> Thresholds:
    """Thresholds (76) from a run's gamma^ samples by three-cluster fuzzy c-means (55)-(62).

    NaN samples (no data) are dropped; any other non-finite value is an error. The run must
    visit all three regimes: adjacent centres at least `min_separation` apart (in units of
    the quantity; gamma is in [0, 1]) and each cluster holding at least `min_fraction` of
    the samples by largest membership. Otherwise DiagnosisError says the run must contain
    fault-free, fault and outage periods.
    """
    x = np.asarray(gamma_hat_samples, dtype=np.float64).ravel()
    x = x[~np.isnan(x)]
    if not (math.isfinite(min_separation) and min_separation > 0.0):
        raise DiagnosisError(f"min_separation must be > 0, got {min_separation!r}")
    if not (math.isfinite(min_fraction) and 0.0 <= min_fraction < 1.0 / 3.0):
        raise DiagnosisError(f"min_fraction must be in [0, 1/3), got {min_fraction!r}")
    need = "the calibration run must contain fault-free, fault and outage periods"
    if x.size > 0 and np.all(np.isfinite(x)) and np.unique(x).size < 3:
        raise DiagnosisError(f"{need}: only {np.unique(x).size} distinct {quantity} value(s)")
    result = fuzzy_c_means(x, n_clusters=3, m=m, seed=seed)
    c = result.centres
    gaps = np.diff(c)
    if np.any(gaps < min_separation):
        shown = ", ".join(f"{v:.4g}" for v in c)
        raise DiagnosisError(
            f"{need}: cluster centres {shown} are closer than min_separation={min_separation:g}"
        )
    counts = np.bincount(np.argmax(result.memberships, axis=0), minlength=3)
    fractions = counts / x.size
    if np.any(fractions < min_fraction):
        shown = ", ".join(f"{f:.2%}" for f in fractions)
        raise DiagnosisError(
            f"{need}: cluster shares {shown} include one below min_fraction={min_fraction:g}"
        )
    return thresholds_from_clusters(result, quantity=quantity)


