"""Fault diagnosis by fuzzy c-means clustering of the estimated loss of effectiveness.

The paper (Liu et al., Int. J. Fuzzy Syst. 22(1), 2020, section 4) collects the fault
information in a set S (55), clusters it with fuzzy c-means (56)-(62) into three groups
(fault-free, fault, outage) and reads two thresholds F1 < F2 off the clusters, which split
the fault quantity into the regions of (76):

    F < F1          fault-free
    F1 <= F <= F2   fault
    F > F2          outage

Which quantity is clustered
---------------------------
The paper clusters its fault function f^ = -B gamma^ u, which is in state units: it scales
with the input voltage u and with the input matrix B, so thresholds found on one motor (or
at one supply voltage) do not carry over to another. This module clusters the *scale-free*
estimate gamma^ of the actuator loss of effectiveness (3)-(5) instead: gamma = 0 is
fault-free and gamma = 1 is a complete outage, for every motor and voltage. The paper's
reported F1 = 0.3, F2 = 1 are in its own units and are deliberately not hard-coded; see
`DEFAULT_THRESHOLDS` for the gamma defaults and `calibrate` for thresholds from a run.

Fuzzy c-means, as implemented
-----------------------------
For points x_k (k = 1..N) and centres c_i (i = 1..c), with distances d_ik = |x_k - c_i|
and fuzzifier m > 1, the objective (56)/(61) is J_m = sum_i sum_k u_ik^m d_ik^2 subject to
sum_i u_ik = 1 for every k (59)/(62). Its stationary conditions are

    u_ik = 1 / sum_j (d_ik / d_jk)^(2/(m-1))          (58)
    c_i  = sum_k u_ik^m x_k / sum_k u_ik^m             (57)

and alternating them decreases J_m monotonically (Bezdek 1981). The paper prints (58) with
the squared-distance ratio and no exponent, which is m = 2; its (57) weights the points by
u rather than u^m, which is not the minimiser paired with (58), and its (56) divides by
sum u. We use the consistent Bezdek pair above, with m = 2 by default and any m > 1
accepted. A point that coincides with a centre (d_ik = 0) belongs wholly to that cluster
(the limit of (58)); memberships are evaluated in log space, so no NaN or overflow arises
even for m close to 1.

Thresholds
----------
Because u_ik is proportional to d_ik^(-2/(m-1)), two clusters i and j have equal
membership at x iff d_i(x) = d_j(x), i.e. |x - c_i| = |x - c_j|: for 1-D data that is the
midpoint (c_i + c_j) / 2, whatever the fuzzifier m and whatever the other centres (they
only change the common normaliser). So F1 and F2 are the midpoints of adjacent sorted
centres, exactly.

Online use
----------
`classify` is (76) applied to one value. `OnlineClassifier` adds a hysteresis band around
each threshold and a dwell time measured in sample timestamps, so noise near a threshold
does not make the reported state flicker. `HealthState` values are the numbers sent on the
CAN bus.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import os
import tempfile
import tomllib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from enum import IntEnum
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

__all__ = [
    "DEFAULT_THRESHOLDS",
    "DiagnosisError",
    "FCMResult",
    "HealthState",
    "OnlineClassifier",
    "Thresholds",
    "calibrate",
    "classify",
    "fcm_memberships",
    "fuzzy_c_means",
    "load_thresholds",
    "save_thresholds",
    "thresholds_from_clusters",
    "transitions",
]


class DiagnosisError(ValueError):
    """Bad clustering input, bad thresholds or a bad thresholds file (one-line message)."""


def _one_line(message: str) -> str:
    return " ".join(message.split())


# --------------------------------------------------------------------------------------
# Fuzzy c-means, eqs (55)-(62)
# --------------------------------------------------------------------------------------


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


# --------------------------------------------------------------------------------------
# Thresholds F1 < F2 of eq (76)
# --------------------------------------------------------------------------------------


def _finite_number(name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
        raise DiagnosisError(f"{name} must be a number, got {type(value).__name__}")
    out = float(value)
    if not math.isfinite(out):
        raise DiagnosisError(f"{name} must be finite, got {out!r}")
    return out


@dataclass(frozen=True)
class Thresholds:
    """Thresholds F1 < F2 of eq (76) on `quantity` (default gamma^, the loss of effectiveness).

    `centres` records the sorted cluster centres they came from (empty for hand-set ones).
    """

    f1: float
    f2: float
    quantity: str = "gamma"
    centres: tuple[float, ...] = field(default=())

    def __post_init__(self) -> None:
        f1 = _finite_number("f1", self.f1)
        f2 = _finite_number("f2", self.f2)
        if not f1 < f2:
            raise DiagnosisError(f"f1 ({f1!r}) must be less than f2 ({f2!r})")
        if not isinstance(self.quantity, str) or not self.quantity.strip():
            raise DiagnosisError("quantity must be a non-empty string")
        if self.quantity == "gamma" and not 0.0 < f1 < f2 < 1.0:
            # gamma^ lies in [0, 1]: outside, a region (76) could never be reported
            raise DiagnosisError(f"gamma thresholds must satisfy 0 < f1 < f2 < 1, "
                                 f"got f1 = {f1!r}, f2 = {f2!r}")
        try:
            centres = tuple(_finite_number(f"centres[{i}]", c) for i, c in enumerate(self.centres))
        except TypeError as exc:
            raise DiagnosisError("centres must be a sequence of numbers") from exc
        if any(b <= a for a, b in itertools.pairwise(centres)):
            raise DiagnosisError("centres must be strictly increasing")
        object.__setattr__(self, "f1", f1)
        object.__setattr__(self, "f2", f2)
        object.__setattr__(self, "centres", centres)


DEFAULT_THRESHOLDS = Thresholds(f1=0.15, f2=0.85, quantity="gamma")
"""Hand-set gamma thresholds used when no calibrated thresholds file is given.

