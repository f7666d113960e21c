"""The self-constructing fuzzy UKF fault estimator, eqs (50)-(54) around (15)-(49).

One `FuzzyUKF` per motor takes one sample (u, y, dt) at a time and returns the state
estimate x^, the fault-model state x~, the loss of effectiveness gamma^, the fault
function f^ = -B diag(u) gamma^, the rule count and the normalised innovation.

Per sample k (the paper's order, made sound where NOTES.md says it must be):

1. The fuzzy system (17), (51) evaluated at the previous input z_{k-1} gives gamma^_k and
   the fault function f^_k = -B diag(u_k) gamma^_k (10). The paper's f^ in R^n is not
   observable from one current (rank 3 of 4); f lives in span(B), so the consequents are
   the per-actuator losses gamma and f^ is built from them.
2. UKF time update (32)-(43) with the fault term: x^- = A x^ + B u + f^ (35).
3. UKF measurement update (44)-(49) gives the innovation nu = y - y^- (the output error e
   of (20) between the plant and the fault model (53)) and its covariance S.
4. Consequent adaptation (28) per sample: a_j <- clip(a_j + r_j e xi_j, u_L, u_U), with e
   the innovation and the gain r_j = s_j M' S_tot^-1 a recursive-least-squares gain,
   where M = d y^/d gamma is the output sensitivity to the fault (carried through the
   filter by V = d x^/d gamma: V^- = A V - B diag(u), V = (I - K C) V^- + K D diag(u))
   and s_j is the consequent's variance, growing by q_gamma dt per second: the random-walk
   fault model (11), (14), (54). The paper's constant r is the special case s_j fixed;
   a constant r either reacts slowly or is noisy, while s_j shrinks as a consequent
   becomes well known and is re-opened by structure learning.
5. The state estimate is made consistent with the adapted fault: x^ += V (gamma^+ - gamma^)
   (the coupling of the two-stage filter, Hsieh & Chen 1999).
6. Fault-model state (52)-(53): x~_k = A x^_{k-1} + B u + f^_k (the paper's open-loop x~
   would integrate the process noise w, which no estimator knows, and drift without bound
   on the unobservable angle); the fuzzy input is x_e = x~ - x^ (50), normalised per state
   by its prior standard deviation so the membership functions are scale-free, and
   averaged over the same short window as the structure-learning test: one sample of x_e
   is mostly measurement noise, and rules switched by noise drift apart and make gamma^
   noisy; the average follows a persistent discrepancy, which is what a fault makes.
7. Structure learning (20)-(22): the paper's test |e| > 1e-5 on the raw current error fires
   every sample (noise sigma is 0.5 A). Here the error e is whitened (w = L^-1 nu with
   L L' = S_tot) and averaged exponentially over a short window; the average's chi-square
   statistic (p degrees of freedom when the model fits, at any sample rate) must exceed a
   threshold. Keeping the sign makes a persistent bias -- what a changed fault produces --
   far more visible than the squared NIS would. Then an MF is added on the input
   with the largest |z| at z (if the bound and the spacing allow), and the firing rules'
   variances are re-opened so that they learn fast, and the sensitivity V restarts at 0
   (the new fault has not yet acted on the state; keeping V would push x^ as if it had
   always been there). A dwell time separates two events.

A missed sample is a step with dt = k T: the ZOH model for that span holds the last
voltage, which is what the ECU does, and the covariance grows accordingly.

Any linear model runs (`monitor.estimation.model`: n states, m actuators, p outputs). Only
the actuators in `model.fault_inputs` have a loss of effectiveness; the others are known
inputs. They enter B and D like the rest, but their projection bounds of (28) are
[u_L, u_U] = [0, 0]: the kernel reads an actuator with equal bounds as known, so its gamma
stays exactly 0, its consequents carry no variance (they add nothing to S_tot), are never
adapted and are not re-opened by structure learning.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from monitor.estimation.fuzzy import FuzzyConfig, SelfConstructingFuzzySystem, fire, infer
from monitor.estimation.jit import njit
from monitor.estimation.model import DiscreteModel
from monitor.estimation.ukf import sigma_weights, spd_inverse, ukf_predict, ukf_update

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["KERNEL_LAYOUT", "EstimatorOutput", "FuzzyUKF", "FuzzyUKFConfig", "ManySteps",
           "select_kernel", "step_many"]

_log = logging.getLogger(__name__)

# Version of the kernel's flat-buffer layout; bump it whenever the meaning of the buffers
# changes (2: per-actuator bounds in prm). An ahead-of-time build of another layout has the
# same signature but would misread the buffers, so select_kernel refuses it.
KERNEL_LAYOUT = 2


def kernel_layout() -> int:
    """The buffer layout this kernel reads (exported into the AOT module as well)."""
    return KERNEL_LAYOUT


@dataclass(frozen=True)
class FuzzyUKFConfig:
    """Tuning of the fuzzy UKF. Defaults are those of the paper where it gives any.

    alpha, beta: sigma-point spread (34), paper 1e-4 and 2.
    q_gamma: random-walk intensity of each consequent, gamma^2 per second (54).
    var0: initial variance of the consequents (gamma^2).
    var_reopen: variance given to firing and new rules on a structure-learning event.
    var_max: cap on consequent variances (rules that never fire do not grow forever).
    nis_window: time constant of the innovation average, seconds.
    nis_threshold: structure-learning threshold on the chi-square statistic of the averaged
        whitened innovation (p degrees of freedom; 14 is 3.7 sigma for one output).
    dwell: minimum time between two structure-learning events, seconds.
    P0: initial state covariance (diagonal value). Without an x0 the first sample sets x^ to
        the fault-free steady state closest to it.
    """

    alpha: float = 1e-4
    beta: float = 2.0
    q_gamma: float = 5e-3
    var0: float = 0.05
    var_reopen: float = 0.05
    var_max: float = 0.25
    nis_window: float = 0.05
    nis_threshold: float = 14.0
    dwell: float = 0.2
    P0: float = 1.0
    fuzzy: FuzzyConfig = field(default_factory=FuzzyConfig)


@dataclass
class EstimatorOutput:
    """Result of one step. Arrays are overwritten by the next step: copy to keep them.

    x_hat: estimate of the observable states (model.observable_names); unobservable ones
    (the motor angle) are left out of the filter: they carry no information on the fault.
    x_tilde: fault-model state (52), observable part. x_e = x_tilde - x_hat_obs (50).
    gamma: loss of effectiveness per actuator (exactly 0 for an actuator not in
    model.fault_inputs). fault: f^ = -B diag(u) gamma (10), per state.
    y_hat: predicted output before the update; y_est: output of the final estimate,
    C x^ + D u (1 - gamma^). nis: normalised innovation squared.
    innovation: whitened innovation L^-1 nu (L L' = S_tot), per output. rules: rule count.
    """

    x_hat: Array
    x_tilde: Array
    x_e: Array
    gamma: Array
    fault: Array
    y_hat: Array
    innovation: Array
    y_est: Array
    nis: float = 0.0
    rules: int = 0
    structure_event: bool = False


@njit
def _fuzzy_ukf_step(
    mdl: Array, u: Array, y: Array, prm: Array, st: Array,
    centres: Array, counts: IntArray, cons: Array, var: Array, rule_idx: IntArray, rule_w: Array,
    wk: Array, out: Array, n: int, m: int, p: int, max_mf: int,
) -> None:
    """One sample of the fuzzy UKF on flat buffers (see FuzzyUKF for the layout).

    prm = [dt, delta, wi, q_gamma, var_max, nis_coef, lower[0..m), upper[0..m)]: the
    per-actuator bounds of (28); lower[a] == upper[a] marks a known actuator.
    """
    # ---- views into the flat buffers (slices and reshapes allocate nothing)
    o = 0
    A = mdl[o:o + n * n].reshape((n, n)); o += n * n
    B = mdl[o:o + n * m].reshape((n, m)); o += n * m
    Q = mdl[o:o + n * n].reshape((n, n)); o += n * n
    C = mdl[o:o + p * n].reshape((p, n)); o += p * n
    D = mdl[o:o + p * m].reshape((p, m)); o += p * m
    R = mdl[o:o + p * p].reshape((p, p))
    dt = prm[0]
    delta = prm[1]
    wi = prm[2]
    q_gamma = prm[3]
    var_max = prm[4]
    nis_coef = prm[5]
    # per-actuator projection bounds of (28); lo[a] == hi[a] marks a known actuator (no
    # loss of effectiveness): its consequents are fixed, carry no variance, never adapt
    lo = prm[6:6 + m]
    hi = prm[6 + m:6 + 2 * m]
    o = 0
    x = st[o:o + n]; o += n
    P = st[o:o + n * n].reshape((n, n)); o += n * n
    V = st[o:o + n * m].reshape((n, m)); o += n * m
    z = st[o:o + n]
    o = 0
    gamma = out[o:o + m]; o += m
    fhat = out[o:o + n]; o += n
    xtilde = out[o:o + n]; o += n
    xe = out[o:o + n]; o += n
    yhat = out[o:o + p]; o += p
    innov = out[o:o + p]; o += p
    stats = out[o:o + 3]; o += 3
    ebar = out[o:o + p]; o += p
    yest = out[o:o + p]
    o = 0
    uf = wk[o:o + m]; o += m
    b = wk[o:o + n]; o += n
    yoff = wk[o:o + p]; o += p
    d = wk[o:o + n]; o += n
    s = wk[o:o + n]; o += n
    dy = wk[o:o + p]; o += p
    nu = wk[o:o + p]; o += p
    xp = wk[o:o + n]; o += n
    dg = wk[o:o + m]; o += m
    tmp = wk[o:o + p]; o += p
    L = wk[o:o + n * n].reshape((n, n)); o += n * n
    Ls = wk[o:o + p * p].reshape((p, p)); o += p * p
    Pyy = wk[o:o + p * p].reshape((p, p)); o += p * p
    Pyy_inv = wk[o:o + p * p].reshape((p, p)); o += p * p
    Pxy = wk[o:o + n * p].reshape((n, p)); o += n * p
    K = wk[o:o + n * p].reshape((n, p)); o += n * p
    IKC = wk[o:o + n * n].reshape((n, n)); o += n * n
    T1 = wk[o:o + n * n].reshape((n, n)); o += n * n
    Pp = wk[o:o + n * n].reshape((n, n)); o += n * n
    Vp = wk[o:o + n * m].reshape((n, m)); o += n * m
    M = wk[o:o + p * m].reshape((p, m)); o += p * m
    St = wk[o:o + p * p].reshape((p, p)); o += p * p
    Sti = wk[o:o + p * p].reshape((p, p)); o += p * p
    G = wk[o:o + p].reshape((1, p))

    # 1. fuzzy output (51) at the previous input, fault function (10)
    nf = fire(z, centres, counts, max_mf, rule_idx, rule_w)
    infer(cons, rule_idx, rule_w, nf, gamma)
    for a in range(m):
        if not hi[a] > lo[a]:
            gamma[a] = lo[a]  # a known actuator: its gamma is fixed
        uf[a] = u[a] * (1.0 - gamma[a])
    for r in range(n):
        acc = 0.0
        f = 0.0
        for a in range(m):
            acc += B[r, a] * uf[a]
            f -= B[r, a] * u[a] * gamma[a]
        b[r] = acc
        fhat[r] = f
    for r in range(p):
        acc = 0.0
        for a in range(m):
            acc += D[r, a] * uf[a]
        yoff[r] = acc
    # 2. time update (35)-(43)
    rep = ukf_predict(x, P, A, b, Q, delta, wi, L, d, xp, Pp)
    for r in range(n):
        xtilde[r] = xp[r]  # fault-model state (52)
    # sensitivity of the prior to gamma: V^- = A V - B diag(u)
    for r in range(n):
        for a in range(m):
            acc = -B[r, a] * u[a]
            for c in range(n):
                acc += A[r, c] * V[c, a]
            Vp[r, a] = acc
    # 3. measurement update (44)-(49); x, P receive the posterior
    rep += ukf_update(xp, Pp, C, yoff, R, y, delta, wi, L, Ls, s, dy, Pyy, Pyy_inv, Pxy, K, nu,
                      x, P, IKC, T1)
    for r in range(p):
        acc = yoff[r]
        for c in range(n):
            acc += C[r, c] * xp[c]
        yhat[r] = acc
    # output sensitivity M = C V^- - D diag(u): nu ~ M (gamma - gamma^)
    for r in range(p):
        for a in range(m):
            acc = -D[r, a] * u[a]
            for c in range(n):
                acc += C[r, c] * Vp[c, a]
            M[r, a] = acc
    # 4. consequent adaptation (28): total innovation covariance
    for r in range(p):
        for c in range(p):
            acc = Pyy[r, c]
            for k in range(nf):
                w2 = rule_w[k] * rule_w[k]
                j = rule_idx[k]
                for a in range(m):
                    if hi[a] > lo[a]:
                        acc += w2 * var[j, a] * M[r, a] * M[c, a]
            St[r, c] = acc
    rep += spd_inverse(St, Ls, Sti)
    nis = 0.0
    for r in range(p):
        acc = 0.0
        for c in range(p):
            acc += Sti[r, c] * nu[c]
        tmp[r] = acc  # S_tot^-1 nu
        nis += nu[r] * acc
    for a in range(m):
        dg[a] = 0.0
    for k in range(nf):
        j = rule_idx[k]
        xi = rule_w[k]
        for a in range(m):
            if not hi[a] > lo[a]:
                continue
            # gain row g = var xi M[:, a]' S_tot^-1
            step = 0.0
            gm = 0.0
            for r in range(p):
                gr = 0.0
                for c in range(p):
                    gr += M[c, a] * Sti[c, r]
                G[0, r] = var[j, a] * xi * gr
                step += G[0, r] * nu[r]
                gm += G[0, r] * M[r, a]
            old = cons[j, a]
            new = old + step
            if new < lo[a]:
                new = lo[a]
            elif new > hi[a]:
                new = hi[a]
            cons[j, a] = new
            dg[a] += xi * (new - old)
            var[j, a] = var[j, a] * (1.0 - gm * xi)
    # random walk (54) on every consequent of a fault actuator, capped
    grow = q_gamma * dt
    for j in range(cons.shape[0]):
        for a in range(m):
            if hi[a] > lo[a]:
                v = var[j, a] + grow
                var[j, a] = v if v < var_max else var_max
    # 5. two-stage coupling: V = (I - K C) V^- + K D diag(u); x^ += V dgamma
    for r in range(n):
        for a in range(m):
            acc = 0.0
            for c in range(n):
                acc += IKC[r, c] * Vp[c, a]
            for c in range(p):
                acc += K[r, c] * D[c, a] * u[a]
            V[r, a] = acc
    for r in range(n):
        acc = 0.0
        for a in range(m):
            acc += V[r, a] * dg[a]
        x[r] += acc
    for a in range(m):
        # a convex combination of bounded consequents, up to one ulp of round-off
        g = gamma[a] + dg[a]
        gamma[a] = lo[a] if g < lo[a] else (hi[a] if g > hi[a] else g)
    # posterior output estimate y^ = C x^ + D u (1 - gamma^)
    for r in range(p):
        acc = 0.0
        for c in range(n):
            acc += C[r, c] * x[c]
        for a in range(m):
            acc += D[r, a] * u[a] * (1.0 - gamma[a])
        yest[r] = acc
    # 6. fuzzy input x_e = x~ - x^ (50), normalised by the prior standard deviation and
    # averaged exponentially
    for r in range(n):
        xe[r] = xtilde[r] - x[r]
        sd = math.sqrt(Pp[r, r]) if Pp[r, r] > 0.0 else 1.0
        z[r] += nis_coef * (xe[r] / sd - z[r])
    # whitened innovation w = L^-1 nu with L L' = S_tot (Ls holds that factor)
    for r in range(p):
        acc = nu[r]
        for c in range(r):
            acc -= Ls[r, c] * innov[c]
        innov[r] = acc / Ls[r, r]
    # 7. statistics for structure learning: an exponentially weighted mean of the whitened
    # innovation; under a fitting model it is N(0, c/(2-c) I), so the statistic below is
    # chi-square with p degrees of freedom whatever the sample rate.
    chi = 0.0
    for r in range(p):
        ebar[r] += nis_coef * (innov[r] - ebar[r])
        chi += ebar[r] * ebar[r]
    stats[0] = nis
    stats[1] = chi * (2.0 - nis_coef) / nis_coef
    stats[2] += rep


def select_kernel(choice: str | None = None) -> tuple[str, Callable[..., None]]:
    """The step kernel to run: ("jit" | "aot" | "python", function).

    MOTOR_MONITOR_KERNEL=jit|aot|python forces one; by default the numba JIT is used
    unless NUMBA_DISABLE_JIT is set (the hardened service forbids W+X memory), in which
    case the ahead-of-time build (`python -m monitor.estimation.kernels_aot`) is used if
    present, and the same code interpreted (about 40x slower) otherwise.
    """
    want = (choice or os.environ.get("MOTOR_MONITOR_KERNEL", "auto")).strip().lower()
    jit_off = os.environ.get("NUMBA_DISABLE_JIT", "0") not in ("", "0")
    if want in ("aot", "auto") and (want == "aot" or jit_off):
        try:
            from monitor.estimation import _fuzzy_ukf_aot  # type: ignore[attr-defined]

            layout = getattr(_fuzzy_ukf_aot, "kernel_layout", lambda: 1)()
            if layout != KERNEL_LAYOUT:
                raise ImportError(f"the AOT kernel reads buffer layout {layout}, this code "
                                  f"writes layout {KERNEL_LAYOUT}: rebuild it (python -m "
                                  "monitor.estimation.kernels_aot)")
            return "aot", _fuzzy_ukf_aot.fuzzy_ukf_step
        except ImportError as exc:
            if want == "aot":
                raise
            _log.warning("JIT disabled and no usable AOT kernel (%s): the estimator runs "
                         "interpreted", exc)
    if want == "python":
        return "python", getattr(_fuzzy_ukf_step, "py_func", _fuzzy_ukf_step)
    return ("python" if jit_off else "jit"), _fuzzy_ukf_step


def _work_size(n: int, m: int, p: int) -> int:
    return 2 * m + 5 * n + 5 * p + 5 * n * n + 5 * p * p + 2 * n * p + n * m + p * m + n * n


class FuzzyUKF:
    """Self-constructing fuzzy UKF fault estimator for one motor (one object per motor).

    >>> est = FuzzyUKF(dc_motor().discretize(0.01))
    >>> out = est.step(u=[220.0], y=[67.7], dt=0.01)
    >>> out.gamma, out.rules, out.nis

    State, outputs and work space live in flat float64 buffers allocated once; `x`, `P`,
    `V` and the arrays of `out` are views into them, so a step allocates nothing.
    """

    def __init__(
        self,
        model: DiscreteModel,
        config: FuzzyUKFConfig | None = None,
        x0: Sequence[float] | None = None,
    ) -> None:
        cfg = config or FuzzyUKFConfig()
        self.model = model
        self.config = cfg
        n, m, p = model.n, model.m, model.p
        self._dims = (n, m, p)
        w = sigma_weights(n, cfg.alpha, cfg.beta)
        self.fuzzy = SelfConstructingFuzzySystem(n, m, cfg.fuzzy, 0.0, cfg.var0)
        # Actuators without a loss of effectiveness (not in model.fault_inputs) get the
        # bounds [0, 0]: their gamma stays exactly 0 and the kernel leaves them out.
        self._known = [a for a in range(m) if a not in model.fault_inputs]
        lower = np.full(m, cfg.fuzzy.lower)
        upper = np.full(m, cfg.fuzzy.upper)
        lower[self._known] = 0.0
        upper[self._known] = 0.0
        self.fuzzy.var[:, self._known] = 0.0
        self._prm = np.concatenate([[0.0, w.delta, w.wi, cfg.q_gamma, cfg.var_max, 0.0],
                                    lower, upper])
        self._st = np.zeros(2 * n + n * n + n * m)
        self.x = self._st[:n]
        self.P = self._st[n:n + n * n].reshape(n, n)
        self.V = self._st[n + n * n:n + n * n + n * m].reshape(n, m)
        self.z = self._st[n + n * n + n * m:]
        if x0 is not None:
            x0a = np.asarray(x0, dtype=float)
            if x0a.shape == (model.n_full,):
                self.x[:] = model.Wobs @ x0a
            elif x0a.shape == (n,):
                self.x[:] = x0a
            else:
                raise ValueError(f"x0 must have {model.n_full} (full) or {n} (observable) entries")
        self.P[:] = np.eye(n) * cfg.P0
        self._needs_init = x0 is None
        self._wk = np.zeros(_work_size(n, m, p))
        self._out = np.zeros(m + 3 * n + 4 * p + 3)
        ob = self._out
        self._stats = ob[m + 3 * n + 2 * p:m + 3 * n + 2 * p + 3]
        self._ebar = ob[m + 3 * n + 2 * p + 3:m + 3 * n + 3 * p + 3]
        self.out = EstimatorOutput(
            x_hat=self.x,
            x_tilde=ob[m + n:m + 2 * n],
            x_e=ob[m + 2 * n:m + 3 * n],
            gamma=ob[:m],
            fault=ob[m:m + n],
            y_hat=ob[m + 3 * n:m + 3 * n + p],
            innovation=ob[m + 3 * n + p:m + 3 * n + 2 * p],
            y_est=ob[m + 3 * n + 3 * p + 3:],
            rules=self.fuzzy.rule_count,
        )
        self._u = np.zeros(m)
        self._y = np.zeros(p)
        self._blocks: dict[float, tuple[Array, float]] = {}
        self.kernel_name, self._kernel = _KERNEL
        self._time = 0.0
        self._last_event = -math.inf
        self.steps = 0
        self.structure_events = 0

    def _block(self, dt: float) -> tuple[Array, float]:
        """Model matrices for a step of dt packed flat, and the NIS averaging coefficient."""
        A, B, Q = self.model.at(dt)
        md = self.model
        blk = np.concatenate([A.ravel(), B.ravel(), Q.ravel(), md.C.ravel(), md.D.ravel(),
                              md.R.ravel()])
        entry = (blk, 1.0 - math.exp(-dt / self.config.nis_window))
        if len(self._blocks) > 1024:  # jittered dt must not grow memory forever
            self._blocks.clear()
        self._blocks[dt] = entry
        return entry

    @property
    def repairs(self) -> int:
        """Cholesky pivots clamped so far (0 in a healthy run)."""
        return int(self._stats[2])

    @property
    def rule_count(self) -> int:
        return self.out.rules

    def step(self, u: Sequence[float] | Array | float, y: Sequence[float] | Array | float,
             dt: float) -> EstimatorOutput:
        """Process one sample; dt is the time since the previous sample (k T if missed)."""
        if not dt > 0.0:
            raise ValueError(f"dt must be positive, got {dt}")
        uu = self._u
        yy = self._y
        uu[:] = u
        yy[:] = y
        if self._needs_init:
            self._init_from_sample(uu, yy)
        blk = self._blocks.get(dt)
        if blk is None:
            blk = self._block(dt)
        prm = self._prm
        prm[0] = dt
        prm[5] = blk[1]
        fz = self.fuzzy
        n, m, p = self._dims
        self._kernel(blk[0], uu, yy, prm, self._st, fz.centres, fz.counts, fz.cons, fz.var,
                     fz.rule_idx, fz.rule_w, self._wk, self._out, n, m, p, fz.max_mf)
        self._time += dt
        self.steps += 1
        out = self.out
        stats = self._stats
        if stats[1] > self.config.nis_threshold and self._time - self._last_event >= \
                self.config.dwell:
            self._structure_event()
            out.structure_event = True
            out.rules = fz.rule_count
        else:
            out.structure_event = False
        out.nis = stats[0]
        return out

    def _init_from_sample(self, u: Array, y: Array) -> None:
        """x^(0) without a given x0: the fault-free steady state closest to the first sample.

        Least squares on [I - A; C] x = [B u; y - D u]: a monitor attached to a running
        motor would otherwise start from x = 0 and read its own convergence as a fault.
        """
        self._needs_init = False
        A, B, _ = self.model.at(self.model.T)
        md = self.model
        M = np.vstack([np.eye(self._dims[0]) - A, md.C])
        rhs = np.concatenate([B @ u, y - md.D @ u])
        x, *_ = np.linalg.lstsq(M, rhs, rcond=None)
        if np.all(np.isfinite(x)):
            self.x[:] = x

    def _structure_event(self) -> None:
        """(20)-(22): add an MF where the evidence is, and re-open every consequent.

        The evidence says the fault has changed, and an actuator's loss of effectiveness
        is not a function of x_e, so no rule's old consequent is worth keeping: all are
        set to the current output (so f^ does not jump, the intent of (23)-(27)) with a
        re-opened variance, and then learn together. The new MF is output-preserving.
        """
        self._last_event = self._time
        self.structure_events += 1
        self._ebar[:] = 0.0  # one change, one event
        # V = d x^ / d gamma accumulates the effect of a gamma error held since the start;
        # a detected change starts a new one, whose effect on the state begins now.
        self.V[:] = 0.0
        fz = self.fuzzy
        cfg = self.config
        fz.cons[:] = self.out.gamma
        np.maximum(fz.var, cfg.var_reopen, out=fz.var)
        v = int(np.argmax(np.abs(self.z)))
        fz.insert(v, float(self.z[v]), cfg.var_reopen)
        fz.var[:, self._known] = 0.0  # known actuators have nothing to learn


_KERNEL = select_kernel()


# ----------------------------------------------------------------------------- many samples


@njit
def _fuzzy_ukf_loop(
    blocks: Array, coefs: Array, bidx: IntArray, dts: Array, U: Array, Y: Array, prm: Array,
    st: Array, centres: Array, counts: IntArray, cons: Array, var: Array, rule_idx: IntArray,
    rule_w: Array, wk: Array, out: Array, n: int, m: int, p: int, max_mf: int,
    clock: Array, nis_threshold: float, dwell: float, start: int,
    gamma_out: Array, yest_out: Array, nis_out: Array,
) -> int:
    """`_fuzzy_ukf_step` -- eqs (50)-(54) around (15)-(49), see the module docstring -- for
    samples start, start + 1, ... of (U, Y, dts), in compiled code.

    Sample i runs with model block ``blocks[bidx[i]]`` (the ZOH model (63)-(65) for its
    dt) and NIS coefficient ``coefs[bidx[i]]``, exactly what `FuzzyUKF.step` passes. clock =
    [time, time of the last structure event]. Stops after the first sample that needs
    Python: a structure-learning event (20)-(22) is due (clock[2] = 1) or gamma^ is NaN
    (clock[2] = 2); returns the index after the last sample run.
    """
    o_stats = m + 3 * n + 2 * p
    o_yest = m + 3 * n + 3 * p + 3
    N = U.shape[0]
    clock[2] = 0.0
    for i in range(start, N):
        b = bidx[i]
        prm[0] = dts[i]
        prm[5] = coefs[b]
        _fuzzy_ukf_step(blocks[b], U[i], Y[i], prm, st, centres, counts, cons, var, rule_idx,
                        rule_w, wk, out, n, m, p, max_mf)
        clock[0] += dts[i]
        nan = False
        for a in range(m):
            gamma_out[i, a] = out[a]
            if out[a] != out[a]:
                nan = True
        for r in range(p):
            yest_out[i, r] = out[o_yest + r]
        nis_out[i] = out[o_stats]
        if out[o_stats + 1] > nis_threshold and clock[0] - clock[1] >= dwell:
            clock[2] = 1.0
            return i + 1
        if nan:
            clock[2] = 2.0
            return i + 1
    return N


@dataclass
class ManySteps:
    """What `step_many` ran: samples [0, count) of its input, per sample gamma^ (count, m),
    the output estimate y_est (count, p), the NIS, the rule count after the sample and
    whether a structure-learning event followed it. `stopped_on_nan`: sample count - 1 gave a
    NaN gamma^ (the caller restarts the estimator, as the pipeline does)."""

    count: int
    gamma: Array
    y_est: Array
    nis: Array
    rules: IntArray
    structure_event: NDArray[np.bool_]
    stopped_on_nan: bool


def step_many(est: FuzzyUKF, u: Array, y: Array, dt: Array) -> ManySteps:
    """`est.step(u[i], y[i], dt[i])` for every row i, with the same results, the samples
    stepped in one compiled loop (`_fuzzy_ukf_loop`: the same kernel, eqs (50)-(54) around
    (15)-(49)) that returns to Python only for a structure-learning event (20)-(22) and
    stops at a NaN gamma^. Without the JIT (AOT or interpreted kernel) it calls `est.step`
    row by row. Leaves `est` as the last `step` would, `est.out` included.
    """
    N = int(u.shape[0])
    n, m, p = est._dims
    gamma = np.zeros((N, m))
    y_est = np.zeros((N, p))
    nis = np.zeros(N)
    rules = np.zeros(N, np.int64)
    event = np.zeros(N, np.bool_)
    if N == 0:
        return ManySteps(0, gamma, y_est, nis, rules, event, False)
    if np.any(~(dt > 0.0)):
        raise ValueError(f"dt must be positive, got {dt[~(dt > 0.0)][0]}")
    if est.kernel_name != "jit":
        for i in range(N):
            out = est.step(u[i], y[i], float(dt[i]))
            gamma[i] = out.gamma
            y_est[i] = out.y_est
            nis[i] = out.nis
            rules[i] = out.rules
            event[i] = out.structure_event
            if out.gamma.max() != out.gamma.max():
                return ManySteps(i + 1, gamma, y_est, nis, rules, event, True)
        return ManySteps(N, gamma, y_est, nis, rules, event, False)
    U = np.ascontiguousarray(u, dtype=np.float64)
    Y = np.ascontiguousarray(y, dtype=np.float64)
    dts = np.ascontiguousarray(dt, dtype=np.float64)
    if est._needs_init:
        est._u[:] = U[0]
        est._y[:] = Y[0]
        est._init_from_sample(est._u, est._y)
    uniq, inv = np.unique(dts, return_inverse=True)
    entries = []
    for d in uniq.tolist():
        blk = est._blocks.get(d)
        entries.append(blk if blk is not None else est._block(d))
    blocks = np.ascontiguousarray(np.stack([e[0] for e in entries]))
    coefs = np.array([e[1] for e in entries])
    bidx = inv.astype(np.int64).reshape(-1)
    clock = np.array([est._time, est._last_event, 0.0])
    fz = est.fuzzy
    cfg = est.config
    i = 0
    nan = False
    while i < N:
        start = i
        i = _fuzzy_ukf_loop(blocks, coefs, bidx, dts, U, Y, est._prm, est._st, fz.centres,
                            fz.counts, fz.cons, fz.var, fz.rule_idx, fz.rule_w, est._wk,
                            est._out, n, m, p, fz.max_mf, clock, cfg.nis_threshold, cfg.dwell,
                            start, gamma, y_est, nis)
        rules[start:i] = est.out.rules
        est.steps += i - start
        est._time = float(clock[0])
        est.out.structure_event = False
        if clock[2] == 1.0:  # the event follows sample i - 1, as in step()
            est._structure_event()
            est.out.structure_event = True
            est.out.rules = fz.rule_count
            rules[i - 1] = est.out.rules
            event[i - 1] = True
            clock[1] = est._last_event
            if gamma[i - 1].max() != gamma[i - 1].max():
                nan = True
        elif clock[2] == 2.0:
            nan = True
        if nan:
            break
    est.out.nis = float(nis[i - 1])
    est._u[:] = U[i - 1]
    est._y[:] = Y[i - 1]
    return ManySteps(i, gamma, y_est, nis, rules, event, nan)
