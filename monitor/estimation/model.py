"""Linear actuator models, their exact discretisation and the DC-motor factory.

The paper (Liu et al., Int. J. Fuzzy Syst. 22(1), 2020) writes its plant as a discrete
descriptor system

    E x(k+1) = A x(k) + B u(k) + w(k),      y(k) = C x(k) + v(k)          (1-2, 71-72)

and obtains it from the continuous DC-motor model (63-67) by forward Euler with T = 1 s
(69). That discretisation is unstable for T > 0.508 s (E^-1 A has an eigenvalue near 95),
so this module discretises the *continuous* descriptor model exactly, by zero-order hold
at the ECU's sample period (`zoh`, scipy.linalg's matrix exponential as
scipy.signal.cont2discrete takes it), and discretises a continuous process-noise intensity
by Van Loan's method.

A model is any linear plant with n states, m actuators and p outputs:

* `ContinuousDescriptor`: E x' = A x + B u_F + w, y = C x + D u_F + v (the paper's plant
  (1-2) in continuous time, with a feed-through D the paper does not have);
* `DiscreteDescriptor`: the same at its own sample period T, as the paper writes it
  (1-2, 6-7). It is turned into the equivalent continuous model by the inverse zero-order
  hold (`inverse_zoh`, `inverse_van_loan`), so that the estimator can step by any dt;
* `dc_motor`: the paper's DC motor (63-68) from its physical parameters (Table 1);
* `model_from_matrices`: either domain from plain nested lists, as a rig file holds them.

Two descriptor cases are supported (continuous or discrete alike):

* invertible E, as in the paper: premultiply by E^-1 (73);
* singular E of a regular index-1 pencil (the La = 0 motor, whose current equation becomes
  algebraic): the pencil is reduced to standard form by an SVD of E, eliminating the
  algebraic variables; the output then gains a direct feed-through, added to the user's D.

The actuator loss of effectiveness gamma (3-5) enters as u_F = (I - diag(gamma)) u, so the
fault function is f(k) = -B diag(gamma_k) u(k) (8-10). `fault_inputs` says which actuators
can lose effectiveness; the others are known inputs that enter B and D with gamma = 0.

Unobservable states (the motor angle theta when only the current is measured: a mode at
z = 1, not even detectable) are split off by `StateSpace.observable_part`; the estimator
never carries their covariance.

Any value a rig file can hold is either refused in one `ModelError` line or gives a model
the estimator runs (issue 17). The checks cannot overflow: matrices are scaled to a largest
entry of 1 before ranks and definiteness are judged, the pencil's regularity and the
observability are SVD ranks (a staircase, not powers of A), Van Loan's integral is doubled
from a short step; every numpy or scipy failure while building a model becomes a
ModelError (`_numerics`), whose `key` is "rate" where the sample period is to blame. A
`DiscreteModel` is built only when what `FuzzyUKF` computes from it before its first step
succeeds (`DiscreteModel._check_estimable`): its memory, a finite zero-order hold over one
period, a positive definite initial covariance and innovation covariance.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cached_property
from typing import Literal, cast

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from monitor.errors import MonitorError, one_line
from monitor.estimation.friction import FRICTION_SPEEDS, Friction
from monitor.estimation.layout import RING

Array = NDArray[np.float64]
FaultInputs = Sequence[int | str] | None

__all__ = [
    "BIAS_MODES",
    "BIAS_WINDOW_S",
    "BiasPlan",
    "ContinuousDescriptor",
    "DCMotorParameters",
    "DiscreteDescriptor",
    "DiscreteModel",
    "ModelError",
    "StateSpace",
    "dc_motor",
    "estimator_bytes",
    "inverse_van_loan",
    "inverse_zoh",
    "model_from_matrices",
    "van_loan",
]

_log = logging.getLogger(__name__)


class ModelError(MonitorError, ValueError):
    """A model that cannot be estimated: the message says what is wrong with it.

    `key` names the one setting to blame when it is not a matrix the message names
    ("rate": the model is fine, its sample period is not), so that a rig file's error can
    point at that key; None otherwise.
    """

    def __init__(self, message: str, key: str | None = None) -> None:
        super().__init__(message)
        self.key = key


# The floating-point failures numpy and scipy raise on a model at the edge of the range
# (an overflowing expm, a Riccati solve or an SVD that does not converge), with `_numerics`
# turning overflow, invalid operations and division by zero into FloatingPointError.
_NUMERIC_FAILURES = (np.linalg.LinAlgError, FloatingPointError, OverflowError,
                     ZeroDivisionError, ValueError)


@contextmanager
def _numerics(what: str, key: str | None = None, advice: str = "") -> Iterator[None]:
    """Run a model computation with floating-point trouble raised, and report any failure
    as one ModelError line: `what` was being computed, what numpy or scipy said, `advice`.

    Overflow, invalid operations (inf - inf, 0 * inf) and division by zero raise instead of
    warning, so an overflow inside scipy's expm ends here rather than as NaN that some later
    Cholesky chokes on. A ModelError from inside passes unchanged.
    """
    try:
        with np.errstate(over="raise", invalid="raise", divide="raise"):
            yield
    except ModelError:
        raise
    except _NUMERIC_FAILURES as exc:
        tail = f"; {advice}" if advice else ""
        raise ModelError(f"{what} fails in floating point ({one_line(exc, 80)}){tail}",
                         key) from None


# The estimator forms covariances, the squares of the states (E^-1 Q E^-T, C P C'), so a
# model quantity beyond the square root of the float range (1.8e308) overflows there.
MAX_ENTRY = 1e150


def _empty() -> Array:
    return np.zeros((0, 0))


def _is_empty(value: object) -> bool:
    return value is None or (isinstance(value, np.ndarray) and value.size == 0) or (
        isinstance(value, (list, tuple)) and len(value) == 0)


def _as_matrix(name: str, value: object, rows: int | None = None, cols: int | None = None,
               rows_of: str = "", cols_of: str = "") -> Array:
    """`value` as a finite float matrix; a wrong size names the matrix and what it must match
    (`rows_of`/`cols_of`, e.g. "A has 3 states")."""
    try:
        arr = np.array(value, dtype=np.float64, ndmin=2)
    except (TypeError, ValueError) as exc:
        raise ModelError(f"{name} is not a numeric matrix: {exc}") from exc
    if arr.ndim != 2:
        raise ModelError(f"{name} must be a 2-D matrix, got {arr.ndim} dimensions")
    if not np.all(np.isfinite(arr)):
        raise ModelError(f"{name} contains NaN or infinite entries")
    top = float(np.abs(arr).max(initial=0.0))
    if top > MAX_ENTRY:
        raise ModelError(f"{name} has an entry of {top:.3g}: the estimator squares the "
                         f"model's quantities (covariances), so entries beyond {MAX_ENTRY:g} "
                         "leave the floating-point range; rescale the units")
    if rows is not None and arr.shape[0] != rows:
        raise ModelError(f"{name} has {arr.shape[0]} rows, {rows_of or f'expected {rows}'}")
    if cols is not None and arr.shape[1] != cols:
        raise ModelError(f"{name} has {arr.shape[1]} columns, {cols_of or f'expected {cols}'}")
    return arr


def _names(kind: str, given: Sequence[str], count: int, prefix: str, what: str
           ) -> tuple[str, ...]:
    """Validated names, or `prefix` (count 1) / prefix1..prefixN when none are given."""
    if len(given) == 0:
        return (prefix,) if count == 1 and prefix != "x" else tuple(
            f"{prefix}{i + 1}" for i in range(count))
    names = tuple(str(s) for s in given)
    if len(names) != count:
        raise ModelError(f"{len(names)} {kind} names for {count} {what}")
    dup = next((s for i, s in enumerate(names) if s in names[:i]), None)
    if dup is not None:
        raise ModelError(f"{kind} name {dup!r} appears twice")
    return names


def _fault_indices(fault_inputs: FaultInputs, m: int, input_names: tuple[str, ...]
                   ) -> tuple[int, ...]:
    """The actuators with a loss of effectiveness (3-5) as sorted indices; None: all."""
    if fault_inputs is None:
        return tuple(range(m))
    if isinstance(fault_inputs, str):
        fault_inputs = [fault_inputs]
    idx: list[int] = []
    for f in fault_inputs:
        if isinstance(f, str):
            if f not in input_names:
                raise ModelError(f"fault_inputs names {f!r}, which is not an input "
                                 f"({', '.join(input_names)})")
            i = input_names.index(f)
        elif isinstance(f, (int, np.integer)) and not isinstance(f, (bool, np.bool_)):
            i = int(f)
            if not 0 <= i < m:
                raise ModelError(f"fault_inputs names actuator {i}, B has {m} actuators "
                                 f"(0 to {m - 1})")
        else:
            raise ModelError(f"fault_inputs entries must be actuator indices or input names, "
                             f"got {f!r}")
        if i in idx:
            raise ModelError(f"fault_inputs names actuator {i} twice")
        idx.append(i)
    if not idx:
        raise ModelError("fault_inputs is empty: name at least one actuator whose loss of "
                         "effectiveness is to be estimated")
    return tuple(sorted(idx))


def _unit_scaled(M: Array) -> Array:
    """M divided by its largest entry in magnitude (M itself when zero): the same
    symmetry, definiteness and rank, with every later product inside the float range."""
    top = float(np.abs(M).max(initial=0.0))
    return M / top if top > 0.0 else M


def _check_noise(name: str, M: Array, definite: bool) -> None:
    # Judged on the matrix scaled to a largest entry of 1: a covariance of 1e308 (or
    # 1e-308) is as symmetric and definite as its scaled copy, and M + M.T overflows.
    S = _unit_scaled(M)
    top = float(np.abs(M).max(initial=0.0))
    # 1e-12 of max(1, largest entry), in the units of M (a tiny matrix keeps the absolute
    # tolerance it always had), expressed on the scaled copy
    tol = 1e-12 * max(1.0, 1.0 / max(top, 1e-300))
    if not np.allclose(S, S.T, atol=tol):
        raise ModelError(f"{name} must be symmetric")
    sym = 0.5 * (S + S.T)
    low = float(np.min(np.linalg.eigvalsh(sym)))
    if definite:
        # The estimator factors R (Cholesky) and inverts the innovation covariance: a
        # smallest eigenvalue lost in the round-off of the largest is not definite.
        if low <= 0 or low <= S.shape[0] * np.finfo(float).eps * float(
                np.abs(sym).max(initial=0.0)):
            raise ModelError(f"{name} must be positive definite (every measurement is noisy)")
        try:
            np.linalg.cholesky(sym)
        except np.linalg.LinAlgError:
            raise ModelError(f"{name} must be positive definite (every measurement is "
                             "noisy)") from None
        if low * top < 1.0 / MAX_ENTRY:
            raise ModelError(f"{name} has an eigenvalue of {low * top:.3g}: the estimator "
                             f"inverts it (the innovation covariance), which overflows below "
                             f"{1.0 / MAX_ENTRY:g}; rescale the units")
    if low < -tol:
        raise ModelError(f"{name} must be positive semi-definite")


def _equilibrated(M: Array, sweeps: int = 4) -> Array:
    """M with its rows and then its columns scaled to a largest entry near 1, a few sweeps
    (by powers of two, exact): the same rank, judged without the units of the states."""
    for axis in (1, 0) * sweeps:
        top = np.abs(M).max(axis=axis, keepdims=True)
        M = M / np.exp2(np.round(np.log2(np.where(top > 0, top, 1.0))))
    return M


def _check_regular(E: Array, A: Array) -> None:
    # A pencil sE - A is regular iff det(sE - A) is not identically zero, i.e. iff sE - A
    # has full rank at some s; a regular pencil is singular at its (at most n) eigenvalues
    # only, so full rank at any of three random real points settles it (real: a complex
    # SVD is a hundred times slower here). E and A are scaled to a largest entry of 1
    # first (regularity is unchanged by scaling either), sE - A is equilibrated (rows and
    # columns scaled alike: the rank is unchanged, but a state in other units, J = 1e9
    # beside La = 1e-3, no longer looks like a zero column) and the rank is numpy's SVD
    # rank: no determinant, whose value over- or underflows with n.
    n = A.shape[0]
    Es, As = _unit_scaled(E), _unit_scaled(A)
    rng = np.random.default_rng(0)
    pts = rng.uniform(0.5, 2.0, 3) * rng.choice([-1.0, 1.0], 3)
    if all(np.linalg.matrix_rank(_equilibrated(s * Es - As)) < n for s in pts):
        raise ModelError("singular pencil: det(sE - A) vanishes for every s (no solution)")


def _validate(model: _Descriptor, Q: object) -> dict[str, object]:
    """Shapes, finiteness, noise covariances, names and fault actuators of `model`'s
    (E, A, B, C, D) with the noise covariance `Q`: its fields normalised, by name (``Q``
    for the noise covariance).

    Every message is one line naming the matrix and what it disagrees with.
    """
    E, A, B, C, D, R = model.E, model.A, model.B, model.C, model.D, model.R
    Aa = _as_matrix("A", A)
    n = Aa.shape[0]
    if Aa.shape != (n, n) or n == 0:
        raise ModelError(f"A must be square, got shape {Aa.shape}")
    states = f"A has {n} states"
    Ea = np.eye(n) if _is_empty(E) else _as_matrix("E", E, n, n, states, states)
    Ba = _as_matrix("B", B, n, None, states)
    m = Ba.shape[1]
    if m == 0:
        raise ModelError("B has no columns: the model needs at least one actuator")
    Ca = _as_matrix("C", C, None, n, "", states)
    p = Ca.shape[0]
    if p == 0:
        raise ModelError("C has no rows: the model needs at least one output")
    outputs = f"C has {p} outputs"
    actuators = f"B has {m} actuators"
    Da = np.zeros((p, m)) if _is_empty(D) else _as_matrix("D", D, p, m, outputs, actuators)
    Qa = _as_matrix("Q", Q, n, n, states, states)
    Ra = _as_matrix("R", R, p, p, outputs, outputs)
    _check_noise("Q", Qa, definite=False)
    _check_noise("R", Ra, definite=True)
    ins = _names("input", model.input_names, m, "u", "actuators")
    faults = _fault_indices(model.fault_inputs, m, ins)
    if len(faults) > p:
        raise ModelError(
            f"{len(faults)} actuators but only {p} outputs: the losses of effectiveness of "
            "more actuators than outputs cannot be separated (fault_inputs selects the "
            "actuators that can lose effectiveness)"
        )
    sts = _names("state", model.state_names, n, "x", "states")
    outs = _names("output", model.output_names, p, "y", "outputs")
    _check_regular(Ea, Aa)
    return {"E": Ea, "A": Aa, "B": Ba, "C": Ca, "D": Da, "Q": Qa, "R": Ra, "state_names": sts,
            "input_names": ins, "output_names": outs, "fault_inputs": faults}


def _checked_friction(model: ContinuousDescriptor, fr: Friction) -> Friction:
    """`fr` normalised against the validated `model`, or one ModelError line (key
    "friction") saying what is wrong with it (`monitor.estimation.friction`, (1))."""
    n, p = model.A.shape[0], model.C.shape[0]
    if fr.speed not in FRICTION_SPEEDS:
        raise ModelError(f"speed must be one of {', '.join(FRICTION_SPEEDS)}, got "
                         f"{fr.speed!r}", "friction")
    if isinstance(fr.output, bool) or not isinstance(fr.output, int) \
            or not 0 <= fr.output < p:
        raise ModelError(f"output must be an output index from 0 to {p - 1}, got "
                         f"{fr.output!r}", "friction")
    width = fr.width
    if isinstance(width, bool) or not isinstance(width, (int, float)) \
            or not (math.isfinite(width) and 0.0 < width < MAX_ENTRY):
        raise ModelError(f"width must be a positive number, got {width!r}", "friction")
    try:
        b = _as_matrix("B", fr.B, 1, n, "a list of one number per state",
                       f"A has {n} states")[0]
    except ModelError as exc:
        raise ModelError(str(exc), "friction") from None
    if np.linalg.matrix_rank(model.E) < n:
        raise ModelError("needs an invertible E (a singular E's algebraic states have no "
                         "friction)", "friction")
    return Friction(B=b.copy(), speed=fr.speed, output=int(fr.output), width=float(width))


def van_loan(A: Array, Qc: Array, T: float) -> Array:
    """Discrete process-noise covariance of dx = A x dt + dW with E[dW dW'] = Qc dt.

    Van Loan (1978): expm([[-A, Qc], [0, A']] h) = [[., F^-1 Qd], [0, F']], so
    Qd = F (F^-1 Qd) with F = expm(A h). That block holds expm(-A h), which grows like
    e^(|A| h): over a period long against the model's fastest mode it overflows (a 1 kHz
    pole over 1 s is e^1000) and loses every digit long before. So it is taken over
    h = T / 2^k with |A| h <= 1/2, and doubled k times by the semigroup property
    Qd(2 h) = Qd(h) + F(h) Qd(h) F(h)', F(2 h) = F(h)^2, a sum of covariances that cannot
    cancel. Symmetrised against round-off.
    """
    n = A.shape[0]
    # |A T| in the infinity norm, summed on A scaled to a largest entry of 1 and scaled back
    # in Python floats: 1e308 entries give inf (then at most 1100 halvings: below that h is
    # no longer a float) instead of raising.
    size = float(np.abs(_unit_scaled(A)).sum(axis=1).max(initial=0.0)) * float(
        np.abs(A).max(initial=0.0)) * T
    k = 0 if not size > 0.5 else min(1100, math.ceil(math.log2(min(size, 1e308) / 0.5)))
    h = math.ldexp(T, -k)
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -A
    M[:n, n:] = Qc
    M[n:, n:] = A.T
    G = scipy.linalg.expm(M * h)
    F = G[n:, n:].T
    Qd = F @ G[:n, n:]
    Qd = 0.5 * (Qd + Qd.T)
    for _ in range(k):
        Qd = Qd + F @ Qd @ F.T
        Qd = 0.5 * (Qd + Qd.T)
        F = F @ F
    return Qd


def zoh(A: Array, B: Array, T: float) -> tuple[Array, Array]:
    """(Ad, Bd): the zero-order hold of x' = A x + B u at period T, from the one exponential
    expm([[A, B], [0, 0]] T) = [[Ad, Bd], [0, I]].

    The same exponential of the same matrix as scipy.signal.cont2discrete(method="zoh"), so
    the same result bit for bit (tests hold the two to each other), taken from scipy.linalg
    because importing scipy.signal costs the daemon a second of its start (three in the
    User-Mode Linux guest): it parses the docstrings of its whole API when imported.
    """
    n, m = B.shape
    M = np.zeros((n + m, n + m))
    M[:n, :n] = A
    M[:n, n:] = B
    G = scipy.linalg.expm(M * T)
    return G[:n, :n], G[:n, n:]


def inverse_zoh(Ad: Array, Bd: Array, T: float) -> tuple[Array, Array]:
    """The continuous (A, B) whose zero-order hold at period T is (Ad, Bd).

    The ZOH of x' = A x + B u is expm([[A, B], [0, 0]] T) = [[Ad, Bd], [0, I]], so
    [[A, B], [0, 0]] = logm([[Ad, Bd], [0, I]]) / T. The principal logarithm is taken: the
    continuous model whose modes all lie below the Nyquist frequency (|Im s| < pi / T),
    the only one a model sampled at T can describe. It is real iff Ad has no eigenvalue on
    the closed negative real axis; a zero eigenvalue (a delay, a dead-beat loop) or a
    negative one (a mode sampled at or above its Nyquist rate) has no continuous
    equivalent, and is refused.
    """
    n, m = Bd.shape
    scale = max(1.0, float(np.abs(Ad).max()))
    for lam in np.linalg.eigvals(Ad):
        if abs(lam) <= 1e-12 * scale:
            raise ModelError(
                "A is singular (eigenvalue 0, a delay or dead-beat mode): no continuous model "
                "has this zero-order hold; give the continuous model")
        if lam.real < 0 and abs(lam.imag) <= 1e-9 * abs(lam):
            raise ModelError(
                f"A has the eigenvalue {lam.real:.6g} on the negative real axis: no real "
                "continuous model has this zero-order hold (a mode at or above the Nyquist "
                "rate); sample faster or give the continuous model")
    M = np.zeros((n + m, n + m))
    M[:n, :n] = Ad
    M[:n, n:] = Bd
    M[n:, n:] = np.eye(m)
    L = np.asarray(scipy.linalg.logm(M))
    norm = max(1.0, float(np.abs(L).max()))
    if np.iscomplexobj(L):
        if float(np.abs(L.imag).max()) > 1e-9 * norm:
            raise ModelError("A has no real logarithm: no continuous model has this zero-order "
                             "hold; sample faster or give the continuous model")
        L = L.real
    L = np.asarray(L, dtype=np.float64)
    back = scipy.linalg.expm(L)
    if float(np.abs(back - M).max()) > 1e-8 * max(1.0, float(np.abs(M).max())) or float(
            np.abs(L[n:]).max(initial=0.0)) > 1e-8 * norm:
        raise ModelError("the inverse zero-order hold of A, B is ill-conditioned (nearly "
                         "defective A): give the continuous model")
    return np.ascontiguousarray(L[:n, :n] / T), np.ascontiguousarray(L[:n, n:] / T)


KRON_STATES = 16  # up to this many states the exact Kronecker inverse of Van Loan is used


def inverse_van_loan(A: Array, Qd: Array, T: float) -> Array:
    """The noise intensity Qc per second whose Van Loan covariance over T is Qd.

    Qd = int_0^T expm(A s) Qc expm(A' s) ds is linear in Qc: with row-major vec,
    vec(Qd) = Phi vec(Qc), Phi = int_0^T expm(K s) ds, K = A (+) A the Kronecker sum, read
    off expm([[K, I], [0, 0]] T). Phi is invertible for the principal-logarithm A of
    `inverse_zoh` (its eigenvalues (e^{mu T} - 1)/mu are not 0 when |Im mu| < 2 pi / T),
    including integrators, where the Stein form Qc - Ad Qc Ad' = -(A Qd + Qd A') is
    singular. The cost is O(n^6): instantaneous for the few states of an actuator model;
    above KRON_STATES states the Stein equation is solved instead (O(n^3), not with an
    integrator).

    A Qd that no white noise produces over one period (the exact Qc is indefinite, e.g. a
    diagonal Qd on states the dynamics couple within T) is replaced by the nearest positive
    semi-definite intensity (negative eigenvalues clipped), with a warning; `van_loan` at T
    then reproduces Qd only approximately.
    """
    n = A.shape[0]
    if n <= KRON_STATES:
        eye = np.eye(n)
        K = np.kron(A, eye) + np.kron(eye, A)
        N = n * n
        G = np.zeros((2 * N, 2 * N))
        G[:N, :N] = K
        G[:N, N:] = np.eye(N)
        Phi = scipy.linalg.expm(G * T)[:N, N:]
        Qc = np.linalg.solve(Phi, Qd.reshape(N)).reshape(n, n)
    else:
        # O(n^6) is minutes and gigabytes here (n = 200: a 80000-square expm). Qd solves
        # A Qd + Qd A' + Qc = F Qc F' (the Lyapunov differential equation integrated over
        # T, F = expm(A T)), a Stein equation in Qc that scipy solves in O(n^3) -- unless
        # two eigenvalues of F multiply to 1 (an integrator), where it is singular.
        F = scipy.linalg.expm(A * T)
        lam = np.linalg.eigvals(F)
        if float(np.min(np.abs(1.0 - np.multiply.outer(lam, lam)))) < 1e-6:
            raise ModelError(
                f"Q: a discrete model of {n} states with an integrator (an eigenvalue of A "
                f"at 1) has no continuous noise intensity computable in reasonable time "
                f"(more than {KRON_STATES} states): give the continuous model")
        Qc = scipy.linalg.solve_discrete_lyapunov(F, -(A @ Qd + Qd @ A.T))
    Qc = 0.5 * (Qc + Qc.T)
    w, V = np.linalg.eigh(Qc)
    if w.size and w.min() < -1e-9 * max(float(np.abs(w).max()), 1e-300):
        _log.warning("Q is not the covariance of any white noise over one period of %g s "
                     "(its continuous intensity would be indefinite): the nearest positive "
                     "semi-definite intensity is used", T)
        Qc = (V * np.clip(w, 0.0, None)) @ V.T
        Qc = 0.5 * (Qc + Qc.T)
    return Qc


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
        # The observable subspace is the Krylov space of A' on the rows of C, built one
        # orthonormal block at a time (the observability staircase): the powers C A^k of
        # the textbook test overflow with n (35^200) and their rank decision drowns the
        # slow modes in the fast ones. A and C are scaled to a largest entry of 1 (the
        # subspace does not change); a new direction counts when it stands out of the
        # round-off of one such product.
        As = _unit_scaled(self.A)
        tol = max(n, self.p) * np.finfo(float).eps * 1e3
        basis = np.zeros((n, 0))
        block = _unit_scaled(self.C).T
        while block.size and basis.shape[1] < n:
            for _ in range(2):  # twice: one Gram-Schmidt pass loses orthogonality
                block = block - basis @ (basis.T @ block)
            U, sv, _ = np.linalg.svd(block, full_matrices=False)
            new = U[:, sv > tol]
            basis = np.hstack([basis, new])
            block = As.T @ new
        rank = basis.shape[1]
        if rank == n:
            return np.eye(n), np.zeros((0, n))
        _, _, Vt = np.linalg.svd(basis.T)
        null = Vt[rank:]
        # Prefer coordinate axes when the unobservable subspace is spanned by them.
        axes = [j for j in range(n) if np.linalg.norm(null[:, j]) > 1 - 1e-9]
        if len(axes) == n - rank:
            keep = [j for j in range(n) if j not in axes]
            return np.eye(n)[keep], np.eye(n)[axes]
        return np.ascontiguousarray(basis.T), null


def _reduce(E: Array, A: Array, B: Array, C: Array, D: Array, names: tuple[str, ...]
            ) -> StateSpace:
    """Standard form of E x' = A x + B u, y = C x + D u (or its discrete twin, E x(k+1)).

    Invertible E: premultiply by E^-1 (73). Singular E: SVD U' E V = diag(S, 0); with
    z = V' x partitioned (z1 dynamic, z2 algebraic), 0 = A21 z1 + A22 z2 + B2 u is solved
    for z2 (index 1 requires A22 invertible) and substituted: y gains -C2 A22^-1 B2 u on top
    of D u. The states kept are z1, which are the original coordinates whenever E is
    diagonal. The algebra is the same in both time domains (z2 at step k depends on u(k)).
    """
    n = A.shape[0]
    if np.linalg.matrix_rank(E) == n:
        Ei = np.linalg.inv(E)
        return StateSpace(Ei @ A, Ei @ B, C.copy(), D.copy(), names)
    if np.allclose(E, np.diag(np.diag(E))):
        # Diagonal E: keep physical coordinates (a permutation, not a rotation).
        d = np.abs(np.diag(E))
        dyn = [j for j in range(n) if d[j] > 1e-12 * d.max()]
        alg = [j for j in range(n) if j not in dyn]
        U = np.eye(n)[:, dyn + alg]
        V = U
        S = np.diag(E)[dyn]
        hint = ("; E's diagonal entries below 1e-12 of its largest are taken as 0: if that is "
                "a unit mismatch, rescale the states"
                if np.any((d > 0) & (d <= 1e-12 * d.max())) else "")
    else:
        U, s, Vt = np.linalg.svd(E)
        r = int(np.sum(s > 1e-12 * s[0]))
        V = Vt.T
        S = s[:r]
        dyn = list(range(r))
        alg = list(range(r, n))
        hint = ""
    r = len(dyn)
    At = U.T @ A @ V
    Bt = U.T @ B
    Ct = C @ V
    A11, A12 = At[:r, :r], At[:r, r:]
    A21, A22 = At[r:, :r], At[r:, r:]
    B1, B2 = Bt[:r], Bt[r:]
    # A22 invertible, judged by its singular values against the size of A (a determinant
    # over- or underflows with the block's size)
    if np.linalg.matrix_rank(A22, tol=1e-12 * float(np.abs(At).max(initial=0.0))) < n - r:
        raise ModelError(
            "singular E with a singular algebraic block: the descriptor system is not "
            f"index 1 (impulsive modes); only regular index-1 systems are supported{hint}"
        )
    A22i = np.linalg.inv(A22)
    Sinv = np.diag(1.0 / S)
    As = Sinv @ (A11 - A12 @ A22i @ A21)
    Bs = Sinv @ (B1 - A12 @ A22i @ B2)
    C1, C2 = Ct[:, :r], Ct[:, r:]
    Cs = C1 - C2 @ A22i @ A21
    Ds = D - C2 @ A22i @ B2
    if np.allclose(V, np.eye(n)[:, dyn + alg]):
        kept = tuple(names[j] for j in dyn)
    else:
        kept = tuple(f"z{j + 1}" for j in range(r))
    return StateSpace(As, Bs, Cs, Ds, kept)


def _reduce_noise(E: Array, Q: Array) -> Array:
    """Process noise on the reduced (dynamic) states of `_reduce`: E^-1 Q E^-T, or the
    dynamic block scaled by S^-1 (noise in an algebraic equation is left out: it would be
    white noise on the output, which R describes)."""
    n = E.shape[0]
    if np.linalg.matrix_rank(E) == n:
        Ei = np.linalg.inv(E)
        return Ei @ Q @ Ei.T
    # the dynamic states of `_reduce`: the same relative rule
    d = np.abs(np.diag(E))
    keep = [j for j in range(n) if d[j] > 1e-12 * d.max()] if np.allclose(
        E, np.diag(np.diag(E))
    ) else None
    if keep is None:
        U, s, _Vt = np.linalg.svd(E)
        r = int(np.sum(s > 1e-12 * s[0]))
        Sinv = np.diag(1.0 / s[:r])
        Qt = (U.T @ Q @ U)[:r, :r]
        return Sinv @ Qt @ Sinv
    Einv = np.diag(1.0 / np.diag(E)[keep])
    return Einv @ Q[np.ix_(keep, keep)] @ Einv


MIN_PERIOD_S = 1e-6  # `DiscreteModel.full_at` keys its steps by the microsecond

ESTIMATOR_LIMIT_BYTES = 2**30
"""The memory one node's estimator may take (a bus has up to 16 nodes)."""
ESTIMATOR_MAX_MF = 5  # FuzzyConfig().max_mf
ESTIMATOR_ONSET_WINDOW_S = 0.2  # FuzzyUKFConfig().onset_window


def ring_slot_size(n: int, m: int, p: int) -> int:
    """Floats per sample in the fuzzy UKF's onset ring (`layout.RING`): the model check
    sizes the estimator without importing it (numba)."""
    return RING.size(n, m, p)


def estimator_bytes(n: int, m: int, p: int, T: float, *, max_mf: int = ESTIMATOR_MAX_MF,
                    onset_window: float = ESTIMATOR_ONSET_WINDOW_S) -> tuple[float, float]:
    """Bytes of one node's fuzzy UKF for n observable states, m inputs, p outputs at period
    T, as (rule base, onset ring): the rule base over the observable state (consequents and
    their variances, max_mf^n rules per input; 2^n firing rules) and the onset ring
    (onset_window / T + 1 samples).
    The rule base grows as 5^n: 160 MB an input at n = 10, 4 GB at n = 12. Computed in
    the log domain: n = 200 is a number, not an overflow."""
    def power(base: float, k: int) -> float:
        return math.exp(min(700.0, k * math.log(base)))

    rules = 16.0 * m * power(max_mf, n) + 16.0 * power(2.0, n)
    ring = 8.0 * (math.ceil(onset_window / T) + 1) * ring_slot_size(n, m, p)
    return rules, ring


BIAS_MODES: tuple[str, ...] = ("auto", "none", "input", "output")
"""The estimator's bias states (`DiscreteModel.bias_plan`, the rig's `[model] bias`)."""

BIAS_WINDOW_S = 3600.0
"""Seconds over which a bias follows a slow drift by default (`BiasPlan.q`); a step goes
through a bias event."""

BIAS_SIGMA0 = 10.0
"""A bias event (a change of a load or an offset) re-opens the bias to a standard deviation
of this many output noise sigmas (its effect on the outputs)."""


@dataclass(frozen=True)
class BiasPlan:
    """Slowly varying biases beside the state, each a random walk (the estimator's
    augmented state [x; b]; our extension, not the paper's).

    kind "input": one per actuator, x(k+1) = A x + B (u_F + b), y = C x + D (u_F + b): a
    load or an offset of the drive, in the input's units. kind "output": one per output,
    y = C x + D u_F + b: a sensor offset, or at steady state any load. "none": no bias.
    info[i] = h_i' R^-1 h_i is what one sample of the outputs tells about bias i at steady
    state (h_i: its steady-state gain to the outputs; on an integrating plant, the
    outputs' response to it held over 100 periods). Its random walk,
    q[i] = T / (info[i] window^2) per second, makes the filter follow a slow drift of the
    bias with a gain of about T / window per sample (a scalar random walk's stationary
    Kalman gain is sqrt(q T info)); a step is taken by a bias event, which re-opens the
    variance to `var0` (`monitor.estimation.fuzzy_ukf`, step 8).
    """

    kind: Literal["none", "input", "output"]
    info: Array
    T: float
    window: float

    @property
    def count(self) -> int:
        return int(self.info.shape[0])

    @property
    def q(self) -> Array:
        """Random-walk intensity of each bias, its units^2 per second."""
        return np.asarray(self.T / (self.info * self.window**2), np.float64)

    @property
    def var0(self) -> Array:
        """Variance each bias is re-opened to by a bias event (`BIAS_SIGMA0`)."""
        return np.asarray(BIAS_SIGMA0**2 / self.info, np.float64)

    @property
    def var_start(self) -> Array:
        """Initial variance of each bias: the stationary variance of its random walk,
        T / (info window), so that healthy running does not move it."""
        return np.asarray(self.T / (self.info * self.window), np.float64)

    @staticmethod
    def entry(kind: str, B: Array, D: Array) -> tuple[Array, Array]:
        """(B_d, D_d): how the biases enter the state step over dt (B: the model's input
        matrix for that step) and the outputs."""
        n = B.shape[0]
        p = D.shape[0]
        if kind == "input":
            return B, D
        if kind == "output":
            return np.zeros((n, p)), np.eye(p)
        return np.zeros((n, 0)), np.zeros((p, 0))


def _check_period(T: float) -> float:
    if not (isinstance(T, (int, float, np.floating)) and math.isfinite(T) and T > 0):
        raise ModelError(f"sample period must be a positive number of seconds, got {T!r}",
                         "rate")
    if T < MIN_PERIOD_S:
        raise ModelError(f"sample period must be at least {MIN_PERIOD_S:g} s (the estimator "
                         f"keeps its steps to the microsecond), got {T!r}", "rate")
    return float(T)


class _Descriptor:
    """What the continuous and discrete descriptor models share: validation on
    construction, the fault actuators and the reduction to standard form (`_reduce`)."""

    E: Array
    A: Array
    B: Array
    C: Array
    D: Array
    R: Array
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    fault_inputs: FaultInputs

    def _validate_into(self, q_field: str) -> None:
        """Validate the fields and store them normalised (the noise covariance in q_field)."""
        with _numerics("checking the model's matrices"):
            parts = _validate(self, getattr(self, q_field))
        for name, value in parts.items():
            object.__setattr__(self, q_field if name == "Q" else name, value)

    @property
    def faults(self) -> tuple[int, ...]:
        """Indices of the actuators with a loss of effectiveness (sorted)."""
        return cast(tuple[int, ...], self.fault_inputs)

    def standard_form(self) -> StateSpace:
        """Standard form x' = A x + B u (or x(k+1) = ...), y = C x + D u: E^-1 applied
        (73), or the index-1 reduction of a singular E (see `_reduce`)."""
        return _reduce(self.E, self.A, self.B, self.C, self.D, self.state_names)


@dataclass(frozen=True)
class ContinuousDescriptor(_Descriptor):
    """Continuous descriptor model E x' = A x + B u_F + w, y = C x + D u_F + v (63-67).

    The paper's plant (1-2) in continuous time, with u_F = (I - diag(gamma)) u the input
    after the actuators' loss of effectiveness (3-5), so the fault function is
    f = -B diag(gamma) u (8-10). n states, m actuators (columns of B), p outputs (rows of C).

    `Qc` is the process-noise intensity per second (the paper's Q read at its T = 1 s),
    `R` the per-sample measurement-noise covariance of y. `D` is the direct feed-through
    (p x m; empty, the default, means zeros); a singular E adds its own (see
    `standard_form`). `fault_inputs` lists the actuators that can lose effectiveness, by
    index or input name (None, the default: all); the others are known inputs, gamma = 0.
    Input and output names default to u / y (one) or u1.. / y1.. (several). After
    construction the matrices are float arrays and `fault_inputs` a sorted tuple of indices.
    """

    E: Array
    A: Array
    B: Array
    C: Array
    Qc: Array
    R: Array
    state_names: tuple[str, ...]
    input_names: tuple[str, ...] = ()
    output_names: tuple[str, ...] = ()
    D: Array = field(default_factory=_empty)
    fault_inputs: FaultInputs = None
    friction: Friction | None = None

    def __post_init__(self) -> None:
        self._validate_into("Qc")
        if self.friction is not None:
            object.__setattr__(self, "friction", _checked_friction(self, self.friction))

    def noise_standard_form(self) -> Array:
        """Process-noise intensity on the reduced (dynamic) states."""
        return _reduce_noise(self.E, self.Qc)

    def discretize(self, T: float) -> DiscreteModel:
        """Exact ZOH discretisation at sample period T, observable part split off."""
        return DiscreteModel(self, _check_period(T))


@dataclass(frozen=True, kw_only=True)
class DiscreteDescriptor(_Descriptor):
    """Discrete descriptor model at its sample period T, as the paper writes its plant:

        E x(k+1) = A x(k) + B u_F(k) + w(k),   y(k) = C x(k) + D u_F(k) + v(k)   (1-2, 6-7)

    with u_F = (I - diag(gamma_k)) u (3-5), w ~ N(0, Q) per period and v ~ N(0, R). E is
    optional (identity); a singular E of a regular index-1 pencil is reduced as in the
    continuous case. Names and `fault_inputs` as in `ContinuousDescriptor`.

    The estimator must step by dt = k T after missed samples and by jittered dt, which
    powers of A cannot give, so `to_continuous` converts the model by the inverse
    zero-order hold: the continuous model whose exact ZOH at T is (A, B) and whose Van
    Loan covariance over T is Q. Its discretisation at T gives the given matrices back to
    round-off, at k T the k-fold step with the input held, at any other dt the consistent
    interpolation. Where no such model exists (an eigenvalue of A at 0 or on the negative
    real axis) the model is refused: sample faster or give the continuous model.
    """

    A: Array
    B: Array
    C: Array
    Q: Array
    R: Array
    T: float
    E: Array = field(default_factory=_empty)
    D: Array = field(default_factory=_empty)
    state_names: tuple[str, ...] = ()
    input_names: tuple[str, ...] = ()
    output_names: tuple[str, ...] = ()
    fault_inputs: FaultInputs = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "T", _check_period(self.T))
        self._validate_into("Q")

    def to_continuous(self) -> ContinuousDescriptor:
        """The equivalent continuous model by the inverse ZOH (`inverse_zoh`,
        `inverse_van_loan`), in standard form (E = I); R and the names carry over."""
        with _numerics("the inverse zero-order hold (the continuous model of A, B and Q)",
                       advice="give the continuous model"):
            ss = self.standard_form()
            Ac, Bc = inverse_zoh(ss.A, ss.B, self.T)
            Qc = inverse_van_loan(Ac, _reduce_noise(self.E, self.Q), self.T)
        return ContinuousDescriptor(
            E=np.eye(ss.n), A=Ac, B=Bc, C=ss.C, Qc=Qc, R=self.R, D=ss.D,
            state_names=ss.state_names, input_names=self.input_names,
            output_names=self.output_names, fault_inputs=self.faults,
        )

    def to_model(self) -> DiscreteModel:
        """The estimator's model at this period (`DiscreteModel` of `to_continuous`)."""
        return DiscreteModel(self.to_continuous(), self.T)


