"""The self-constructing fuzzy UKF fault estimator, eqs (50)-(54) around (15)-(49).

One `FuzzyUKF` per motor takes one sample (u, y, dt) at a time and returns the state
estimate x^, the fault-model state x~, the loss of effectiveness gamma^, the fault
function f^ = -B diag(u) gamma^, the rule count and the normalised innovation (Liu, Bao,
Xue, Du, "Fault Estimator and Diagnosis for Generalized Linear Discrete-Time System via
Self-constructing Fuzzy UKF Method", Int. J. Fuzzy Systems 22(1), 2020). This module is the
object API: the configuration, the output and the estimator's state. The method is in the
modules of `monitor.estimation`, each with the paper's equations it implements:

* `kernel`: one sample, steps 1-7 -- the fuzzy output (17), (51) and the fault function
  (10), the UKF time update (32)-(43) and measurement update (44)-(49), the random walk of
  the fault (11), (14), (54), the structure-learning test (20), 5b the adaptive output
  noise, the consequent adaptation (28) with the two-stage coupling, and the fault-model
  state (52)-(53) with the fuzzy input x_e (50) -- compiled, on the flat buffers of
  `layout`; `select_kernel` picks the JIT, the AOT build or the interpreted code.
* `structure`: what a structure event (20)-(22) does -- the onset of the change, the
  samples since processed again, a new membership function (`fuzzy`, (15)-(29)).
* `bias`: step 8, the bias states (a load or an offset the model lacks).
* `friction`: the model's Coulomb friction, a known input of step 2 from the model's own
  speed (our extension, like the bias states).
* `start`: the initial covariance and the start without an x0.
* `many`: `FuzzyUKF.step_many`, many samples in one compiled loop.
* `ukf`: the sigma points and the UKF (30)-(49); `fuzzy`: the rule base (15)-(29).

Why it is built this way -- what failed on a small, stiff, back-EMF dominated motor (a
24 V servo at 1 kHz: J = 2e-5, b = 1e-5, Ke = Ki = 0.03, Ra = 1, La = 1e-3, sensor sigma
0.01 A) while the paper's motor worked -- is in the docstrings of the parts it concerns:
(a), (b), (g) in `structure`, (c)-(e) in `kernel`, (f), (h) in `start`.

Any linear model runs (`monitor.estimation.model`: n states, m actuators, p outputs). Only
the actuators in `model.fault_inputs` have a loss of effectiveness; the others are known
inputs, with the projection bounds [0, 0] of (28): their gamma stays exactly 0.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from monitor.estimation.bias import augmented_matrices
from monitor.estimation.friction import friction_code, speed_row
from monitor.estimation.fuzzy import FuzzyConfig, SelfConstructingFuzzySystem
from monitor.estimation.kernel import select_kernel
from monitor.estimation.layout import (
    FRICTION,
    KERNEL_LAYOUT,
    MODEL,
    OUT,
    PRM,
    RING,
    STATE,
    WORK,
    offsets,
)
from monitor.estimation.many import ManyStepping, ManySteps
from monitor.estimation.model import (
    BIAS_WINDOW_S,
    ESTIMATOR_LIMIT_BYTES,
    DiscreteModel,
    ModelError,
    estimator_bytes,
)
from monitor.estimation.start import (
    StartState,
    initial_covariance,
    initial_covariance_of,
    start_state,
    steady_start,
)
from monitor.estimation.structure import StructureLearning
from monitor.estimation.ukf import sigma_weights

Array = NDArray[np.float64]

# the estimator's names, importable from here as the rest of the monitor does
__all__ = [
    "KERNEL_LAYOUT",
    "EstimatorOutput",
    "FuzzyUKF",
    "FuzzyUKFConfig",
    "ManySteps",
    "StartState",
    "initial_covariance",
    "select_kernel",
    "start_state",
    "steady_start",
]


@dataclass(frozen=True)
class FuzzyUKFConfig:
    """Tuning of the fuzzy UKF. Defaults are those of the paper where it gives any.

    alpha, beta: sigma-point spread (34), paper 1e-4 and 2.
    q_gamma: random-walk intensity of the loss of effectiveness, gamma^2 per second (54),
        on the part of the consequents common to all rules.
    growth_share: cap on that growth per second, as a share of the information a sample
        gives on gamma (M' P_yy^-1 M): keeps gamma's share of the innovation covariance
        near sqrt(growth_share dt), so that the NIS stays calibrated at any scale. The
        growth is also at most twice what the sample's evidence takes away, so that a
        sample which shows nothing of gamma widens nothing (`kernel`, (f)).
    var0: initial variance of the common part of the consequents (gamma^2).
    var_reopen: the same on a structure-learning event.
    var_rule: variance of each rule's own part, initially and on an event (small: the
        loss of effectiveness does not depend on x_e much).
    var_start: initial variance of the common part after a start from the first output
        (`start_state`, when the steady state of the first input does not explain it):
        small, so that the start-up transient goes to the widely uncertain state and not
        to gamma^; a fault present from the start is found by the structure test (20).
    var_max: cap on the common variance.
    nis_window: time constant of the innovation average, seconds.
    nis_threshold: structure-learning threshold on the chi-square statistic of the averaged
        whitened innovation (p degrees of freedom; 14 is 3.7 sigma for one output).
    slow_window: time constant of a second, slower innovation average beside it, seconds
        (0: none): a change whose effect on the outputs grows over many samples (a slow
        plant, a loss at a low input) shows a mean shift of about one noise unit a sample,
        which no window of the short average holds long enough to cross its threshold.
    slow_threshold: the threshold of that average's statistic (chi-square as the short
        one's).
    slow_min_jump: the least jump of gamma, located at the onset as for every event, less
        its posterior standard deviation, that the slow average alone may start an event
        with: a model that fits a little less than perfectly (a gain off by a few per cent,
        friction, a saturation the linear model averages) also shifts the innovations' mean
        by a fraction of a noise unit, and its located jump is small or uncertain; a loss
        worth re-learning gamma for is neither.
    dwell: minimum time between two structure-learning events, seconds.
    onset_window: how far back, in seconds, an event looks for the onset of the change.
    min_jump: a located jump of gamma smaller than this after the bounds of (28) is not
        a structure event.
    max_onsets: above this many samples in the onset window the onset search is
        two-stage (a coarse grid, then around its best), which bounds its cost to
        O(window (max_onsets + 2 window / max_onsets)) instead of O(window^2).
    P0: initial state covariance: None, the stationary Kalman covariance (in the state's
        own units); a number, that value on the diagonal. Without an x0 the filter starts
        from what its first output says (`start_state`), this covariance being the floor
        of the start's.
    adaptive_noise: learn the output noise from the innovations (step 5b of the module
        docstring): R + diag(rx), rx >= 0, so never below the model's R.
    noise_window: time constant of that learning, seconds (per received sample, like
        nis_window): much longer than the classifier's dwell and the onset window, so a
        fault -- a mean shift that gamma^ explains within them -- moves R little.
    process_noise_gain: how fast the process noise is learnt from the innovations (step 5c
        of `monitor.estimation.kernel`), in units of the output noise's learning weight
        (0: the model's Q): Q's plant part is scaled by exp(qs) >= 1, qs moving by this
        times that weight times the whitened innovations' clipped product with the
        previous sample's. 4: a process noise five times the model's is learnt within
        about 10 s on the paper's motor at 100 Hz (a time constant of noise_window /
        (gain x ~0.08), the last factor how the innovations' correlation answers Q's
        scale there), and a fitting model's scale wanders between 1 and about 1.6.
    bias: slowly varying bias states beside the plant's (step 8 of the module docstring):
        "output" (an offset per output), "input" (a load or offset per actuator), "auto"
        (output where observable, else input, else none) or "none"
        (`DiscreteModel.bias_plan`; an explicit kind the outputs cannot observe is refused).
    bias_window: seconds over which a bias follows a slow drift (its random walk); a
        step is taken at once by a bias event (step 8). Long, so that the bound of gamma^
        does not lift gamma^ on a healthy plant through the bias.
    """

    alpha: float = 1e-4
    beta: float = 2.0
    q_gamma: float = 5e-3
    var0: float = 0.05
    var_reopen: float = 0.05
    var_max: float = 0.25
    var_rule: float = 1e-4
    var_start: float = 1e-4
    nis_window: float = 0.05
    nis_threshold: float = 14.0
    slow_window: float = 0.2
    slow_threshold: float = 14.0
    slow_min_jump: float = 0.1
    dwell: float = 0.2
    growth_share: float = 0.5
    onset_window: float = 0.2
    min_jump: float = 0.01
    max_onsets: int = 24
    P0: float | None = None
    adaptive_noise: bool = True
    noise_window: float = 2.0
    process_noise_gain: float = 4.0
    bias: str = "auto"
    bias_window: float = BIAS_WINDOW_S
    fuzzy: FuzzyConfig = field(default_factory=FuzzyConfig)


@dataclass
class EstimatorOutput:
    """Result of one step. Arrays are overwritten by the next step: copy to keep them.

    x_hat: estimate of the observable states (model.observable_names); unobservable ones
    (the motor angle) are left out of the filter: they carry no information on the fault.
    x_tilde: fault-model state (52), observable part. x_e = x_tilde - x_hat_obs (50).
    gamma: loss of effectiveness per actuator (exactly 0 for an actuator not in
    model.fault_inputs). fault: f^ = -B diag(u) gamma (10), per state.
    gamma_sd: the standard deviation of gamma^ after the sample (the square root of its
    variance, the consequents' common part and the firing rules' own; 0 for a known
    actuator): how far the diagnosis trusts gamma^ (`monitor.diagnosis.rules.cls_update`).
    y_hat: predicted output before the update; y_est: output of the final estimate,
    C x^ + D u (1 - gamma^). nis: normalised innovation squared.
    innovation: whitened innovation L^-1 nu (L L' = S_tot), per output. rules: rule count.
    bias: the estimated bias states (`FuzzyUKF.bias_plan`; empty without).
    output_noise: per output, the output-noise variance the filter has adapted to (step 5b
    of `monitor.estimation.kernel`, R + diag(rx)) as a multiple of the model's R_ii (1: the
    model's noise fits, or R_ii is 0). process_noise: the factor on the plant's part of
    the model's Q (step 5c; one entry; 1 to 100: far above 1, the model misses dynamics,
    and the state takes up more of a loss of effectiveness, which gamma^ then shows less).
    Both after the sample's adaptation: the noises the next sample is filtered with.
    """

    x_hat: Array
    x_tilde: Array
    x_e: Array
    gamma: Array
    fault: Array
    y_hat: Array
    innovation: Array
    y_est: Array
    gamma_sd: Array = field(default_factory=lambda: np.zeros(0))
    bias: Array = field(default_factory=lambda: np.zeros(0))
    output_noise: Array = field(default_factory=lambda: np.zeros(0))
    process_noise: Array = field(default_factory=lambda: np.ones(1))
    nis: float = 0.0
    rules: int = 0
    structure_event: bool = False


class FuzzyUKF(StructureLearning, ManyStepping):
    """Self-constructing fuzzy UKF fault estimator for one motor (one object per motor).

    >>> est = FuzzyUKF(dc_motor().discretize(0.01))
    >>> out = est.step(u=[220.0], y=[67.7], dt=0.01)
    >>> out.gamma, out.rules, out.nis

    State, outputs and work space live in flat float64 buffers allocated once; `x`, `P`,
    `V` and the arrays of `out` are views into them, so a step allocates nothing (a
    structure event, a few per fault change, re-processes the samples since its onset).
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
        # the filter's state: the plant's observable states, then the bias states (step 8)
        self.bias_plan = model.bias_plan(cfg.bias, cfg.bias_window)
        nx, m, p = model.n, model.m, model.p
        n = nx + self.bias_plan.count
        self._nx = nx
        self._dims = (n, m, p)
        # the model check sized the default estimator with the same rule; a configuration
        # with more MFs, a longer onset window or bias states is sized again here, before
        # allocating (the rule base spans the plant's states, the ring the filter's)
        rules, _ = estimator_bytes(nx, m, p, model.T, max_mf=cfg.fuzzy.max_mf,
                                   onset_window=cfg.onset_window)
        _, ring = estimator_bytes(n, m, p, model.T, max_mf=cfg.fuzzy.max_mf,
                                  onset_window=cfg.onset_window)
        need = rules + ring
        if need > ESTIMATOR_LIMIT_BYTES:
            raise ModelError(f"the estimator of {n} observable states at {1.0 / model.T:g} Hz "
                             f"would need {need / 2**30:.3g} GiB a node (at most "
                             f"{ESTIMATOR_LIMIT_BYTES / 2**30:g}): fewer MFs (max_mf) or a "
                             "shorter onset window")
        w = sigma_weights(n, cfg.alpha, cfg.beta)
        self.fuzzy = SelfConstructingFuzzySystem(nx, m, cfg.fuzzy, 0.0, cfg.var_rule)
        # Actuators without a loss of effectiveness (not in model.fault_inputs) get the
        # bounds [0, 0]: their gamma stays exactly 0 and the kernel leaves them out.
        self._known = [a for a in range(m) if a not in model.fault_inputs]
        self._faulty = [a for a in range(m) if a in model.fault_inputs]
        lower = np.full(m, cfg.fuzzy.lower)
        upper = np.full(m, cfg.fuzzy.upper)
        lower[self._known] = 0.0
        upper[self._known] = 0.0
        self.fuzzy.var[:, self._known] = 0.0
        # one weight per received sample, as the innovation average's (`_block`)
        noise_coef = (1.0 - math.exp(-model.T / cfg.noise_window)) if cfg.adaptive_noise \
            else 0.0
        # the flat buffers (`monitor.estimation.layout`); every view below is one of them
        self._lay = offsets(n, m, p)
        self._prm = np.zeros(PRM.size(n, m, p))
        for name, value in (("delta", w.delta), ("wi", w.wi), ("q_gamma", cfg.q_gamma),
                            ("var_max", cfg.var_max), ("var_reopen", cfg.var_reopen),
                            ("nis_threshold", cfg.nis_threshold),
                            ("growth_share", cfg.growth_share), ("var_rule", cfg.var_rule),
                            ("lower", lower), ("upper", upper), ("noise_coef", noise_coef),
                            ("slow_ratio", cfg.nis_window / cfg.slow_window
                             if cfg.slow_window > 0.0 else 0.0),
                            ("slow_threshold", cfg.slow_threshold),
                            ("process_coef", cfg.process_noise_gain * noise_coef)):
            PRM.view(self._prm, name, n, m, p)[:] = value
        self._lower = PRM.view(self._prm, "lower", n, m, p)
        self._upper = PRM.view(self._prm, "upper", n, m, p)
        self._i_dt, self._i_coef, self._i_mode, self._i_slot = (
            PRM.span(f, n, m, p)[0] for f in ("dt", "nis_coef", "mode", "slot"))
        # the state, then the onset ring (one slot per sample)
        head = STATE.size(n, m, p)
        self._ring_len = max(2, math.ceil(cfg.onset_window / model.T) + 1)
        slot = RING.size(n, m, p)
        self._st = np.zeros(head + self._ring_len * slot)
        self.x = STATE.view(self._st, "x", n, m, p)
        self.P = STATE.view(self._st, "P", n, m, p)
        self.V = STATE.view(self._st, "V", n, m, p)
        self._zall = STATE.view(self._st, "z", n, m, p)
        self.z = self._zall[:nx]  # the fuzzy input: the plant's part
        self.bias = self.x[nx:]  # the bias states (step 8)
        self._bias_var0 = self.bias_plan.var0
        self.common_var = STATE.view(self._st, "vc", n, m, p)
        self.noise_excess = STATE.view(self._st, "rx", n, m, p)  # R + diag(rx): output noise
        # exp(qs) Q on the plant's states: the process noise (step 5c)
        self._process_log_scale = STATE.view(self._st, "qs", n, m, p)
        self._w_prev = STATE.view(self._st, "w_prev", n, m, p)
        self._w_mean = STATE.view(self._st, "w_mean", n, m, p)
        self.common_var[self._faulty] = cfg.var0
        self._ring = self._st[head:].reshape(self._ring_len, slot)
        self._ring_spans = {f: RING.span(f, n, m, p) for f in RING.names}
        if x0 is not None:
            x0a = np.asarray(x0, dtype=float)
            if x0a.shape == (model.n_full,):
                self.x[:nx] = model.Wobs @ x0a
            elif x0a.shape == (nx,):
                self.x[:nx] = x0a
            else:
                raise ValueError(f"x0 must have {model.n_full} (full) or {nx} (observable) "
                                 "entries")
        self.P[:nx, :nx] = initial_covariance_of(model) if cfg.P0 is None \
            else np.eye(nx) * cfg.P0
        self.P[nx:, nx:] = np.diag(self.bias_plan.var_start)
        self._needs_init = x0 is None
        self._wk = np.zeros(WORK.size(n, m, p))
        self._out = np.zeros(OUT.size(n, m, p))

        def out(name: str) -> Array:
            return OUT.view(self._out, name, n, m, p)

        self._stats = out("stats")
        self._ebar = out("ebar")
        self._ebar_slow = out("ebar_slow")
        self._gamma_slow = out("gamma_slow")
        self._var_slow = out("var_slow")
        # the model's noises until a sample has adapted them (the kernel writes the factors
        # after every sample; a start from the first output runs no kernel)
        out("output_noise")[:] = 1.0
        out("process_noise")[:] = 1.0
        self.out = EstimatorOutput(
            x_hat=self.x[:nx],
            x_tilde=out("x_tilde")[:nx],
            x_e=out("x_e")[:nx],
            gamma=out("gamma"),
            fault=out("fault")[:nx],
            y_hat=out("y_hat"),
            innovation=out("innovation"),
            y_est=out("y_est"),
            gamma_sd=out("gamma_sd"),
            rules=self.fuzzy.rule_count,
            bias=self.bias,
            output_noise=out("output_noise"),
            process_noise=out("process_noise"),
        )
        self._u = np.zeros(m)
        self._y = np.zeros(p)
        self._blocks: dict[float, tuple[Array, float]] = {}
        self.kernel_name, self._kernel = _KERNEL
        self._time = 0.0
        self._last_event = -math.inf
        self._onset_floor = 0  # no onset before the previous event's
        self._faulty_idx = np.array(self._faulty, dtype=np.int64)
        self.steps = 0
        self.structure_events = 0
        self.bias_events = 0  # changes of a load or an offset (step 8)
        self._bias_armed_until = -math.inf  # a first sight of one waits for a second

    def _block(self, dt: float) -> tuple[Array, float]:
        """Model matrices for a step of dt packed flat, and the NIS averaging coefficient."""
        blk = self._blocks.get(dt)
        if blk is not None:
            return blk
        A, B, Q, C, D = self._matrices(dt)
        n = A.shape[0]
        fr = self.model.friction
        F = np.zeros(n)
        F[:self._nx] = self.model.friction_at(dt)
        mats = {"A": A, "B": B, "Q": Q, "C": C, "D": D, "R": self.model.R, "F": F,
                "S": speed_row(self.model.C, fr.output, n) if fr is not None else np.zeros(n),
                "fr": np.array([friction_code(fr.speed), fr.width] if fr is not None
                               else [0.0, 1.0])}
        flat = np.concatenate([mats[f].ravel() for f in (*MODEL.names, *FRICTION.names)])
        # The averaging weight of the innovation (test (20), the NIS, the fuzzy input) is
        # that of one sample period even after lost samples (dt = k T): the statistic
        # chi (2 - c) / c assumes the stationary variance c / (2 - c) of the average,
        # which a single weight 1 - exp(-k T / window) breaks -- after a 50-sample gap at
        # 1 kHz the average has variance 0.4 where the test expects 0.01, so every burst
        # fired the test (a full onset search each) on a healthy motor. One innovation per
        # received sample at a fixed weight keeps it chi-square with p degrees of freedom
        # under any loss; the window then counts received samples.
        entry = (flat, 1.0 - math.exp(-min(dt, self.model.T) / self.config.nis_window))
        if len(self._blocks) > 1024:  # jittered dt must not grow memory forever
            self._blocks.clear()
        self._blocks[dt] = entry
        return entry

    def _matrices(self, dt: float) -> tuple[Array, Array, Array, Array, Array]:
        """(A, B, Q, C, D) of the filter's state for a step of dt, with the bias states
        (`monitor.estimation.bias.augmented_matrices`)."""
        return augmented_matrices(self.model, self.bias_plan, dt)

    @property
    def repairs(self) -> int:
        """Cholesky pivots clamped so far (0 in a healthy run)."""
        return int(self._stats[2])

    @property
    def rule_count(self) -> int:
        return self.out.rules

    def _run(self, k: int, dt: float, mode: float) -> None:
        """The kernel on sample k (self._u, self._y) with structure mode 0, 1 or 2."""
        blk = self._blocks.get(dt)
        if blk is None:
            blk = self._block(dt)
        self._call(dt, blk, self._u, self._y, mode, k)

    def _call(self, dt: float, blk: tuple[Array, float], u: Array, y: Array, mode: float,
              k: int) -> None:
        """The kernel on (u, y) after dt, with its model block blk (`_block`), structure
        mode 0, 1 or 2 and ring slot k mod ring_len."""
        prm = self._prm
        prm[self._i_dt] = dt
        prm[self._i_coef] = blk[1]
        prm[self._i_mode] = mode
        prm[self._i_slot] = k % self._ring_len
        fz = self.fuzzy
        n, m, p = self._dims
        self._kernel(blk[0], u, y, prm, self._st, fz.centres, fz.counts, fz.cons, fz.var,
                     fz.rule_idx, fz.rule_w, self._wk, self._out, self._lay, n, m, p, fz.max_mf)

    def step(self, u: Sequence[float] | Array | float, y: Sequence[float] | Array | float,
             dt: float) -> EstimatorOutput:
        """Process one sample; dt is the time since the previous sample (k T if missed)."""
        if not dt > 0.0:
            raise ValueError(f"dt must be positive, got {dt}")
        uu = self._u
        yy = self._y
        uu[:] = u
        yy[:] = y
        out = self.out
        if self._needs_init and self._init_from_sample(uu, yy):
            # the first sample conditioned the start (`start_state`): no kernel call
            self._time += dt
            self.steps += 1
            out.structure_event = False
            out.nis = self._stats[0]
            return out
        blk = self._blocks.get(dt)
        if blk is None:
            blk = self._block(dt)
        now = self._time + dt
        self._call(dt, blk, uu, yy,
                   1.0 if now - self._last_event >= self.config.dwell else 0.0, self.steps)
        self._time = now
        if self._stats[3] > 0.0 and self._structure_event():
            out.structure_event = True
            out.rules = self.fuzzy.rule_count
        else:
            out.structure_event = False
        self.steps += 1
        out.nis = self._stats[0]
        return out

    def warm_up(self) -> None:
        """Load (or compile) every compiled function of a step, a structure event (the onset
        search and the re-processing) and `step_many`'s loop, on this scratch estimator, so
        that the first event on a live bus does not stall the caller for the JIT. Leaves the
        estimator dirty: use a throw-away instance."""
        _, m, p = self._dims
        for _ in range(2):
            self.step(np.zeros(m), np.zeros(p), self.model.T)
        k = self.steps - 1
        j, _, _, _, models = self._onset(k)
        first = k - len(models[2]) + 1
        self._held_error(first, k, models)
        self._reprocess(j, k, first, models)
        self.step_many(np.zeros((2, m)), np.zeros((2, p)), np.full(2, self.model.T))

    def _init_from_sample(self, u: Array, y: Array) -> bool:
        """The start without a given x0 (`start_state`); True when the first sample has
        been used by it (then its output is written here and the kernel does not run).

        A start from the first output gives gamma's common part the small variance
        `var_start` (the transient of the start goes to the state, whose uncertainty is
        wide, not to gamma^), and that sample is out of the onset search of (20): it had
        no time update, so it cannot be processed again from the state before it.
        """
        self._needs_init = False
        nx = self._nx
        try:
            st = start_state(self.model, u, y, self.P[:nx, :nx].copy())
            Ls = np.linalg.cholesky(st.S) if st.measured and st.S is not None else None
        except np.linalg.LinAlgError:
            # a start the float range does not hold (a model or a sample at its edge: the
            # wide prior's innovation covariance not positive definite): the steady state,
            # else rest -- a start must never raise on a model the rig check accepted
            try:
                x0, V0 = steady_start(self.model, u, y)
            except np.linalg.LinAlgError:
                x0, V0 = np.zeros(nx), np.zeros((nx, self._dims[1]))
            st, Ls = StartState(False, x0, V0, self.P[:nx, :nx].copy()), None
        # the plant's start; the bias states start at 0, uncorrelated, with their prior
        self.x[:nx] = st.x
        self.x[nx:] = 0.0
        self.V[:nx] = st.V
        self.V[nx:] = 0.0
        self.P[:] = 0.0
        self.P[:nx, :nx] = st.P
        self.P[nx:, nx:] = np.diag(self.bias_plan.var_start)
        if not st.measured:
            return False
        assert st.x_prior is not None and st.y_prior is not None
        assert st.nu is not None and Ls is not None
        self.common_var[self._faulty] = self.config.var_start
        self._onset_floor = 1
        out = self.out
        out.gamma[:] = 0.0
        # gamma^'s spread at the start: its common part's (the rules have not fired yet)
        out.gamma_sd[:] = np.sqrt(self.common_var)
        out.fault[:] = 0.0
        out.x_tilde[:] = st.x_prior  # the fault model's state (52) before the output
        out.x_e[:] = st.x_prior - st.x
        out.y_hat[:] = st.y_prior
        out.innovation[:] = scipy.linalg.solve_triangular(Ls, st.nu, lower=True)
        out.y_est[:] = self.model.C @ st.x + self.model.D @ u
        self._stats[0] = float(out.innovation @ out.innovation)  # NIS
        self._stats[1] = 0.0
        self._stats[3] = 0.0
        return True

    def _field(self, k: int, name: str) -> Array:
        """Field `name` of sample k's slot in the onset ring (`layout.RING`, flat)."""
        a, b = self._ring_spans[name]
        return self._ring[k % self._ring_len, a:b]


_KERNEL = select_kernel()
