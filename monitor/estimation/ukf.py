"""Unscented Kalman filter on a linear (descriptor-reduced) model, eqs (30)-(49).

Sigma points (32) x_{k-1} +- delta * column_i(sqrt(P)), delta = sqrt(n + lambda) (33),
with the paper's scaling lambda = alpha^2 (n + beta) - n (34) -- beta stands where the
usual kappa would, and appears again in (41). Weights:

    W_m^(0) = lambda / (n + lambda)                          (40)
    W_c^(0) = lambda / (n + lambda) + 1 - alpha^2 + beta     (41)
    W_c^(i) = W_m^(i) = 1 / (2 (n + lambda))                  (42-43)

Time update (35)-(37): propagate the sigma points through x -> A x + B u + f, take the
weighted mean and covariance, add Q. Measurement update (44)-(49): new sigma points around
the prior, P_yy = sum W_c dy dy' + R (46), P_xy = sum W_c dx dy' (47, *without* the R the
paper prints there: a misprint), G = P_xy P_yy^-1, x = x^- + G (y - y^-) (48).

Numerical soundness. With the paper's alpha = 1e-4, W_m^(0) is about -1e8 and the textbook
sums lose everything to cancellation (W_0 x_0 + sum W_i x_i subtracts numbers 1e8 times the
state); the covariance then goes indefinite (a known filterpy failure). Here the transform is
evaluated in *deviation form*: each sigma point is carried as its offset s_i = +-delta L_i
from the centre, and for an affine map the offsets propagate as A s_i exactly. The +- pairs
then cancel exactly in IEEE arithmetic, so the weighted mean is the image of the centre and
the W^(0) terms multiply an exact zero; the covariance is sum_i 2 W_i (A s_i)(A s_i)' with
positive weights only. The update uses the Joseph form, which equals (49) for the optimal
gain but cannot lose positive definiteness, and P is symmetrised. A Cholesky pivot that
round-off drives below a floor is clamped and counted (`repairs`), never silently NaN.

The kernels (`chol_lower`, `spd_inverse`, `ukf_predict`, `ukf_update`) are numba-compiled,
allocation-free and take preallocated work arrays: `monitor.estimation.fuzzy_ukf` owns those
arrays and calls the kernels directly. `sigma_weights`, `sigma_points` and
`unscented_transform` are the plain-numpy reference of the same equations.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from monitor.jit import njit

Array = NDArray[np.float64]

__all__ = [
    "SigmaWeights",
    "chol_lower",
    "mat_mul",
    "mat_vec_add",
    "sigma_points",
    "sigma_weights",
    "spd_inverse",
    "ukf_predict",
    "ukf_update",
    "unscented_transform",
]


@dataclass(frozen=True)
class SigmaWeights:
    n: int
    alpha: float
    beta: float
    lam: float  # (34)
    delta: float  # (33)
    wm0: float  # (40)
    wc0: float  # (41)
    wi: float  # (42-43)


def sigma_weights(n: int, alpha: float = 1e-4, beta: float = 2.0) -> SigmaWeights:
    """Weights (33)-(34), (40)-(43) with the paper's parameterisation."""
    if n < 1:
        raise ValueError("state dimension must be at least 1")
    if not (0.0 < alpha <= 1.0):
        raise ValueError(f"alpha must lie in (0, 1] (paper: 0 <= alpha <= 1), got {alpha}")
    if not beta > 0:
        raise ValueError(f"beta must be positive, got {beta}")
    lam = alpha**2 * (n + beta) - n
    npl = alpha**2 * (n + beta)  # n + lambda, computed without cancellation
    return SigmaWeights(
        n=n,
        alpha=alpha,
        beta=beta,
        lam=lam,
        delta=math.sqrt(npl),
        wm0=lam / npl,
        wc0=lam / npl + 1.0 - alpha**2 + beta,
        wi=1.0 / (2.0 * npl),
    )