@dataclass
class DiscreteModel:
    """The estimator's view of a plant: ZOH matrices for any multiple of the period.

    `at(dt)` returns (A, B, Q) for a step of dt seconds on the observable states x_o,
    cached, so a missed sample (dt = k T) or a jittered period costs one expm once.
    The output map is y = C x_o + D u_F; `Wobs`/`Wunobs` map full states to the
    observable and unobservable parts. `fault_inputs` are the actuators whose loss of
    effectiveness is estimated. Build one with `ContinuousDescriptor.discretize`,
    `DiscreteModel.from_discrete` or `model_from_matrices`.
    """

    continuous: ContinuousDescriptor
    T: float
    _cache: dict[int, tuple[Array, Array, Array, Array, Array]] = field(
        default_factory=dict, repr=False
    )
    _bias_plans: dict[tuple[str, float], BiasPlan] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        self.T = _check_period(self.T)
        with _numerics("reducing the model to its observable standard form (E^-1 A, "
                       "E^-1 B, E^-1 Q E^-T)", advice="rescale the states (units) or check E"):
            ss = self.continuous.standard_form()
            self.continuous.noise_standard_form()
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
        self._p0 = self._check_estimable()
        with _numerics("the fault's observability test"):
            self._check_fault_observable()

    def _check_estimable(self) -> Array:
        """What the estimator computes from the model before its first step, computed once
        here, so that a model that passes is one `FuzzyUKF` takes without raising: its
        memory (`estimator_bytes` of the default estimator) within ESTIMATOR_LIMIT_BYTES,
        the zero-order hold over one period finite, and the initial covariance P0 (the
        estimator's, `initial_covariance`) with P0 and the innovation covariance
        C P0 C' + R both Cholesky-factorable (the sigma points and the gain). Returns P0.
        """
        T = self.T
        if self.n == 0:
            raise ModelError("no state of the model reaches its outputs (C and its products "
                             "with A are zero): the estimator needs at least one state the "
                             "outputs observe")
        rules, ring = estimator_bytes(self.n, self.m, self.p, T)
        need = rules + ring
        if need > ESTIMATOR_LIMIT_BYTES:
            raise ModelError(
                f"the estimator of this model's {self.n} observable states at {1.0 / T:g} Hz "
                f"would need {need / 2**30:.3g} GiB a node (at most "
                f"{ESTIMATOR_LIMIT_BYTES / 2**30:g}): "
                + ("its onset ring holds n^2 floats a sample: lower the rate"
                   if ring > rules else
                   f"its fuzzy rule base spans the observable state ({ESTIMATOR_MAX_MF}^n "
                   "rules): fewer observable states (at most 10 for one input)"),
                "rate" if ring > rules else None)
        A, B, Q = self.at(T)
        if not (np.all(np.isfinite(A)) and np.all(np.isfinite(B)) and np.all(np.isfinite(Q))):
            raise self._zoh_failure()
        P = self._initial_covariance()
        if P is None:
            raise ModelError(
                f"the estimator finds no initial covariance at {1.0 / T:g} Hz: the "
                "stationary Kalman covariance does not exist (no process noise on an "
                "unstable or undamped mode) and the states are not recoverable from n "
                "samples of the outputs; give Q > 0 on every state or sample faster")
        try:
            with np.errstate(over="raise", invalid="raise"):
                np.linalg.cholesky(P)
                np.linalg.cholesky(self.C @ P @ self.C.T + self.R)
        except (np.linalg.LinAlgError, FloatingPointError):
            raise ModelError(
                f"the estimator's initial covariance at {1.0 / T:g} Hz is not positive "
                "definite in floating point (states whose variances differ by more than "
                "1e12 or beyond the float range): rescale the states (units) or check Q "
                "and R") from None
        return P

    def _zoh_failure(self) -> ModelError:
        """Why the zero-order hold over one period is not finite, as the error to raise:
        an unstable mode that grows past the float range within a period (the rate's
        fault: key "rate"), or |A T| too large for scipy's expm (whose norm estimates
        square A T several times) although the model is stable."""
        T = self.T
        A = self._ss.A
        try:
            growth = float(np.max(np.linalg.eigvals(A).real)) * T
        except np.linalg.LinAlgError:
            growth = math.inf
        if growth > 300.0:  # its covariance grows by e^(2 growth); e^709 is the largest float
            return ModelError(
                f"a mode of the model grows by e^{growth:.4g} within one sample period "
                f"({T:g} s), its covariance by the square of that, beyond the floating-point "
                f"range (unstable A, max Re(eig) = {growth / T:.4g}/s): sample faster or "
                "check the signs in A", "rate")
        size = float(np.abs(A).max(initial=0.0)) * T
        return ModelError(
            f"the zero-order hold expm(A T) over one sample period ({T:g} s) is beyond "
            f"floating point: A T has entries up to {size:.3g} (a mode that much faster "
            "than the sampling); rescale the units of A")

    def _initial_covariance(self) -> Array | None:
        """The estimator's P0 (see `initial_covariance`), None if there is none."""
        A, _, Q = self.at(self.T)
        C, R = self.C, self.R
        n = A.shape[0]
        # Overflow, NaN and a failed solve all mean "not this way": each result is tested.
        with np.errstate(all="ignore"):
            P: Array | None = None
            try:
                Pm = scipy.linalg.solve_discrete_are(A.T, C.T, Q, R)
                P = Pm - Pm @ C.T @ np.linalg.solve(C @ Pm @ C.T + R, C @ Pm)
                P = 0.5 * (P + P.T)
                ev = np.linalg.eigvalsh(P)
                if not (np.all(np.isfinite(ev)) and ev[0] > 1e-12 * ev[-1]):
                    P = None
            except (np.linalg.LinAlgError, ValueError):
                P = None
            if P is None:
                try:
                    obs = np.vstack([C @ np.linalg.matrix_power(A, k) for k in range(n)])
                    Ri = np.kron(np.eye(n), np.linalg.inv(R))
                    P = np.linalg.inv(obs.T @ Ri @ obs)
                    P = 0.5 * (P + P.T)
                except (np.linalg.LinAlgError, ValueError):
                    return None
            if not np.all(np.isfinite(P)):
                return None
        return np.asarray(P)

    def initial_covariance(self) -> Array:
        """A scale-aware initial covariance of the observable state (the estimator's P0).

        The Kalman filter's stationary posterior covariance at the model's period (the
        discrete Riccati equation): the state known as well as the filter will ever know
        it, in the state's own units, where an absolute P0 = 1 is a tiny uncertainty for a
        speed of 800 rad/s and a huge one for a current of 0.26 A. Where that has no
        positive definite solution (no process noise, say), the covariance of the state
        fitted to n noisy samples of the outputs, (O' R^-1 O)^-1 with
        O = [C; C A; ...; C A^(n-1)]. Computed and checked when the model is built.
        """
        return self._p0

    @classmethod
    def from_discrete(
        cls, A: object, B: object, C: object, Q: object, R: object, T: float, *,
        D: object = None, E: object = None, state_names: Sequence[str] = (),
        input_names: Sequence[str] = (), output_names: Sequence[str] = (),
        fault_inputs: FaultInputs = None,
    ) -> DiscreteModel:
        """The model of a plant given at its sample period T (see `DiscreteDescriptor`):
        converted by the inverse zero-order hold, so that `at(T)` gives (A, B, Q) back
        (on the observable part) and `at(k T)` the k-step model with the input held."""
        return DiscreteDescriptor(
            A=cast(Array, A), B=cast(Array, B), C=cast(Array, C), Q=cast(Array, Q),
            R=cast(Array, R), T=T, E=cast(Array, E), D=cast(Array, D),
            state_names=tuple(state_names), input_names=tuple(input_names),
            output_names=tuple(output_names), fault_inputs=fault_inputs,
        ).to_model()

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

    @property
    def fault_inputs(self) -> tuple[int, ...]:
        """Actuators whose loss of effectiveness gamma is estimated; the others are known."""
        return self.continuous.faults

    def _check_fault_observable(self) -> None:
        # gamma of the fault actuators is a random-walk state (a mode at z = 1): it is
        # observable iff the steady-state gain from those actuators to the outputs has full
        # column rank, i.e. rank [[A - I, B_F], [C, D_F]] = n + m_F on the observable part
        # (PBH at z = 1 of the augmented system, for a unit input on each fault actuator).
        # Known actuators carry no gamma and do not take part.
        Ao, Bo, _, _, _ = self.full_at(self.T)
        F = list(self.fault_inputs)
        n = self.n
        M = np.block([[Ao - np.eye(n), Bo[:, F]], [self.C, self.D[:, F]]])
        if np.linalg.matrix_rank(M, tol=1e-9 * max(1.0, float(np.abs(M).max()))) < n + len(F):
            names = ", ".join(self.continuous.input_names[a] for a in F)
            raise ModelError(
                f"a loss of effectiveness of some actuator ({names}) does not show in the "
                "outputs (steady-state gain to y is rank-deficient): the fault is not observable"
            )

    def full_at(self, dt: float) -> tuple[Array, Array, Array, Array, Array]:
        """(A_o, B_o, Q_o, A_full, B_full) for a step of dt seconds, cached per microsecond."""
        key = round(dt * 1e6) if math.isfinite(dt) else 0
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        if key <= 0:
            raise ModelError(f"step of {dt!r} s: time must move forward")
        ss = self._ss
        # The period itself was checked finite when the model was built; a step of many
        # periods (predicting through lost samples) of an unstable model may overflow,
        # which the estimator meets as NaN, counts and restarts from: no warning each time.
        with np.errstate(over="ignore", invalid="ignore", under="ignore"):
            Ad, Bd = zoh(ss.A, ss.B, key * 1e-6)
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

    @property
    def friction(self) -> Friction | None:
        """The model's Coulomb friction (`monitor.estimation.friction`), None without."""
        return self.continuous.friction

    def friction_at(self, dt: float) -> Array:
        """The zero-order hold of the friction's column b_f over a step of dt on the
        observable states (zeros without friction): the step's response to phi of (1)
        held over it, as `at` gives B for the inputs."""
        fr = self.continuous.friction
        if fr is None:
            return np.zeros(self.n)
        ss = self._ss
        Ef = np.asarray(np.linalg.solve(self.continuous.E, fr.B)[:, None], dtype=np.float64)
        with np.errstate(over="ignore", invalid="ignore", under="ignore"):
            _, Fd = zoh(ss.A, Ef, dt)
        return np.ascontiguousarray(self.Wobs @ Fd[:, 0])

    def bias_plan(self, mode: str, window: float) -> BiasPlan:
        """The slowly varying biases the estimator adds to its state for `mode` (one of
        BIAS_MODES), each observable with the model's state (see `BiasPlan`), computed once
        per (mode, window).

        "output" (one offset per output) and "input" (one bias per actuator) are refused
        with a one-line ModelError (key "bias") where the outputs cannot tell the biases
        from the state: rank [[A - I, B_d], [C, D_d]] < n + n_b on the observable part (the
        PBH test at z = 1 of the pair augmented with the biases, which are modes at z = 1).
        "auto" takes "output" where it is observable, else "input", else none, the last
        with one log line. `window`: seconds over which a bias follows a slow drift (its
        random-walk intensity, `BiasPlan.q`)."""
        key = (mode, float(window))
        hit = self._bias_plans.get(key)
        if hit is not None:
            return hit
        if mode not in BIAS_MODES:
            raise ModelError(f"bias must be one of {', '.join(BIAS_MODES)}, got {mode!r}", "bias")
        if not (math.isfinite(window) and window > 0.0):
            raise ModelError(f"the bias window must be a positive number of seconds, got "
                             f"{window!r}", "bias")
        plan: BiasPlan | None = None
        if mode == "none":
            plan = BiasPlan("none", np.zeros(0), self.T, window)
        elif mode in ("output", "input"):
            plan, why = self._bias_try(mode, window)
            if plan is None:
                raise ModelError(why, "bias")
        else:
            why_out = why_in = ""
            plan, why_out = self._bias_try("output", window)
            if plan is None:
                plan, why_in = self._bias_try("input", window)
            if plan is None:
                _log.warning("bias = \"auto\": no bias state: %s; %s", why_out, why_in)
                plan = BiasPlan("none", np.zeros(0), self.T, window)
        self._bias_plans[key] = plan
        return plan

    def _bias_try(self, kind: str, window: float) -> tuple[BiasPlan | None, str]:
        """(the plan of `kind`, "") if its biases are observable with the state, else
        (None, why)."""
        with _numerics(f"the observability test of the {kind} biases"):
            A, B, _ = self.at(self.T)
            n, m, p = self.n, self.m, self.p
            Bd, Dd = BiasPlan.entry(kind, B, self.D)
            nb = Bd.shape[1]
            M = np.block([[A - np.eye(n), Bd], [self.C, Dd]])
            rank = np.linalg.matrix_rank(M, tol=1e-9 * max(1.0, float(np.abs(M).max())))
            if rank < n + nb:
                if kind == "output":
                    why = ("bias = \"output\": an offset on each output is not told apart from "
                           "the state (the outputs see an integrator: A has an eigenvalue at "
                           "1), so it is not observable; use \"input\", \"auto\" or \"none\"")
                else:
                    why = (f"bias = \"input\": a constant bias on each of the {m} inputs is not "
                           f"told apart from the state by the {p} output(s) (rank "
                           "[[A - I, B], [C, D]] < n + m), so it is not observable; use "
                           "\"output\", \"auto\" or \"none\"")
                return None, why
            # what the outputs show of a unit bias held over the window, per bias: its
            # steady-state gain on a stable plant, a finite measure on an integrating one
            if kind == "output":
                H = np.eye(p)
            elif np.linalg.cond(np.eye(n) - A) < 1e12:
                H = self.C @ np.linalg.solve(np.eye(n) - A, B) + self.D
            else:  # an integrating plant: the response to the bias held over 100 periods
                _, Bw, _ = self.at(100.0 * self.T)
                H = self.C @ Bw + self.D
            info = np.einsum("pb,pq,qb->b", H, np.linalg.inv(self.R), H)
        if not (np.all(np.isfinite(info)) and np.all(info > 0.0)):
            return None, f"bias = \"{kind}\": a bias does not reach the outputs"
        return BiasPlan(cast(Literal["input", "output"], kind), np.asarray(info, np.float64),
                        self.T, window), ""

    @cached_property
    def dc_gain(self) -> Array:
        """Steady-state gain y/u per actuator (p x m): C (I - A)^-1 B + D."""
        A, B, _ = self.at(self.T)
        return np.asarray(self.C @ np.linalg.solve(np.eye(self.n) - A, B) + self.D)


