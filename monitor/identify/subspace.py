"""Subspace identification (N4SID) of x(k+1) = A x + B u + K e, y = C x + e, on scipy.

Van Overschee & De Moor's N4SID (Automatica 30(1), 1994) in its state-sequence form
(Verhaegen & Verdult, "Filtering and System Identification", 2007, sections 9.6 and 10.6):

1. block Hankel matrices of s past and s future samples of the (RMS-scaled) inputs and
   outputs, stacked [U_f; U_p; Y_p; Y_f] and triangularised by an LQ factorisation
   (a QR of the transpose, by blocks of rows so it stays in cache);
2. the oblique projection of Y_f along U_f onto the past W_p = [U_p; Y_p], O = L32 L22^+ W_p,
   whose singular values show the order (its SVD comes from the small L factor: the
   columns of Q are orthonormal);
3. for an order n, the state sequence X = S_n^-1/2 U_n' O (a bank of Kalman filters), and
   A, B, C by least squares on X(k+1) = A X(k) + B u(k), y(k) = C X(k) (no feed-through
   D: ContinuousDescriptor has none and a zero-order-hold sample has none);
4. B and the initial state re-estimated by linear least squares on the simulated output
   (given A and C, y is linear in B and x0), on the record `model` is given (the raw one,
   means kept): this removes the bias of step 3's B under coloured noise and is what an
   output-error fit would give for the deterministic part;
5. K from the residual covariances (Q, R, S) by the Riccati equation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from monitor.identify.errors import IdentifyError
from monitor.identify.lti import dsim

Array = NDArray[np.float64]

__all__ = ["N4SID", "SubspaceModel", "n4sid", "output_error_b"]

# The largest growth (natural log) of a mode over a record whose responses output_error_b
# fits: e^300 leaves float64 room for the products of its least squares.
MAX_LOG_GROWTH = 300.0


@dataclass(frozen=True)
class SubspaceModel:
    """x(k+1) = A x + B u + K e, y = C x + e, cov(e) = Re; x0 the state at sample 0."""

    A: Array
    B: Array
    C: Array
    K: Array
    Re: Array
    x0: Array

    @property
    def n(self) -> int:
        return int(self.A.shape[0])


def _tsqr_r(H: Array, rows: int = 4096) -> Array:
    """R of a QR factorisation of a tall matrix, by blocks of rows (same R up to signs)."""
    Rs = [np.linalg.qr(H[i:i + rows], mode="r") for i in range(0, H.shape[0], rows)]
    return np.asarray(np.linalg.qr(np.vstack(Rs), mode="r"))


def _hankel(x: Array, s: int, j: int, start: int) -> Array:
    """(j, s*dim) rows [x(k+start), ..., x(k+start+s-1)] for k = 0..j-1."""
    w = sliding_window_view(x[start:start + j + s - 1], s, axis=0)  # (j, dim, s)
    return np.ascontiguousarray(w.transpose(0, 2, 1).reshape(j, -1))


def output_error_b(A: Array, C: Array, u: Array, y: Array) -> tuple[Array, Array, float]:
    """B and x0 minimising sum |y - C (zI - A)^-1 (B u) - C A^k x0|^2 for fixed A, C (linear
    least squares on the responses to each entry of B and of x0). Returns (B, x0, SSE).

    Raises IdentifyError where a mode of A grows beyond what float64 holds over the record
    (a spurious mode of a high order, |z| = 1.02 over 45,000 samples: the responses
    overflow and the least squares cannot be solved)."""
    n, m = A.shape[0], u.shape[1]
    N = y.shape[0]
    radius = float(np.max(np.abs(np.linalg.eigvals(A)))) if n else 0.0
    if radius > 1.0 and N * math.log(radius) > MAX_LOG_GROWTH:
        raise IdentifyError(
            f"the order-{n} subspace model has a mode at |z| = {radius:.4g}, which grows by "
            f"e^{N * math.log(radius):.0f} over the {N} samples: record the plant in open "
            "loop, its input not computed from its output")
    cols = []
    for j in range(m):
        for i in range(n):
            E = np.zeros((n, m))
            E[i, j] = 1.0
            cols.append(dsim(A, E, C, u).ravel())
    for i in range(n):
        e = np.zeros(n)
        e[i] = 1.0
        cols.append(dsim(A, np.zeros((n, 1)), C, np.zeros((N, 1)), e).ravel())
    Phi = np.column_stack(cols)
    theta, *_ = np.linalg.lstsq(Phi, y.ravel(), rcond=None)
    resid = y.ravel() - Phi @ theta
    B = theta[:n * m].reshape(m, n).T
    x0 = np.asarray(theta[n * m:], dtype=float)
    return np.asarray(B, dtype=float), x0, float(resid @ resid)


class N4SID:
    """The decomposition of one record; `model(n)` gives the order-n model (cheap)."""

    def __init__(self, u: Array, y: Array, s: int) -> None:
        N, m = u.shape
        p = y.shape[1]
        self.su = np.sqrt(np.mean(u**2, axis=0)) + 1e-300
        self.sy = np.sqrt(np.mean(y**2, axis=0)) + 1e-300
        us = u / self.su
        ys = y / self.sy
        j = N - 2 * s + 1
        Uf = _hankel(us, s, j, s)
        Up = _hankel(us, s, j, 0)
        Yp = _hankel(ys, s, j, 0)
        Yf = _hankel(ys, s, j, s)
        Wp = np.hstack([Up, Yp])
        L = _tsqr_r(np.hstack([Uf, Wp, Yf])).T
        a, b = s * m, s * (m + p)
        L21, L22 = L[a:a + b, :a], L[a:a + b, a:a + b]
        L32 = L[a + b:, a:a + b]
        self._Ob = L32 @ np.linalg.pinv(L22, rtol=1e-10)
        U, sv, _ = np.linalg.svd(self._Ob @ np.hstack([L21, L22]), full_matrices=False)
        self.singular_values = sv
        self._U = U
        self._Wp = Wp
        self._us, self._ys = us, ys
        self.s, self.j, self.m, self.p = s, j, m, p

    @property
    def max_order(self) -> int:
        return int(min(self.s * self.p, np.sum(self.singular_values > 1e-12 *
                                                self.singular_values[0])))

    def _states(self, n: int) -> tuple[Array, Array, Array, Array]:
        """(X, Z = [X u], [A B]' of step 3, the scaled outputs) of order n."""
        s, j = self.s, self.j
        Sn = self.singular_values[:n]
        M = (self._U[:, :n] / np.sqrt(Sn)).T @ self._Ob  # (n, s(m+p))
        X = self._Wp @ M.T  # (j, n): states at samples s..s+j-1
        us = self._us[s:s + j]
        Z = np.hstack([X[:-1], us[:-1]])
        AB, *_ = np.linalg.lstsq(Z, X[1:], rcond=None)
        return X, Z, AB, self._ys[s:s + j]

    def transition(self, n: int) -> Array:
        """A of the order-n model (step 3 alone)."""
        return np.asarray(self._states(n)[2][:n].T)

    def model(self, n: int, u: Array, y: Array) -> SubspaceModel:
        """The order-n model, its B and x0 (step 4) fitted on the record u (N, m), y (N, p)
        in engineering units (the decomposition's may have had its means removed)."""
        X, Z, AB, ys = self._states(n)
        A = AB[:n].T
        Ct, *_ = np.linalg.lstsq(X, ys, rcond=None)
        C = np.asarray(Ct.T, dtype=float)
        W = X[1:] - Z @ AB
        V = ys[:-1] - X[:-1] @ C.T
        k = W.shape[0]
        Qd, Rd, Sd = W.T @ W / k, V.T @ V / k, W.T @ V / k
        try:
            P = scipy.linalg.solve_discrete_are(A.T, C.T, Qd, Rd, s=Sd)
            Re = C @ P @ C.T + Rd
            K = np.linalg.solve(Re.T, (A @ P @ C.T + Sd).T).T
        except (np.linalg.LinAlgError, ValueError):
            K = np.linalg.lstsq(Rd, Sd.T, rcond=None)[0].T
            Re = Rd
        # Back to engineering units: u = su * us, y = sy * ys.
        Dy = np.diag(self.sy)
        # Step 4: B and x0 of the deterministic part, on the record given.
        B, x0, _ = output_error_b(A, Dy @ C, u, y)
        return SubspaceModel(
            A=A,
            B=B,
            C=Dy @ C,
            K=K / self.sy,
            Re=Dy @ (0.5 * (Re + Re.T)) @ Dy,
            x0=x0,
        )


def n4sid(u: Array, y: Array, s: int) -> N4SID:
    """Decompose a record with s block rows (s > the largest order / p)."""
    return N4SID(u, y, s)


def horizon(u: Array, y: Array, cap_rows: int = 240) -> int:
    """Block rows for N4SID: about one dominant time constant (from a first-order fit with
    10 rows), at least 10, at most what keeps the data matrix to `cap_rows` columns. A
    horizon much shorter than the dominant time constant biases the states under noise."""
    m, p = u.shape[1], y.shape[1]
    cap = max(10, cap_rows // (2 * (m + p)))
    z = float(np.real(np.linalg.eigvals(N4SID(u, y, 10).transition(1))[0]))
    if not 0.0 < z < 1.0:
        return cap
    return int(min(cap, max(10, math.ceil(-1.0 / math.log(z)))))