def sigma_points(mean: Array, cov: Array, w: SigmaWeights) -> Array:
    """The 2n+1 sigma points (32) as rows: mean, mean + delta L_i, mean - delta L_i."""
    L = np.linalg.cholesky(cov)
    n = mean.shape[0]
    pts = np.empty((2 * n + 1, n))
    pts[0] = mean
    pts[1 : n + 1] = mean + w.delta * L.T
    pts[n + 1 :] = mean - w.delta * L.T
    return pts


def unscented_transform(
    mean: Array, cov: Array, fn: Callable[[Array], Array], w: SigmaWeights
) -> tuple[Array, Array, Array]:
    """General unscented transform (32), (36)-(37), (39), (46)-(47) in deviation form.

    Returns (mean_y, cov_y, cross_xy). Offsets are taken from the image of the centre,
    y_i - y_0, so the huge W^(0) of small alpha never multiplies a full-size number; the
    result equals the textbook sums in exact arithmetic. For a black-box map the +- pairs
    still leave a round-off residue of eps |y| that the weights 1/(2 alpha^2 (n + beta))
    amplify (about 1e-8 relative at alpha = 1e-4); the compiled kernels below propagate
    the offsets through the linear part and have no such residue.
    """
    pts = sigma_points(mean, cov, w)
    ys = np.array([np.atleast_1d(fn(p)) for p in pts], dtype=float)
    dy = ys[1:] - ys[0]
    dx = pts[1:] - pts[0]
    mean_y = ys[0] + w.wi * dy.sum(axis=0)
    c = ys[0] - mean_y  # offset of the centre from the mean
    dyc = dy - (mean_y - ys[0])
    cov_y = w.wc0 * np.outer(c, c) + w.wi * dyc.T @ dyc
    cross = w.wi * dx.T @ dyc
    return mean_y, 0.5 * (cov_y + cov_y.T), cross


# --------------------------------------------------------------------------- kernels