def model_from_matrices(
    domain: Literal["continuous", "discrete"] | str,
    *,
    A: object,
    B: object,
    C: object,
    Q: object,
    R: object,
    T: float,
    E: object = None,
    D: object = None,
    fault_inputs: FaultInputs = None,
    state_names: Sequence[str] | None = None,
    input_names: Sequence[str] | None = None,
    output_names: Sequence[str] | None = None,
    friction: Friction | None = None,
) -> DiscreteModel:
    """The estimator's model from plain matrices (nested lists as read from a rig file).

    domain "continuous": E x' = A x + B u_F + w, y = C x + D u_F + v with Q the noise
    intensity per second, sampled by the ECU every T seconds. domain "discrete":
    E x(k+1) = A x(k) + B u_F(k) + w(k) at period T with Q per period, converted by the
    inverse zero-order hold (`DiscreteDescriptor`). E (identity) and D (zeros) are optional;
    `fault_inputs` are actuator indices or input names (all by default); names default to
    x1.., u/u1.., y/y1... `friction`: Coulomb friction (`monitor.estimation.friction`), of
    the continuous domain only. Any problem raises a one-line ModelError naming the matrix.
    """
    if domain not in ("continuous", "discrete"):
        raise ModelError(f"model domain must be 'continuous' or 'discrete', got {domain!r}")
    names: list[tuple[str, ...]] = []
    for key, given in (("state_names", state_names), ("input_names", input_names),
                       ("output_names", output_names)):
        if isinstance(given, str) or any(not isinstance(s, str) for s in given or ()):
            raise ModelError(f"{key} must be a list of strings")
        names.append(tuple(given or ()))
    sts, ins, outs = names
    if domain == "continuous":
        return ContinuousDescriptor(
            E=cast(Array, E), A=cast(Array, A), B=cast(Array, B), C=cast(Array, C),
            Qc=cast(Array, Q), R=cast(Array, R), D=cast(Array, D), state_names=sts,
            input_names=ins, output_names=outs, fault_inputs=fault_inputs,
            friction=friction,
        ).discretize(T)
    if friction is not None:
        raise ModelError("friction is given in continuous time: use domain \"continuous\"")
    return DiscreteModel.from_discrete(A, B, C, Q, R, T, D=D, E=E, state_names=sts,
                                       input_names=ins, output_names=outs,
                                       fault_inputs=fault_inputs)


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
    speed_noise_ratio: float = 1.0,
) -> ContinuousDescriptor:
    """The DC motor (63-67) as a continuous descriptor model, states [i, omega, theta].

        [La 0 0] [di/dt ]   [-Ra -Ke 0] [i    ]   [1]
        [0  J 0] [dw/dt ] = [ Ki -b  0] [omega] + [0] u,    y = i   (68)
        [0  0 1] [dth/dt]   [ 0   1  0] [theta]   [0]

    This is (65) multiplied by La, so La = 0 gives a singular E with an algebraic current
    equation Ra i + Ke omega = u (index 1). The paper's printed (67) writes Ke/La in the
    first row with the wrong sign and 1 in place of omega in the third; (63)-(65) are used.
    `q` is the process-noise intensity per second on each state (the paper's Q = 1.44 I
    read at its T = 1 s), `r` the current-sensor variance in A^2 (R = 0.25);
    `speed_noise_ratio` scales the intensity on speed and angle relative to the current's
    (1 in the paper; `monitor.identify` fits it, since a J known only up to scale rescales
    the speed state).
    """
    p = params or DCMotorParameters()
    for name in ("J", "b", "Ke", "Ki", "Ra"):
        if getattr(p, name) <= 0:
            raise ModelError(f"motor parameter {name} must be positive, got {getattr(p, name)}")
    if p.La < 0:
        raise ModelError(f"motor parameter La must be >= 0, got {p.La}")
    for name, value in (*((k, getattr(p, k)) for k in ("J", "b", "Ke", "Ki", "Ra", "La")),
                        ("process_noise", q), ("output_sigma^2", r)):
        if not (math.isfinite(value) and abs(value) <= MAX_ENTRY):
            raise ModelError(f"motor parameter {name} is {value:.3g}: beyond {MAX_ENTRY:g} the "
                             "estimator's covariances leave the floating-point range; "
                             "rescale the units")
    E = np.diag([p.La, p.J, 1.0])
    A = np.array([[-p.Ra, -p.Ke, 0.0], [p.Ki, -p.b, 0.0], [0.0, 1.0, 0.0]])
    B = np.array([[1.0], [0.0], [0.0]])
    C = np.array([[1.0, 0.0, 0.0]])
    # Q is given on the physical states; in descriptor form the noise enters E x' so
    # scale it by E to keep the paper's per-state intensity where E is invertible.
    Eq = np.diag([p.La if p.La > 0 else 1.0, p.J, 1.0])
    if not (math.isfinite(speed_noise_ratio) and speed_noise_ratio > 0):
        raise ModelError(f"speed_noise_ratio must be positive, got {speed_noise_ratio}")
    Qc = Eq @ (q * np.diag([1.0, speed_noise_ratio, speed_noise_ratio])) @ Eq
    if float(np.abs(Qc).max()) > MAX_ENTRY:  # a J or La in other units, squared
        raise ModelError(f"J = {p.J:g} kg m^2, La = {p.La:g} H: the motor's process-noise "
                         f"intensity (La^2 q, J^2 q speed_noise_ratio) reaches "
                         f"{float(np.abs(Qc).max()):.3g}, beyond {MAX_ENTRY:g}; check the units")
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