Typical gamma^ clusters are fault-free at 0, a partial fault somewhere in 0.3-0.7 and an
outage at 1. The equal-membership midpoints are then F1 in [0.15, 0.35] and F2 in
[0.65, 0.85]; F1 = 0.15 = (0 + 0.3)/2 and F2 = 0.85 = (0.7 + 1)/2 are the widest choice, so
every partial fault in that range is reported as a fault and not confused with fault-free
or outage. The monitor uses calibrated thresholds (`calibrate`, `load_thresholds`) when a
file is given. The paper's F1 = 0.3, F2 = 1 are in its f^ units and do not apply here.
"""


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


# --------------------------------------------------------------------------------------
# Thresholds file (TOML)
# --------------------------------------------------------------------------------------


def _toml_string(value: str) -> str:
    out = ['"']
    for ch in value:
        code = ord(ch)
        if ch == '"':
            out.append('\\"')
        elif ch == "\\":
            out.append("\\\\")
        elif ch == "\n":
            out.append("\\n")
        elif ch == "\t":
            out.append("\\t")
        elif ch == "\r":
            out.append("\\r")
        elif code < 0x20 or code == 0x7F:
            out.append(f"\\u{code:04X}")
        elif 0xD800 <= code <= 0xDFFF:  # lone surrogate: not representable in TOML
            out.append("\\uFFFD")
        else:
            out.append(ch)
    out.append('"')
    return "".join(out)


def _toml_float(value: float) -> str:
    text = repr(float(value))  # shortest round-trip form; valid TOML for finite floats
    if text in ("inf", "-inf", "nan"):
        raise DiagnosisError(f"cannot write non-finite value {text}")
    return text


def save_thresholds(
    path: str | os.PathLike[str], thresholds: Thresholds, *, source: str = ""
) -> None:
    """Write `thresholds` as a small TOML file (atomically: temporary file, then rename).

    Keys: quantity, f1, f2, centres, source (free text, e.g. the run it was calibrated on)
    and created (UTC offset date-time). Read back with `load_thresholds`.
    """
    path = Path(path)
    created = datetime.now(UTC).isoformat(timespec="seconds")
    centres = ", ".join(_toml_float(c) for c in thresholds.centres)
    text = (
        "# motor-monitor diagnosis thresholds, eq (76) of Liu et al. 2020\n"
        "# fault-free: value < f1; fault: f1 <= value <= f2; outage: value > f2\n"
        f"quantity = {_toml_string(thresholds.quantity)}\n"
        f"f1 = {_toml_float(thresholds.f1)}\n"
        f"f2 = {_toml_float(thresholds.f2)}\n"
        f"centres = [{centres}]\n"
        f"source = {_toml_string(source)}\n"
        f"created = {created}\n"
    )
    directory = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def load_thresholds(path: str | os.PathLike[str], *, quantity: str = "gamma") -> Thresholds:
    """Read thresholds written by `save_thresholds` (or by hand).

    Required keys: quantity (must equal `quantity`), f1, f2; optional: centres, source,
    created. Any problem (missing or unreadable file, invalid TOML, missing key, non-number,
    non-finite value, f1 >= f2, wrong quantity) raises DiagnosisError with one line naming
    the file and the problem.
    """
    name = os.fspath(path)

    def fail(problem: str) -> DiagnosisError:
        return DiagnosisError(_one_line(f"thresholds file {name}: {problem}"))

    try:
        with open(name, "rb") as fh:
            doc = tomllib.load(fh)
    except FileNotFoundError:
        raise fail("file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise fail(f"not valid TOML: {exc}") from None
    except UnicodeDecodeError as exc:
        raise fail(f"not valid TOML (not UTF-8: {exc.reason})") from None
    except OSError as exc:
        raise fail(f"cannot read: {exc.strerror or exc}") from None
    for key in ("quantity", "f1", "f2"):
        if key not in doc:
            raise fail(f"missing key '{key}'")
    found = doc["quantity"]
    if not isinstance(found, str):
        raise fail(f"quantity must be a string, got {type(found).__name__}")
    if found != quantity:
        raise fail(f"thresholds are for quantity '{found}', expected '{quantity}'")
    centres = doc.get("centres", [])
    if not isinstance(centres, list):
        raise fail(f"centres must be an array, got {type(centres).__name__}")
    try:
        return Thresholds(f1=doc["f1"], f2=doc["f2"], quantity=found, centres=tuple(centres))
    except DiagnosisError as exc:
        raise fail(str(exc)) from None


# --------------------------------------------------------------------------------------
# Health states and classification, eq (76)
# --------------------------------------------------------------------------------------


class HealthState(IntEnum):
    """Diagnosed actuator health; the integer values are sent on the CAN bus."""

    FAULT_FREE = 0
    FAULT = 1
    OUTAGE = 2
    NO_DATA = 3

    @property
    def label(self) -> str:
        """'fault_free', 'fault', 'outage' or 'no_data'."""
        return self.name.lower()


_STATES = (HealthState.FAULT_FREE, HealthState.FAULT, HealthState.OUTAGE, HealthState.NO_DATA)


def classify(value: float, thresholds: Thresholds) -> HealthState:
    """Eq (76): value < F1 fault-free; F1 <= value <= F2 fault; value > F2 outage.

    NaN (no estimate) gives NO_DATA.
    """
    if value < thresholds.f1:
        return HealthState.FAULT_FREE
    if value <= thresholds.f2:
        return HealthState.FAULT
    if value > thresholds.f2:
        return HealthState.OUTAGE
    return HealthState.NO_DATA  # NaN: every comparison above was False


class OnlineClassifier:
    """Debounced online version of (76) for a stream of (timestamp, value) samples.

    Hysteresis: the region of the reported state is widened by `hysteresis` on each side,
    so to leave a region the value must cross its threshold by that much (fault-free is
    left at value >= F1 + h, fault at value < F1 - h or value > F2 + h, outage at
    value <= F2 - h). With h = 0 the regions are exactly those of (76).

    Dwell: the reported state changes to a candidate only after the candidate has persisted
    for `dwell_s` seconds of *sample time* (the timestamps passed to `update`, never the
    wall clock); it is reported on the first sample at or after onset + dwell_s. If the
    value stays outside the reported region for dwell_s but alternates between the two
    other states (noise right at the far threshold), the state moves one step towards
    them (fault-free or outage -> fault; from fault, to the latest candidate), and the
    usual rule continues from there.

    NO_DATA: the classifier starts in NO_DATA, and `mark_no_data(t)` forces it (a silent
    ECU). The first valid sample after NO_DATA is classified by (76) and reported at once,
    without dwell or hysteresis: there is no previous state to debounce against.

    NaN values are ignored and counted (`n_ignored_nan`); samples whose timestamp is NaN
    or earlier than the previous sample are ignored and counted (`n_ignored_time`).
    `update` uses plain floats and ints only; it is cheap enough for thousands of calls
    per second.
    """

    __slots__ = (
        "_away_since",
        "_cand",
        "_cand_since",
        "_dwell",
        "_f1",
        "_f1_down",
        "_f1_up",
        "_f2",
        "_f2_down",
        "_f2_up",
        "_last_t",
        "_n_nan",
        "_n_time",
        "_onset",
        "_since",
        "_state",
        "thresholds",
    )

    def __init__(
        self, thresholds: Thresholds, *, dwell_s: float = 0.05, hysteresis: float = 0.02
    ) -> None:
        dwell_s = float(dwell_s)
        hysteresis = float(hysteresis)
        if not (math.isfinite(dwell_s) and dwell_s >= 0.0):
            raise DiagnosisError(f"dwell_s must be a finite number >= 0, got {dwell_s!r}")
        half_gap = 0.5 * (thresholds.f2 - thresholds.f1)
        if not (math.isfinite(hysteresis) and 0.0 <= hysteresis < half_gap):
            raise DiagnosisError(
                f"hysteresis must be in [0, (f2 - f1)/2 = {half_gap:g}), got {hysteresis!r}"
            )
        self.thresholds = thresholds
        self._f1 = thresholds.f1
        self._f2 = thresholds.f2
        self._f1_up = thresholds.f1 + hysteresis
        self._f1_down = thresholds.f1 - hysteresis
        self._f2_up = thresholds.f2 + hysteresis
        self._f2_down = thresholds.f2 - hysteresis
        self._dwell = dwell_s
        self._state = 3
        self._since: float | None = None
        self._onset: float | None = None
        self._cand = -1
        self._cand_since = 0.0
        self._away_since: float | None = None
        self._last_t = -math.inf
        self._n_nan = 0
        self._n_time = 0

    @property
    def state(self) -> HealthState:
        """The reported state."""
        return _STATES[self._state]

    @property
    def since(self) -> float | None:
        """Timestamp at which the reported state was adopted (None before any input)."""
        return self._since

    @property
    def onset(self) -> float | None:
        """Timestamp of the first sample supporting the reported state (since - dwell, about)."""
        return self._onset

    @property
    def n_ignored_nan(self) -> int:
        return self._n_nan

    @property
    def n_ignored_time(self) -> int:
        return self._n_time

    def _enter(self, state: int, t: float, onset: float) -> HealthState | None:
        self._cand = -1
        self._away_since = None
        if state == self._state:
            return None
        self._state = state
        self._since = t
        self._onset = onset
        return _STATES[state]

    def mark_no_data(self, t: float) -> HealthState | None:
        """Force NO_DATA at time t (e.g. the ECU fell silent); returns it if it is new."""
        if t > self._last_t:
            self._last_t = t
        return self._enter(3, t, t)

    def update(self, t: float, value: float) -> HealthState | None:
        """Feed one sample; return the new state on a transition, else None."""
        if value != value:  # NaN
            self._n_nan += 1
            return None
        if not t >= self._last_t:  # also catches a NaN timestamp
            self._n_time += 1
            return None
        self._last_t = t
        s = self._state
        if (
            (s == 0 and value < self._f1_up)
            or (s == 1 and self._f1_down <= value <= self._f2_up)
            or (s == 2 and value > self._f2_down)
        ):  # inside the reported state's region widened by the hysteresis
            self._cand = -1
            self._away_since = None
            return None
        # Outside the reported (widened) region, or NO_DATA: plain (76).
        c = 0 if value < self._f1 else (1 if value <= self._f2 else 2)
        if s == 3:
            return self._enter(c, t, t)
        if self._away_since is None:
            self._away_since = t
        if c != self._cand:
            self._cand = c
            self._cand_since = t
        slack = 1e-9 + abs(t) * 1e-15  # float round-off in timestamp differences
        if t - self._cand_since >= self._dwell - slack:
            return self._enter(c, t, self._cand_since)
        if t - self._away_since >= self._dwell - slack:
            return self._enter(1 if s != 1 else c, t, self._away_since)
        return None


def transitions(
    times: Iterable[float], states: Iterable[int | HealthState]
) -> list[tuple[float, HealthState, HealthState]]:
    """State changes in a sampled state sequence: [(time, from_state, to_state), ...].

    The time is that of the first sample in the new state. `times` and `states` must have
    the same length; states are HealthState members or their integer values.
    """
    ts = [float(t) for t in times]
    try:
        ss = [HealthState(int(s)) for s in states]
    except ValueError as exc:
        raise DiagnosisError(f"invalid health state: {exc}") from None
    if len(ts) != len(ss):
        raise DiagnosisError(f"times has {len(ts)} entries but states has {len(ss)}")
    return [(ts[i], ss[i - 1], ss[i]) for i in range(1, len(ss)) if ss[i] != ss[i - 1]]
