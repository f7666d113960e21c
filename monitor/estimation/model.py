"""Descriptor plant models, their exact discretisation and the DC-motor factory.

The paper (Liu et al., Int. J. Fuzzy Syst. 22(1), 2020) writes its plant as a discrete
descriptor system

    E x(k+1) = A x(k) + B u(k) + w(k),      y(k) = C x(k) + v(k)          (1-2, 71-72)

and obtains it from the continuous DC-motor model (63-67) by forward Euler with T = 1 s
(69). That discretisation is unstable for T > 0.508 s (E^-1 A has an eigenvalue near 95),
so this module discretises the *continuous* descriptor model exactly, by zero-order hold
at the ECU's sample period (scipy.signal.cont2discrete), and discretises a continuous
process-noise intensity by Van Loan's method.

Two descriptor cases are supported:

* invertible E, as in the paper: premultiply by E^-1 (73);
* singular E of a regular index-1 pencil (the La = 0 motor, whose current equation becomes
  algebraic): the pencil is reduced to standard form by an SVD of E, eliminating the
  algebraic variables; the output then gains a direct feed-through D.

The actuator loss of effectiveness gamma (3-5) enters as u_F = (I - diag(gamma)) u, so the
fault function is f(k) = -B diag(gamma_k) u(k) (8-10).

Unobservable states (the motor angle theta when only the current is measured: a mode at
z = 1, not even detectable) are split off by `StateSpace.observable_part`; the estimator
never carries their covariance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.linalg
import scipy.signal
from numpy.typing import NDArray

from monitor.errors import MonitorError

Array = NDArray[np.float64]

__all__ = [
    "ContinuousDescriptor",
    "DCMotorParameters",
    "DiscreteModel",
    "ModelError",
    "StateSpace",
    "dc_motor",
    "van_loan",
]


class ModelError(MonitorError, ValueError):
    """A model that cannot be estimated: the message says what is wrong with it."""


def _as_matrix(name: str, value: object, rows: int | None = None, cols: int | None = None) -> Array:
    try:
        arr = np.array(value, dtype=np.float64, ndmin=2)
    except (TypeError, ValueError) as exc:
        raise ModelError(f"{name} is not a numeric matrix: {exc}") from exc
    if arr.ndim != 2:
        raise ModelError(f"{name} must be a 2-D matrix, got {arr.ndim} dimensions")
    if not np.all(np.isfinite(arr)):
        raise ModelError(f"{name} contains NaN or infinite entries")
    if rows is not None and arr.shape[0] != rows:
        raise ModelError(f"{name} has {arr.shape[0]} rows, expected {rows}")
    if cols is not None and arr.shape[1] != cols:
        raise ModelError(f"{name} has {arr.shape[1]} columns, expected {cols}")
    return arr


def van_loan(A: Array, Qc: Array, T: float) -> Array:
    """Discrete process-noise covariance of dx = A x dt + dW with E[dW dW'] = Qc dt.

    Van Loan (1978): expm([[-A, Qc], [0, A']] T) = [[., F^-1 Qd], [0, F']], so
    Qd = F (F^-1 Qd) with F = expm(A T). Symmetrised against round-off.
    """
    n = A.shape[0]
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -A
    M[:n, n:] = Qc
    M[n:, n:] = A.T
    G = scipy.linalg.expm(M * T)
    F = G[n:, n:].T
    Qd = F @ G[:n, n:]
    return 0.5 * (Qd + Qd.T)


@dataclass(frozen=True)
class StateSpace:
    """A standard-form model y = C x + D u with x' = A x + B u (continuous) or x(k+1) = ...

    `state_names` label the columns of A. `B` has one column per actuator.
    """

    A: Array
    B: Array
    C: Array
    D: Array
    state_names: tuple[str, ...]

    @property
    def n(self) -> int:
        return int(self.A.shape[0])

    @property
    def m(self) -> int:
        return int(self.B.shape[1])

    @property
    def p(self) -> int:
        return int(self.C.shape[0])

    def observable_part(self) -> tuple[Array, Array]:
        """Return (W, N): orthonormal rows spanning the observable and unobservable parts.

        x_o = W x is observable; x_u = N x is not (the unobservable subspace null(O) is
        A-invariant, so W A = (W A W') W). Where the unobservable subspace is spanned by
        coordinate axes (the motor angle), W and N are row selections, so the estimator
        keeps physical coordinates.
        """
        n = self.n
        obs = np.vstack([self.C @ np.linalg.matrix_power(self.A, k) for k in range(n)])
        # Scale-aware rank decision (the observability matrix mixes units).
        _, s, Vt = np.linalg.svd(obs)
        tol = max(obs.shape) * np.finfo(float).eps * (s[0] if s.size else 1.0) * 1e3
        rank = int(np.sum(s > tol))
        null = Vt[rank:]
        if rank == n:
            return np.eye(n), np.zeros((0, n))
        # Prefer coordinate axes when the unobservable subspace is spanned by them.
        axes = [j for j in range(n) if np.linalg.norm(null[:, j]) > 1 - 1e-9]
        if len(axes) == n - rank:
            keep = [j for j in range(n) if j not in axes]
            return np.eye(n)[keep], np.eye(n)[axes]
        return Vt[:rank], null


@dataclass(frozen=True)
class ContinuousDescriptor:
    """Continuous descriptor model E x' = A x + B u, y = C x (63-67).

    `Qc` is the process-noise intensity per second (the paper's Q read at its T = 1 s),
    `R` the per-sample measurement-noise covariance of y.
    """

    E: Array
    A: Array
    B: Array
    C: Array
    Qc: Array
    R: Array
    state_names: tuple[str, ...]
    input_names: tuple[str, ...] = ("u",)
    output_names: tuple[str, ...] = ("y",)

    def __post_init__(self) -> None:
        A = _as_matrix("A", self.A)
        n = A.shape[0]
        if A.shape != (n, n):
            raise ModelError(f"A must be square, got shape {A.shape}")
        E = _as_matrix("E", self.E, n, n)
        B = _as_matrix("B", self.B, n)
        C = _as_matrix("C", self.C, None, n)
        Qc = _as_matrix("Q", self.Qc, n, n)
        R = _as_matrix("R", self.R, C.shape[0], C.shape[0])
        for name, M in (("Q", Qc), ("R", R)):
            if not np.allclose(M, M.T, atol=1e-12 * max(1.0, float(np.abs(M).max()))):
                raise ModelError(f"{name} must be symmetric")
            if np.min(np.linalg.eigvalsh(0.5 * (M + M.T))) < -1e-12:
                raise ModelError(f"{name} must be positive semi-definite")
        if np.min(np.linalg.eigvalsh(0.5 * (R + R.T))) <= 0:
            raise ModelError("R must be positive definite (every measurement is noisy)")
        if len(self.state_names) != n:
            raise ModelError(f"{len(self.state_names)} state names for {n} states")
        object.__setattr__(self, "E", E)
        object.__setattr__(self, "A", A)
        object.__setattr__(self, "B", B)
        object.__setattr__(self, "C", C)
        object.__setattr__(self, "Qc", Qc)
        object.__setattr__(self, "R", R)
        if B.shape[1] > C.shape[0]:
            raise ModelError(
                f"{B.shape[1]} actuators but only {C.shape[0]} outputs: the losses of "
                "effectiveness of more actuators than outputs cannot be separated"
            )
        self._check_regular()

    def _check_regular(self) -> None:
        # A pencil sE - A is regular iff det(sE - A) is not identically zero; a
        # polynomial of degree <= n vanishing at n+1 distinct points is zero.
        n = self.A.shape[0]
        rng = np.random.default_rng(0)
        pts = rng.uniform(0.5, 2.0, n + 1) * np.exp(1j * rng.uniform(0, np.pi, n + 1))
        scale = max(1.0, float(np.abs(self.A).max()), float(np.abs(self.E).max())) ** n
        if all(abs(np.linalg.det(s * self.E - self.A)) < 1e-10 * scale for s in pts):
            raise ModelError("singular pencil: det(sE - A) vanishes for every s (no solution)")

    def standard_form(self) -> StateSpace:
        """Reduce to standard form x' = A x + B u, y = C x + D u.

        Invertible E: premultiply by E^-1 (73). Singular E: SVD U' E V = diag(S, 0);
        with z = V' x partitioned (z1 dynamic, z2 algebraic), 0 = A21 z1 + A22 z2 + B2 u
        is solved for z2 (index 1 requires A22 invertible) and substituted. The states
        kept are z1, which are the original coordinates whenever E is diagonal.
        """
        E, A, B, C = self.E, self.A, self.B, self.C
        n = A.shape[0]
        m = B.shape[1]
        if np.linalg.matrix_rank(E) == n:
            Ei = np.linalg.inv(E)
            D0 = np.zeros((C.shape[0], m))
            return StateSpace(Ei @ A, Ei @ B, C.copy(), D0, self.state_names)
        if np.allclose(E, np.diag(np.diag(E))):
            # Diagonal E: keep physical coordinates (a permutation, not a rotation).
            d = np.abs(np.diag(E))
            dyn = [j for j in range(n) if d[j] > 1e-12 * d.max()]
            alg = [j for j in range(n) if j not in dyn]
            U = np.eye(n)[:, dyn + alg]
            V = U
            S = np.diag(E)[dyn]
        else:
            U, s, Vt = np.linalg.svd(E)
            r = int(np.sum(s > 1e-12 * s[0]))
            V = Vt.T
            S = s[:r]
            dyn = list(range(r))
            alg = list(range(r, n))
        r = len(dyn)
        At = U.T @ A @ V
        Bt = U.T @ B
        Ct = C @ V
        A11, A12 = At[:r, :r], At[:r, r:]
        A21, A22 = At[r:, :r], At[r:, r:]
        B1, B2 = Bt[:r], Bt[r:]
        if abs(np.linalg.det(A22)) < 1e-12 * max(1.0, float(np.abs(A22).max())) ** A22.shape[0]:
            raise ModelError(
                "singular E with a singular algebraic block: the descriptor system is not "
                "index 1 (impulsive modes); only regular index-1 systems are supported"
            )
        A22i = np.linalg.inv(A22)
        Sinv = np.diag(1.0 / S)
        As = Sinv @ (A11 - A12 @ A22i @ A21)
        Bs = Sinv @ (B1 - A12 @ A22i @ B2)
        C1, C2 = Ct[:, :r], Ct[:, r:]
        Cs = C1 - C2 @ A22i @ A21
        Ds = -C2 @ A22i @ B2
        if np.allclose(V, np.eye(n)[:, dyn + alg]):
            names = tuple(self.state_names[j] for j in dyn)
        else:
            names = tuple(f"z{j + 1}" for j in range(r))
        return StateSpace(As, Bs, Cs, Ds, names)

    def noise_standard_form(self) -> Array:
        """Process-noise intensity on the reduced (dynamic) states."""
        E = self.E
        n = E.shape[0]
        if np.linalg.matrix_rank(E) == n:
            Ei = np.linalg.inv(E)
            return Ei @ self.Qc @ Ei.T
        keep = [j for j in range(n) if abs(E[j, j]) > 1e-12] if np.allclose(
            E, np.diag(np.diag(E))
        ) else None
        if keep is None:
            U, s, _Vt = np.linalg.svd(E)
            r = int(np.sum(s > 1e-12 * s[0]))
            Sinv = np.diag(1.0 / s[:r])
            Qt = (U.T @ self.Qc @ U)[:r, :r]
            return Sinv @ Qt @ Sinv
        Einv = np.diag(1.0 / np.diag(E)[keep])
        return Einv @ self.Qc[np.ix_(keep, keep)] @ Einv

    def discretize(self, T: float) -> DiscreteModel:
        """Exact ZOH discretisation at sample period T, observable part split off."""
        if not (math.isfinite(T) and T > 0):
            raise ModelError(f"sample period must be a positive number of seconds, got {T!r}")
        return DiscreteModel(self, float(T))


@dataclass
class DiscreteModel:
    """The estimator's view of a plant: ZOH matrices for any multiple of the period.

    `at(dt)` returns (A, B, Q) for a step of dt seconds on the observable states x_o,
    cached, so a missed sample (dt = k T) or a jittered period costs one expm once.
    The output map is y = C x_o + D u_F; `Wobs`/`Wunobs` map full states to the
    observable and unobservable parts.
    """

    continuous: ContinuousDescriptor
    T: float
    _cache: dict[int, tuple[Array, Array, Array, Array, Array]] = field(
        default_factory=dict, repr=False
    )

    def __post_init__(self) -> None:
        ss = self.continuous.standard_form()
        W, N = ss.observable_part()
        self._ss = ss
        self.Wobs = W
        self.Wunobs = N
        self.C = ss.C @ W.T
        self.D = ss.D.copy()
        self.R = self.continuous.R.copy()
        self.state_names = ss.state_names
        self.observable_names = tuple(
            ss.state_names[int(np.argmax(np.abs(w)))] if np.isclose(np.abs(w).max(), 1) else f"x{i}"
            for i, w in enumerate(W)
        )
        self._check_fault_observable()

    @property
    def standard(self) -> StateSpace:
        return self._ss

    @property
    def n(self) -> int:
        """Dimension of the observable state the filter carries."""
        return int(self.Wobs.shape[0])

    @property
    def n_full(self) -> int:
        return self._ss.n

    @property
    def m(self) -> int:
        return self._ss.m

    @property
    def p(self) -> int:
        return self._ss.p

    def _check_fault_observable(self) -> None:
        # gamma is a random-walk state (a mode at z = 1): it is observable iff the
        # steady-state gain from each actuator to the outputs has full column rank,
        # i.e. rank [[A - I, B], [C, D]] = n + m on the observable part (PBH at z = 1
        # of the augmented system). For a unit input on each actuator.
        Ao, Bo, _, _, _ = self.full_at(self.T)
        n, m = self.n, self.m
        Wc = np.eye(n)
        M = np.block([[Ao - Wc, Bo], [self.C, self.D]])
        if np.linalg.matrix_rank(M, tol=1e-9 * max(1.0, float(np.abs(M).max()))) < n + m:
            raise ModelError(
                "a loss of effectiveness of some actuator does not show in the outputs "
                "(steady-state gain to y is rank-deficient): the fault is not observable"
            )

    def full_at(self, dt: float) -> tuple[Array, Array, Array, Array, Array]:
        """(A_o, B_o, Q_o, A_full, B_full) for a step of dt seconds, cached per microsecond."""
        key = round(dt * 1e6)
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        if key <= 0:
            raise ModelError(f"step of {dt!r} s: time must move forward")
        ss = self._ss
        Ad, Bd, _, _, _ = scipy.signal.cont2discrete(
            (ss.A, ss.B, ss.C, ss.D), key * 1e-6, method="zoh"
        )
        Qd = van_loan(ss.A, self.continuous.noise_standard_form(), key * 1e-6)
        W = self.Wobs
        entry = (
            np.ascontiguousarray(W @ Ad @ W.T),
            np.ascontiguousarray(W @ Bd),
            np.ascontiguousarray(W @ Qd @ W.T),
            np.ascontiguousarray(Ad),
            np.ascontiguousarray(Bd),
        )
        if len(self._cache) > 4096:  # jittered timestamps must not grow memory forever
            self._cache.clear()
        self._cache[key] = entry
        return entry

    def at(self, dt: float) -> tuple[Array, Array, Array]:
        A, B, Q, _, _ = self.full_at(dt)
        return A, B, Q

    @cached_property
    def dc_gain(self) -> Array:
        """Steady-state gain y/u per actuator (p x m): C (I - A)^-1 B + D."""
        A, B, _ = self.at(self.T)
        return np.asarray(self.C @ np.linalg.solve(np.eye(self.n) - A, B) + self.D)


@dataclass(frozen=True)
class DCMotorParameters:
    """Table 1 of the paper (armature inductance `La` may be 0: singular E)."""

    J: float = 0.01
    b: float = 0.05
    Ke: float = 0.25
    Ki: float = 0.25
    Ra: float = 2.0
    La: float = 2.0


def dc_motor(
    params: DCMotorParameters | None = None,
    q: float = 1.44,
    r: float = 0.25,
) -> ContinuousDescriptor:
    """The DC motor (63-67) as a continuous descriptor model, states [i, omega, theta].

        [La 0 0] [di/dt ]   [-Ra -Ke 0] [i    ]   [1]
        [0  J 0] [dw/dt ] = [ Ki -b  0] [omega] + [0] u,    y = i   (68)
        [0  0 1] [dth/dt]   [ 0   1  0] [theta]   [0]

    This is (65) multiplied by La, so La = 0 gives a singular E with an algebraic current
    equation Ra i + Ke omega = u (index 1). The paper's printed (67) writes Ke/La in the
    first row with the wrong sign and 1 in place of omega in the third; (63)-(65) are used.
    `q` is the process-noise intensity per second on each state (the paper's Q = 1.44 I
    read at its T = 1 s), `r` the current-sensor variance in A^2 (R = 0.25).
    """
    p = params or DCMotorParameters()
    for name in ("J", "b", "Ke", "Ki", "Ra"):
        if getattr(p, name) <= 0:
            raise ModelError(f"motor parameter {name} must be positive, got {getattr(p, name)}")
    if p.La < 0:
        raise ModelError(f"motor parameter La must be >= 0, got {p.La}")
    E = np.diag([p.La, p.J, 1.0])
    A = np.array([[-p.Ra, -p.Ke, 0.0], [p.Ki, -p.b, 0.0], [0.0, 1.0, 0.0]])
    B = np.array([[1.0], [0.0], [0.0]])
    C = np.array([[1.0, 0.0, 0.0]])
    # Q is given on the physical states; in descriptor form the noise enters E x' so
    # scale it by E to keep the paper's per-state intensity where E is invertible.
    Eq = np.diag([p.La if p.La > 0 else 1.0, p.J, 1.0])
    Qc = Eq @ (q * np.eye(3)) @ Eq
    return ContinuousDescriptor(
        E=E,
        A=A,
        B=B,
        C=C,
        Qc=Qc,
        R=np.array([[r]]),
        state_names=("current", "speed", "angle"),
        input_names=("voltage",),
        output_names=("current",),
    )