@njit
def chol_lower(P: Array, L: Array) -> int:
    """Lower Cholesky factor of P into L; returns the number of clamped pivots.

    Pivot j below floor_j = 1e-12 * max(P_jj, 1e-12 max(diag P), 1e-300) is clamped to
    the floor: a positive semi-definite P that round-off made slightly indefinite still
    yields a usable factor, and the clamp is counted instead of producing NaN. The floor
    is relative to the pivot's own diagonal, where the round-off of its elimination is: a
    state known far better than the others in their units (a slow bias beside a wide
    speed, step 8 of `monitor.estimation.fuzzy_ukf`) is no round-off.
    """
    n = P.shape[0]
    dmax = 0.0
    for i in range(n):
        if P[i, i] > dmax:
            dmax = P[i, i]
    base = max(1e-12 * dmax, 1e-300)
    repairs = 0
    for j in range(n):
        s = P[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        pj = P[j, j]
        floor = 1e-12 * (pj if pj > base else base)  # a NaN diagonal: the base
        if not s > floor:  # also catches NaN
            s = floor
            repairs += 1
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            t = P[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / d
        for i in range(j):
            L[i, j] = 0.0
    return repairs


@njit
def spd_inverse(S: Array, L: Array, Sinv: Array) -> int:
    """Inverse of a small symmetric positive definite matrix through its Cholesky factor."""
    p = S.shape[0]
    rep = chol_lower(S, L)
    for col in range(p):
        # solve L z = e_col, then L' x = z, into Sinv[:, col]
        for i in range(p):
            t = 1.0 if i == col else 0.0
            for k in range(i):
                t -= L[i, k] * Sinv[k, col]
            Sinv[i, col] = t / L[i, i]
        for i in range(p - 1, -1, -1):
            t = Sinv[i, col]
            for k in range(i + 1, p):
                t -= L[k, i] * Sinv[k, col]
            Sinv[i, col] = t / L[i, i]
    return rep


@njit
def mat_vec_add(M: Array, v: Array, sign: float, out: Array) -> None:
    """out <- out + sign M v (sign +-1: exact), each row summed left to right from out: the
    order of the sums the kernels' results depend on, to the bit."""
    for r in range(M.shape[0]):
        acc = out[r]
        for c in range(M.shape[1]):
            acc += sign * M[r, c] * v[c]
        out[r] = acc


@njit
def mat_mul(A: Array, B: Array, out: Array) -> None:
    """out <- A B, each entry summed left to right from 0."""
    for r in range(A.shape[0]):
        for c in range(B.shape[1]):
            acc = 0.0
            for k in range(A.shape[1]):
                acc += A[r, k] * B[k, c]
            out[r, c] = acc


@njit
def ukf_predict(
    x: Array, P: Array, A: Array, b: Array, Q: Array, delta: float, wi: float,
    L: Array, d: Array, x_out: Array, P_out: Array,
) -> int:
    """Time update (32), (35)-(37) for x -> A x + b; writes x_out, P_out; returns repairs.

    `b` = B u + f^ (35). Sigma offsets s_i = delta L_i map to A s_i; the mean (36) is the
    image of the centre (the +- offsets cancel exactly) and (37) sums 2 W_i (A s_i)(A s_i)'.
    """
    n = x.shape[0]
    rep = chol_lower(P, L)
    for r in range(n):
        x_out[r] = b[r]
    mat_vec_add(A, x, 1.0, x_out)
    for r in range(n):
        for c in range(n):
            P_out[r, c] = Q[r, c]
    for i in range(n):
        for r in range(n):
            acc = 0.0
            for c in range(i, n):  # L is lower triangular
                acc += A[r, c] * L[c, i]
            d[r] = delta * acc
        for r in range(n):
            for c in range(r, n):
                P_out[r, c] += 2.0 * wi * d[r] * d[c]
    for r in range(n):
        for c in range(r):
            P_out[r, c] = P_out[c, r]
    return rep


@njit
def ukf_update(
    xp: Array, Pp: Array, C: Array, yoff: Array, R: Array, y: Array, delta: float, wi: float,
    L: Array, Ls: Array, s: Array, dy: Array, Pyy: Array, Pyy_inv: Array, Pxy: Array,
    K: Array, nu: Array, x_out: Array, P_out: Array, IKC: Array, T1: Array,
) -> int:
    """Measurement update (44)-(49) with y = C x + yoff + v; returns repairs.

    Fills nu (innovation), Pyy (46, innovation covariance), K (gain G_k), x_out (48) and
    P_out by the Joseph form (I-KC) P^- (I-KC)' + K R K' (equal to (49) for this K).
    """
    n = xp.shape[0]
    p = C.shape[0]
    rep = chol_lower(Pp, L)
    for r in range(p):
        for c in range(p):
            Pyy[r, c] = R[r, c]
        for c in range(n):
            Pxy[c, r] = 0.0
    for i in range(n):
        for r in range(n):
            s[r] = delta * L[r, i] if r >= i else 0.0
        for r in range(p):
            dy[r] = 0.0
        mat_vec_add(C, s, 1.0, dy)
        for r in range(p):
            for c in range(p):
                Pyy[r, c] += 2.0 * wi * dy[r] * dy[c]
            for c in range(n):
                Pxy[c, r] += 2.0 * wi * s[c] * dy[r]
    rep += spd_inverse(Pyy, Ls, Pyy_inv)
    for r in range(p):
        nu[r] = y[r] - yoff[r]
    mat_vec_add(C, xp, -1.0, nu)
    mat_mul(Pxy, Pyy_inv, K)
    for r in range(n):
        x_out[r] = xp[r]
    mat_vec_add(K, nu, 1.0, x_out)
    # Joseph form
    for r in range(n):
        for c in range(n):
            acc = 1.0 if r == c else 0.0
            for k in range(p):
                acc -= K[r, k] * C[k, c]
            IKC[r, c] = acc
    mat_mul(IKC, Pp, T1)
    for r in range(n):
        for c in range(r, n):
            acc = 0.0
            for k in range(n):
                acc += T1[r, k] * IKC[c, k]
            for a in range(p):
                for bb in range(p):
                    acc += K[r, a] * R[a, bb] * K[c, bb]
            P_out[r, c] = acc
            P_out[c, r] = acc
    return rep
