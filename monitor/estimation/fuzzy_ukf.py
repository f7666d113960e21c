"""The self-constructing fuzzy UKF fault estimator, eqs (50)-(54) around (15)-(49).

One `FuzzyUKF` per motor takes one sample (u, y, dt) at a time and returns the state
estimate x^, the fault-model state x~, the loss of effectiveness gamma^, the fault
function f^ = -B diag(u) gamma^, the rule count and the normalised innovation.

Per sample k (the paper's order, made sound where Liu et al. 2020 is ambiguous or broken):

1. The fuzzy system (17), (51) evaluated at the previous input z_{k-1} gives gamma^_k and
   the fault function f^_k = -B diag(u_k) gamma^_k (10). The paper's f^ in R^n is not
   observable from one current (rank 3 of 4); f lives in span(B), so the consequents are
   the per-actuator losses gamma and f^ is built from them. When other rules fire than
   at the previous sample, gamma^ changes, and the state follows it (step 6).
2. UKF time update (32)-(43) with the fault term: x^- = A x^ + B u + f^ (35), and the
   sensitivity of the prior to gamma, V^- = A V - B diag(u).
3. UKF measurement update (44)-(49): the innovation nu = y - y^- (the output error e of
   (20) between the plant and the fault model (53)) and its covariance P_yy.
4. The random walk of the fault (11), (14), (54) adds q_gamma dt to the variance of
   gamma, but at most growth_share dt / (M' P_yy^-1 M): see (e) below. The innovation
   covariance with the fault's uncertainty is S_tot = P_yy + M pg M', M = C V^- - D diag(u)
   (nu ~ M (gamma - gamma^)), pg the variance of gamma^; NIS = nu' S_tot^-1 nu.
5. Structure-learning test (20), before the adaptation: the paper's test |e| > 1e-5 on
   the raw current error fires every sample (noise sigma is 0.5 A). Here e is whitened
   (w = L^-1 nu, L L' = S_tot) and averaged exponentially over a short window; the
   average's chi-square statistic (p degrees of freedom when the model fits, at any
   sample rate) must exceed a threshold, with a dwell time between two events. Keeping
   the sign makes a persistent bias -- what a changed fault produces -- far more visible
   than the squared NIS would. What an event does is below (b).
5b. Adaptive output noise (`adaptive_noise`): a real sensor is noisier than the model's R
   (the NIS then sits near the ratio and the model-mismatch flag stays up). The measurement
   update uses R + diag(rx), rx learnt by innovation-based covariance matching (the
   Sage-Husa estimator as adaptive UKFs use it; Mohamed and Schwarz, J. Geodesy 1999):

       rx_r <- max(0, rx_r + d min(nu_r^2 - S_rr, 8 (R + diag(rx))_rr)),
       d = 1 - exp(-T / noise_window)

   which drives E[nu_r^2] = S_tot,rr (S_rr - rx_r = C P^- C' + R + M pg M' on the diagonal:
   the same as R <- (1 - d) R + d (nu nu' - C P^- C' - M pg M')). rx >= 0 keeps R positive
   definite and never below the model's. A fault must not be learnt as noise: it is a mean
   shift in the innovations for gamma^ to explain, so a sample the mean-shift test (20)
   rejects (stat > nis_threshold) or a structure event's onset does not adapt, the cap
   bounds what a sample the test has not yet caught can add (R grows at most by 8 d a
   sample), and noise_window (2 s) is far longer than the
   classifier's dwell and the onset window. A persistent bias too small for the test (a
   small unmodelled load) is partly learnt as noise; a large one stays visible to the
   mismatch detector. Q is not adapted. rx is part of the onset ring: a structure event
   re-processes from the learnt noise of its onset.
6. Consequent adaptation (28) per sample, a_j <- clip(a_j + r e, u_L, u_U), with e = nu
   and the gain r of a recursive least squares on nu = M (gamma - gamma^) + noise: every
   consequent is a_j = c + d_j, a part c common to all rules (variance vc, gain
   vc M' S_tot^-1) and the rule's own part d_j (variance var_j, gain var_j xi_j M'
   S_tot^-1); the paper's constant r is the special case of fixed variances, which
   either reacts slowly or is noisy. Then the two-stage coupling (Friedland 1969; Hsieh
   and Chen 1999): V = (I - K C) V^- + K D diag(u) and x^ += V (gamma^+ - gamma^).
7. Fault-model state (52)-(53): x~_k = A x^_{k-1} + B u + f^_k (the paper's open-loop x~
   would integrate the process noise w, which no estimator knows, and drift without bound
   on the unobservable angle); the fuzzy input is x_e = x~ - x^ (50), normalised per state
   by the standard deviation of the whole prior, P^- + V^- pg V^-', so the membership
   functions are scale-free, and averaged over the test's window: one sample of x_e is
   mostly measurement noise; the average follows a persistent discrepancy, which is what
   a fault makes.
8. Bias states (`bias`; our extension, not the paper's): a load or an offset the model
   lacks is a constant the outputs show, which gamma^ cannot take where it sits on its
   bound (a load raises a motor's current: gamma < 0) and takes wrongly where it can (a
   0.4 loss under a constant load read 0.32). The filter's state is the plant's followed
   by biases (`DiscreteModel.bias_plan`): one per output, y = C x + D u_F + b ("output"),
   or one per actuator, x(k+1) = A x + B (u_F + b) ("input"), each a slow random walk
   (q_b = T / (info window^2), `BiasPlan.q`, window 1 h by default), only where the pair
   augmented with them is observable (the PBH rank at z = 1; "auto" takes output, else
   input, else none with a log line; an explicit kind that is not is refused). At a
   constant input a bias and gamma are not told apart (both are constants in the
   outputs): they are told apart by when they may change. A bias changes at a *bias
   event*: the structure test (20) fired, and the jump of gamma located at the onset
   leaves the bounds of (28) by more than min_jump while the bounds reduce it below
   min_jump -- a change gamma cannot take -- for the second time within 10 dwell times
   (a burst of noise fires the test too, and what a bias learns from one stays: gamma^,
   faster, takes up the difference). Then the biases are re-opened at the onset (their
   variance raised by that of BIAS_SIGMA0 output sigmas) and the samples since are
   processed again (mode 0: gamma is not re-opened). Every other change goes to gamma^,
   so a fault is never learnt as a bias. Between events a bias barely moves: a faster
   random walk integrates the innovations' small positive mean that the bound of gamma
   leaves on a healthy plant (noise below 0 is clipped), lifting gamma^ off its bound
   with it -- with a 1 s window a healthy motor's gamma^ crept from 0.013 to 0.04 within 5
   minutes. The biases start at their random walk's stationary variance, so healthy
   running does not move them; a load present from the start is taken by the first
   event. They are held apart from gamma in the two-stage coupling (their rows of V stay
   0): coupled, a bias learns d x^ / d gamma, the sensitivity M of the innovation to
   gamma decays, gamma^ becomes unobservable and drifts with the rules' switching while
   the bias follows it (a 0.4 loss under a load drifted to 0.33 in 10 s). Where the input
   varies, the outputs tell a bias and gamma apart as well. The fuzzy inputs stay the
   plant's states; a bias is reported in `EstimatorOutput.bias`, the events counted in
   `FuzzyUKF.bias_events`.

Why it is built this way -- what failed on a small, stiff, back-EMF dominated motor (a
24 V servo at 1 kHz: J = 2e-5, b = 1e-5, Ke = Ki = 0.03, Ra = 1, La = 1e-3, sensor sigma
0.01 A) while the paper's motor worked:

(a) The consequent update is exact only for the sensitivity M it is given. M = C V^- with
    V = d x^ / d gamma accumulated since V last started is the innovation's response to
    a gamma error held all that time -- right while gamma has not changed, wrong by orders
    of magnitude after a change: on the servo a held 0.4 error shows as 0.1 A (the back
    EMF takes the loss up), a 0.4 jump as -6 A on its first sample (La/Ra = 1 ms = T). The
    former code adapted with the held M before testing, so the first sample after the loss
    (600 sigma) moved gamma^ past its bound (clipped to 1) and x^ by V dgamma to the
    outage's steady state (speed 0 with the rotor at 790 rad/s); then it reset V to 0 and
    left P alone, so the filter was sure of a wrong speed: NIS in the thousands, gamma^
    oscillating between 0 and 1, a structure event every dwell time.
(b) A structure event is therefore a jump of gamma at the onset of the change. The test
    fires some samples after it; the onset is located over a short ring of past samples
    by the generalised likelihood ratio of Willsky and Jones (1976) -- for each candidate
    onset j the signature M_i(j) of a jump there (the two-stage sensitivity started at j)
    against the innovations since, the jump integrated out with its prior var_reopen --
    and the filter goes back to its state before j and processes the samples since again,
    with the event first: every consequent re-opened at the current output (f^ does not
    jump: the intent of (23)-(27)), and the raise of gamma's variance from g0 to g1 done
    the exact two-stage way, V <- V g0/g1, P <- P + V (g0 (g1 - g0) / g1) V' (the state
    keeps the uncertainty the old gamma gave it; the new gamma acts from j on). The former
    "V restarts at 0" is the limit g1 >> g0 of this, without its P term and samples late.
    A jump that the bounds (28) reduce below min_jump is no event (typically noise pushing
    a fault-free gamma^ below 0, where it sits on its bound).
(c) gamma^ = sum xi_j a_j also changes when z fires other rules; x^ = x_bar + V gamma^ must
    hold whichever way it changes, or the state is left with a fault it no longer has.
(d) The loss of effectiveness is not a function of x_e: rules that share one value and
    learn it together (the common part c) keep gamma^ steady when z moves; with separate
    variances only, a rule that fires weakly keeps a large variance, follows the noise,
    and on a slow plant (large V) its switching moves the state.
(e) The random walk: q_gamma is in gamma^2 per second and scale-free, but its share in
    S_tot is not: it settles near sqrt(q_gamma dt M' P_yy^-1 M), 6 % on the servo at
    5e-3 /s (NIS 5 % low, where the model-mismatch monitor's band at 1 kHz is +-7 %),
    over 100 % on a 500 Hz speed-output rig. Capping the growth at growth_share dt of the
    sample's information keeps that share near sqrt(growth_share dt) at any scale and
    rate (2 % at 1 kHz, 7 % at 100 Hz); on the paper's motor the cap does not bind. The
    random walk stays in gamma's variance and is not coupled into the state: the optimal
    two-stage filter of a random-walk bias (Hsieh and Chen's extra terms, V^- <- V^- g0/g1,
    P^- += U g0 (g1 - g0) / g1 U') is the augmented KF with that q, and on the servo it
    makes the model expect the speed to wander with gamma (NIS 0.2-0.3). So the update is
    the two-stage filter of a constant gamma whose old evidence fades; with one rule,
    q_gamma = 0, var_rule = 0, no projection and no events it is the augmented Kalman
    filter's gamma update to round-off (tested).
(f) Scale: P0 = None is the stationary Kalman covariance in the state's own units
    (`initial_covariance`); P0 = 1 meant 1 A on a 0.26 A current and 1 rad/s on a
    790 rad/s speed. The fuzzy input is normalised by the whole prior covariance (step 7):
    by P^- alone, the bias-free part, the servo's speed component of x_e swung by 28 of
    its "sigmas" in healthy running.
(g) Cost, bounded per sample whatever the frame loss (an unbounded cost starves a
    one-CPU daemon under a CAN flood). A sample costs one kernel call (35)-(54) plus its
    ring slot. The structure test (20) can fire at most once per dwell time (a negligible
    jump restarts the dwell too), and only then does a sample pay for the onset search and
    the re-processing, both over the ring: ring_len = onset_window / T + 1 samples, where a
    lost stretch is one slot (one step of dt = k T), so loss never lengthens it. The search
    is O(ring_len^2) up to `max_onsets` samples and two-stage above (a coarse grid of onsets,
    then around its best: O(ring_len (max_onsets + 2 ring_len / max_onsets))); with the JIT
    it and the re-processing (at most ring_len kernel calls) run compiled, one call each.
    The estimator's restart after a long gap reuses the model's stationary covariance.
(h) Start without an x0 (`start_state`): from the fault-free steady state of the first
    input, x_ss = (I - A)^-1 B u with V = d x_ss / d gamma (`steady_start`), only when the
    first output confirms it (a monitor attached to a running motor). Started from there
    in every case, a motor at rest when the first command came -- no current at full
    voltage, what an outage at steady state looks like -- was read as an outage for the
    60-80 ms the filter took to converge, at every start of a replay and after every
    restart. Otherwise the state at the first sample is the steady state whose output is
    nearest the first output, each state's uncertainty the whole range from rest to the
    steady state, conditioned on that output by the update (44)-(49); gamma's common part
    starts at the small variance var_start, so the start-up transient goes to the state
    and not to gamma^, and a fault present from the start is found by the test (20).

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

import itertools
import logging
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from monitor.estimation.fuzzy import FuzzyConfig, SelfConstructingFuzzySystem, fire, infer
from monitor.estimation.jit import njit
from monitor.estimation.model import (
    BIAS_WINDOW_S,
    ESTIMATOR_LIMIT_BYTES,
    DiscreteModel,
    ModelError,
    estimator_bytes,
    ring_slot_size,
)
from monitor.estimation.ukf import sigma_weights, spd_inverse, ukf_predict, ukf_update

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

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
    "step_many",
]

_log = logging.getLogger(__name__)

# Version of the kernel's flat-buffer layout; bump it whenever the meaning of the buffers
# changes (2: per-actuator bounds in prm; 3: structure events in the kernel, the onset
# ring and the consequents' common variance in st). An ahead-of-time build of another
# layout has the same signature but would misread the buffers, so select_kernel refuses it.
# 4: the adapted output-noise excess in st and in every ring slot, its weight in prm.
# 5: the filter's state may hold bias states after the plant's (x, P, V, z of the augmented
# dimension n): the fuzzy inputs are the first centres.shape[0] entries of z, and V is 0 on
# the bias rows.
KERNEL_LAYOUT = 5

# The adaptive output noise (step 5b) lets a sample raise the output noise by at most
# (this - 1) times itself, times the forgetting weight: a burst the mean-shift test has not
# caught yet moves R by a bounded step, and a fitting model loses < 1 % to the cap.
_NOISE_CLIP = 9.0

# A bias event (step 8) needs the change gamma cannot take seen twice, the second time within
# this many dwell times of the first: a burst of noise that fires the test (3.7 sigma) is
# seldom followed by another within 2 s, a load that the outputs keep showing is.
_BIAS_CONFIRM = 10.0


def kernel_layout() -> int:
    """The buffer layout this kernel reads (exported into the AOT module as well)."""
    return KERNEL_LAYOUT


@dataclass(frozen=True)
class FuzzyUKFConfig:
    """Tuning of the fuzzy UKF. Defaults are those of the paper where it gives any.

    alpha, beta: sigma-point spread (34), paper 1e-4 and 2.
    q_gamma: random-walk intensity of the loss of effectiveness, gamma^2 per second (54),
        on the part of the consequents common to all rules.
    growth_share: cap on that growth per second, as a share of the information a sample
        gives on gamma (M' P_yy^-1 M): keeps gamma's share of the innovation covariance
        near sqrt(growth_share dt), so that the NIS stays calibrated at any scale.
    var0: initial variance of the common part of the consequents (gamma^2).
    var_reopen: the same on a structure-learning event.
    var_rule: variance of each rule's own part, initially and on an event (small: the
        loss of effectiveness does not depend on x_e much).
    var_start: initial variance of the common part after a start from the first output
        (`start_state`, when the steady state of the first input does not explain it):
        small, so that the start-up transient goes to the widely uncertain state and not
        to gamma^; a fault present from the start is found by the structure test (20).
    var_max: cap on the common variance (no excitation, u = 0, does not grow it forever).
    nis_window: time constant of the innovation average, seconds.
    nis_threshold: structure-learning threshold on the chi-square statistic of the averaged
        whitened innovation (p degrees of freedom; 14 is 3.7 sigma for one output).
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
    dwell: float = 0.2
    growth_share: float = 0.5
    onset_window: float = 0.2
    min_jump: float = 0.01
    max_onsets: int = 24
    P0: float | None = None
    adaptive_noise: bool = True
    noise_window: float = 2.0
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
    y_hat: predicted output before the update; y_est: output of the final estimate,
    C x^ + D u (1 - gamma^). nis: normalised innovation squared.
    innovation: whitened innovation L^-1 nu (L L' = S_tot), per output. rules: rule count.
    bias: the estimated bias states (`FuzzyUKF.bias_plan`; empty without).
    """

    x_hat: Array
    x_tilde: Array
    x_e: Array
    gamma: Array
    fault: Array
    y_hat: Array
    innovation: Array
    y_est: Array
    bias: Array = field(default_factory=lambda: np.zeros(0))
    nis: float = 0.0
    rules: int = 0
    structure_event: bool = False


@njit
def _rule_variance(var: Array, rule_idx: IntArray, rule_w: Array, nf: int, a: int) -> float:
    """sum xi_j^2 var_j over the firing rules: the part of the variance of the fuzzy output
    gamma^_a = sum xi_j a_j that the rules' own deviations (independent) contribute."""
    acc = 0.0
    for k in range(nf):
        acc += rule_w[k] * rule_w[k] * var[rule_idx[k], a]
    return acc


@njit
def _fuzzy_ukf_step(
    mdl: Array, u: Array, y: Array, prm: Array, st: Array,
    centres: Array, counts: IntArray, cons: Array, var: Array, rule_idx: IntArray, rule_w: Array,
    wk: Array, out: Array, n: int, m: int, p: int, max_mf: int,
) -> None:
    """One sample of the fuzzy UKF on flat buffers (see FuzzyUKF for the layout).

    prm = [dt, delta, wi, q_gamma, var_max, nis_coef, var_reopen, nis_threshold, mode,
    growth_share, slot, var_rule, lower[0..m), upper[0..m), noise_coef]: lower/upper are the
    per-actuator bounds of (28), lower[a] == upper[a] marks a known actuator; noise_coef
    the forgetting weight of the adaptive output noise (0: the model's R). mode 0: no
    structure test (dwell time), 1: test (stats[3] = 1 when it fires), 2: a structure event
    at the start of this sample (the caller re-processes from the onset of a change).
    slot: this sample's place in the onset ring (st after x, P, V, z, the common
    variance of the consequents and the adapted output-noise excess).
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
    var_reopen = prm[6]
    threshold = prm[7]
    mode = prm[8]
    share = prm[9]
    var_rule = prm[11]
    # per-actuator projection bounds of (28); lo[a] == hi[a] marks a known actuator (no
    # loss of effectiveness): its consequents are fixed, carry no variance, never adapt
    lo = prm[12:12 + m]
    hi = prm[12 + m:12 + 2 * m]
    noise_coef = prm[12 + 2 * m]
    o = 0
    x = st[o:o + n]; o += n
    P = st[o:o + n * n].reshape((n, n)); o += n * n
    V = st[o:o + n * m].reshape((n, m)); o += n * m
    z = st[o:o + n]; o += n
    vc = st[o:o + m]; o += m
    rx = st[o:o + p]; o += p
    o += int(prm[10]) * (2 * n + n * n + n * m + 4 * p + 3 * m + 1 + n * p + p * p)
    r_x = st[o:o + n]; o += n
    r_P = st[o:o + n * n].reshape((n, n)); o += n * n
    r_V = st[o:o + n * m].reshape((n, m)); o += n * m
    r_z = st[o:o + n]; o += n
    r_ebar = st[o:o + p]; o += p
    r_gamma = st[o:o + m]; o += m
    r_vc = st[o:o + m]; o += m
    r_u = st[o:o + m]; o += m
    r_y = st[o:o + p]; o += p
    r_dt = st[o:o + 1]; o += 1
    r_K = st[o:o + n * p].reshape((n, p)); o += n * p
    r_Sti = st[o:o + p * p].reshape((p, p)); o += p * p
    r_nu = st[o:o + p]; o += p
    r_rx = st[o:o + p]
    o = 0
    gamma = out[o:o + m]; o += m
    fhat = out[o:o + n]; o += n
    xtilde = out[o:o + n]; o += n
    xe = out[o:o + n]; o += n
    yhat = out[o:o + p]; o += p
    innov = out[o:o + p]; o += p
    stats = out[o:o + 4]; o += 4
    ebar = out[o:o + p]; o += p
    yest = out[o:o + p]
    o = 0
    uf = wk[o:o + m]; o += m
    dg = wk[o:o + m]; o += m
    pg = wk[o:o + m]; o += m
    b = wk[o:o + n]; o += n
    d = wk[o:o + n]; o += n
    s = wk[o:o + n]; o += n
    xp = wk[o:o + n]; o += n
    xq = wk[o:o + n]; o += n
    yoff = wk[o:o + p]; o += p
    dy = wk[o:o + p]; o += p
    nu = wk[o:o + p]; o += p
    L = wk[o:o + n * n].reshape((n, n)); o += n * n
    IKC = wk[o:o + n * n].reshape((n, n)); o += n * n
    T1 = wk[o:o + n * n].reshape((n, n)); o += n * n
    Pp = wk[o:o + n * n].reshape((n, n)); o += n * n
    Pq = wk[o:o + n * n].reshape((n, n)); o += n * n
    Ls = wk[o:o + p * p].reshape((p, p)); o += p * p
    Pyy = wk[o:o + p * p].reshape((p, p)); o += p * p
    Pyy_inv = wk[o:o + p * p].reshape((p, p)); o += p * p
    St = wk[o:o + p * p].reshape((p, p)); o += p * p
    Sti = wk[o:o + p * p].reshape((p, p)); o += p * p
    Pxy = wk[o:o + n * p].reshape((n, p)); o += n * p
    K = wk[o:o + n * p].reshape((n, p)); o += n * p
    Vp = wk[o:o + n * m].reshape((n, m)); o += n * m
    M = wk[o:o + p * m].reshape((p, m)); o += p * m
    Ra = wk[o:o + p * p].reshape((p, p))

    # 0. the state before this sample, in the onset ring (a structure event re-processes
    # the samples since the onset of the change from there)
    for r in range(n):
        r_x[r] = x[r]
        r_z[r] = z[r]
        for c in range(n):
            r_P[r, c] = P[r, c]
        for a in range(m):
            r_V[r, a] = V[r, a]
    for r in range(p):
        r_ebar[r] = ebar[r]
        r_y[r] = y[r]
        r_rx[r] = rx[r]
    for a in range(m):
        r_gamma[a] = gamma[a]
        r_vc[a] = vc[a]
        r_u[a] = u[a]
    r_dt[0] = dt

    # 1. fuzzy output (51) at the previous input. gamma holds the previous output; the
    # rules fired by the new input may give another, and the state estimate follows
    # gamma^ whichever way it changes (two-stage: x^ = x_bar + V gamma^)
    # the fuzzy inputs are the plant's states, the first ones of z (bias states follow)
    nf = fire(z[:centres.shape[0]], centres, counts, max_mf, rule_idx, rule_w)
    infer(cons, rule_idx, rule_w, nf, uf)
    for a in range(m):
        if not hi[a] > lo[a]:
            uf[a] = lo[a]  # a known actuator: its gamma is fixed
        dg[a] = uf[a] - gamma[a]
        gamma[a] = uf[a]
    for r in range(n):
        acc = x[r]
        for a in range(m):
            acc += V[r, a] * dg[a]
        x[r] = acc
    if mode > 1.0:
        # Structure event (20)-(22) at the onset of a change: gamma jumps before this
        # sample's transition. Every consequent is re-opened at the current output (f^
        # does not jump: the intent of (23)-(27)): the common variance to var_reopen, the
        # rules' own to var_rule. In the two-stage filter, raising the variance of gamma
        # from g0 to g1 is exact with V <- V g0/g1 and P <- P + V (g0 (g1 - g0) / g1) V':
        # the state keeps the uncertainty that the old gamma gave it, and what is learnt
        # of the new one moves the state only as far as the jump has acted on it.
        for a in range(m):
            if not hi[a] > lo[a]:
                continue
            g0 = vc[a] + _rule_variance(var, rule_idx, rule_w, nf, a)
            for j in range(cons.shape[0]):
                cons[j, a] = gamma[a]
                var[j, a] = var_rule
            if vc[a] < var_reopen:
                vc[a] = var_reopen
            g1 = vc[a] + _rule_variance(var, rule_idx, rule_w, nf, a)
            if g1 > 0.0:
                f = g0 / g1
                s0 = g0 - g0 * f
                for r in range(n):
                    for c in range(r, n):
                        v = P[r, c] + s0 * V[r, a] * V[c, a]
                        P[r, c] = v
                        P[c, r] = v
                for r in range(n):
                    V[r, a] *= f
        for r in range(p):
            ebar[r] = 0.0
    # fault function (10) and the input after the loss of effectiveness
    for a in range(m):
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
    # 2. time update (35)-(43); the prior's sensitivity to gamma V^- = A V - B diag(u)
    # (zero for a known actuator)
    for r in range(n):
        for a in range(m):
            acc = 0.0
            if hi[a] > lo[a]:
                acc = -B[r, a] * u[a]
                for c in range(n):
                    acc += A[r, c] * V[c, a]
            Vp[r, a] = acc
    rep = ukf_predict(x, P, A, b, Q, delta, wi, L, d, xp, Pp)
    for r in range(n):
        xtilde[r] = xp[r]  # fault-model state (52)
    # 3. measurement update (44)-(49) into (xq, Pq), with the output noise the innovations
    # have shown: R + diag(rx) (step 5b), never below the model's R
    for r in range(p):
        for c in range(p):
            Ra[r, c] = R[r, c]
        Ra[r, r] += rx[r]
    rep += ukf_update(xp, Pp, C, yoff, Ra, y, delta, wi, L, Ls, s, dy, Pyy, Pyy_inv, Pxy, K, nu,
                      xq, Pq, IKC, T1)
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
    # 4. random walk (11), (54) of the actuator's effectiveness over this sample, on the part
    # common to all consequents: q_gamma dt, but at most `share` dt of what the sample
    # resolves (M' P_yy^-1 M), so that the variance of gamma keeps a small share of the
    # innovation covariance and the NIS stays calibrated on a plant that resolves gamma
    # in a few samples; capped at var_max
    for a in range(m):
        pg[a] = 0.0
        if hi[a] > lo[a]:
            grow = q_gamma * dt
            vis = 0.0
            for r in range(p):
                acc = 0.0
                for c in range(p):
                    acc += Pyy_inv[r, c] * M[c, a]
                vis += M[r, a] * acc
            if vis * grow > share * dt:
                grow = share * dt / vis
            v = vc[a] + grow
            vc[a] = v if v < var_max else (vc[a] if vc[a] > var_max else var_max)
            pg[a] = vc[a] + _rule_variance(var, rule_idx, rule_w, nf, a)
    # total innovation covariance S_tot = P_yy + M diag(pg) M' (pg: variance of gamma^)
    for r in range(p):
        for c in range(p):
            acc = Pyy[r, c]
            for a in range(m):
                acc += pg[a] * M[r, a] * M[c, a]
            St[r, c] = acc
    rep += spd_inverse(St, Ls, Sti)
    nis = 0.0
    for r in range(p):
        acc = 0.0
        for c in range(p):
            acc += Sti[r, c] * nu[c]
        nis += nu[r] * acc
    # whitened innovation w = L^-1 nu with L L' = S_tot (Ls holds that factor)
    for r in range(p):
        acc = nu[r]
        for c in range(r):
            acc -= Ls[r, c] * innov[c]
        innov[r] = acc / Ls[r, r]
    # 5. structure-learning test (20), before the adaptation: the exponentially weighted
    # mean of w is N(0, c/(2-c) I) under a fitting model, so its statistic is chi-square
    # with p degrees of freedom at any sample rate
    chi = 0.0
    for r in range(p):
        ebar[r] += nis_coef * (innov[r] - ebar[r])
        chi += ebar[r] * ebar[r]
    stat = chi * (2.0 - nis_coef) / nis_coef
    stats[3] = 1.0 if (mode == 1.0 and stat > threshold) else 0.0
    # 5b. adaptive output noise, innovation-based covariance matching (Sage-Husa; Mohamed
    # and Schwarz 1999): rx <- max(0, rx + d (min(nu_r^2, c S_rr) - S_rr)), which drives
    # E[nu nu'] = S_tot on the diagonal. Not from a sample the mean-shift test (20) rejects:
    # a fault is a mean shift for gamma^ to explain, not noise to learn
    if noise_coef > 0.0 and stat <= threshold and mode < 2.0:
        for r in range(p):
            # the excess is capped in units of the output noise itself, not of S_tot: at a
            # structure event S_tot is mostly gamma's uncertainty (M pg M'), and a cap in
            # S_tot let one sample raise a stiff servo's R 125-fold
            inc = nu[r] * nu[r] - St[r, r]
            cap = (_NOISE_CLIP - 1.0) * Ra[r, r]
            v = rx[r] + noise_coef * (inc if inc < cap else cap)
            rx[r] = v if v > 0.0 else 0.0
    # the sample as the filter saw it, for locating the onset of a change
    for r in range(n):
        for c in range(p):
            r_K[r, c] = K[r, c]
    for r in range(p):
        r_nu[r] = nu[r]
        for c in range(p):
            r_Sti[r, c] = Sti[r, c]
    # 6. consequent adaptation (28): a_j = c + d_j, the part c common to all consequents
    # (variance vc) and the rules' own parts d_j (variance var_j), independent: the RLS
    # gains are vc M' S_tot^-1 for c, which moves every consequent, and
    # var_j xi_j M' S_tot^-1 for d_j; then the projection on [u_L, u_U]
    for a in range(m):
        dg[a] = 0.0
        if not hi[a] > lo[a]:
            continue
        step = 0.0
        gm = 0.0
        for r in range(p):
            gr = 0.0
            for c in range(p):
                gr += M[c, a] * Sti[c, r]
            step += gr * nu[r]  # M' S_tot^-1 nu
            gm += gr * M[r, a]
        old_out = 0.0
        for k in range(nf):
            old_out += rule_w[k] * cons[rule_idx[k], a]
        dc = vc[a] * step
        vc[a] = vc[a] * (1.0 - vc[a] * gm)
        for j in range(cons.shape[0]):
            cons[j, a] += dc
        new_out = 0.0
        for k in range(nf):
            j = rule_idx[k]
            xi = rule_w[k]
            new = cons[j, a] + var[j, a] * xi * step
            var[j, a] = var[j, a] * (1.0 - var[j, a] * xi * xi * gm)
            cons[j, a] = new
        for j in range(cons.shape[0]):
            if cons[j, a] < lo[a]:
                cons[j, a] = lo[a]
            elif cons[j, a] > hi[a]:
                cons[j, a] = hi[a]
        for k in range(nf):
            new_out += rule_w[k] * cons[rule_idx[k], a]
        dg[a] = new_out - old_out
    # two-stage coupling: V = (I - K C) V^- + K D diag(u); x^ += V dgamma. The bias states
    # (after the plant's nx = centres.shape[0]) are held apart from gamma (V = 0 there):
    # coupled, a bias would follow every change of gamma^ and take over what gamma^
    # explained -- at a constant input the two are not told apart -- as soon as the bias
    # has had its window to adapt (step 8)
    nx = centres.shape[0]
    for r in range(n):
        for a in range(m):
            acc = 0.0
            if hi[a] > lo[a] and r < nx:
                for c in range(n):
                    acc += IKC[r, c] * Vp[c, a]
                for c in range(p):
                    acc += K[r, c] * D[c, a] * u[a]
            V[r, a] = acc
    for r in range(n):
        acc = xq[r]
        for a in range(m):
            acc += V[r, a] * dg[a]
        x[r] = acc
        for c in range(n):
            P[r, c] = Pq[r, c]
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
    # 7. fuzzy input x_e = x~ - x^ (50), normalised by the standard deviation of the prior
    # (all of it: P^- + V^- diag(pg) V^-', the two-stage form of the covariance) and
    # averaged exponentially
    for r in range(n):
        xe[r] = xtilde[r] - x[r]
        var_r = Pp[r, r]
        for a in range(m):
            var_r += pg[a] * Vp[r, a] * Vp[r, a]
        sd = math.sqrt(var_r) if var_r > 0.0 else 1.0
        z[r] += nis_coef * (xe[r] / sd - z[r])
    stats[0] = nis
    stats[1] = stat
    stats[2] += rep


@njit
def _onset_glr(
    blocks: Array, bidx: IntArray, ring: Array, first: int, count: int, ring_len: int,
    offs: IntArray, faulty: IntArray, n: int, m: int, p: int, cands: IntArray, g: Array,
    info: Array,
) -> None:
    """The sufficient statistics of the onset search (20) over ring samples first ..
    first + count - 1 (see `FuzzyUKF._onset`), in compiled code: for every candidate onset
    first + cands[c] (cands sorted, in [0, count)), g[c] = sum_i M_i(c)' S_i^-1 nu_i and
    info[c] = sum_i M_i(c)' S_i^-1 M_i(c), with the signature of a jump at the candidate
    propagated through the filter as it ran (K, S_tot^-1, nu of each sample from the
    ring, eqs (44)-(49)): W <- A W - B_F u (the response of the prior (35)-(39)),
    M = C W - D_F u, W <- (I - K C) W + K D_F u. blocks[bidx[t]] is the flat model block of
    sample first + t (A, B, Q, C, D, R as `FuzzyUKF._block` packs them, one per distinct
    dt). O(count len(cands)
    n^2 f) flops.
    """
    f = faulty.shape[0]
    nc = cands.shape[0]
    W = np.zeros((nc, n, f))
    Wm = np.zeros((n, f))
    Mi = np.zeros((p, f))
    SM = np.zeros((p, f))
    Du = np.zeros((p, f))
    Bu = np.zeros((n, f))
    o_u, o_K, o_Sti, o_nu = offs[0], offs[2], offs[3], offs[4]  # offs[1]: dt, unused
    oA = 0
    oB = n * n
    oC = 2 * n * n + n * m
    oD = oC + p * n
    for c in range(nc):
        for a in range(f):
            g[c, a] = 0.0
            for b in range(f):
                info[c, a, b] = 0.0
    for t in range(count):
        row = ring[(first + t) % ring_len]
        mdl = blocks[bidx[t]]
        for a in range(f):
            ua = row[o_u + faulty[a]]
            for r in range(n):
                Bu[r, a] = mdl[oB + r * m + faulty[a]] * ua
            for r in range(p):
                Du[r, a] = mdl[oD + r * m + faulty[a]] * ua
        for c in range(nc):
            if cands[c] > t:
                break  # sorted: no later candidate has started yet
            Wc = W[c]
            for r in range(n):
                for a in range(f):
                    acc = -Bu[r, a]
                    for q in range(n):
                        acc += mdl[oA + r * n + q] * Wc[q, a]
                    Wm[r, a] = acc
            for r in range(p):
                for a in range(f):
                    acc = -Du[r, a]
                    for q in range(n):
                        acc += mdl[oC + r * n + q] * Wm[q, a]
                    Mi[r, a] = acc
            for r in range(p):
                for a in range(f):
                    acc = 0.0
                    for q in range(p):
                        acc += row[o_Sti + r * p + q] * Mi[q, a]
                    SM[r, a] = acc
            for a in range(f):
                acc = 0.0
                for r in range(p):
                    acc += SM[r, a] * row[o_nu + r]
                g[c, a] += acc
                for b in range(f):
                    acc = 0.0
                    for r in range(p):
                        acc += Mi[r, a] * SM[r, b]
                    info[c, a, b] += acc
            # W = (I - K C) Wm + K Du = Wm + K (Du - C Wm) = Wm - K Mi
            for r in range(n):
                for a in range(f):
                    acc = Wm[r, a]
                    for q in range(p):
                        acc -= row[o_K + r * p + q] * Mi[q, a]
                    Wc[r, a] = acc


@njit
def _reprocess_loop(
    blocks: Array, coefs: Array, bidx: IntArray, ring: Array, first: int, count: int, ring_len: int,
    o_u: int, o_y: int, o_dt: int, prm: Array, st: Array, centres: Array, counts: IntArray,
    cons: Array, var: Array, rule_idx: IntArray, rule_w: Array, wk: Array, out: Array,
    n: int, m: int, p: int, max_mf: int, u: Array, y: Array, first_mode: float,
) -> None:
    """Samples first .. first + count - 1 of the ring again through `_fuzzy_ukf_step`, the
    first in first_mode (2: a structure event of gamma; 0: none, a bias event having
    re-opened the biases), the others without the test (mode 0): what
    `FuzzyUKF._reprocess` does one Python call per sample, in one compiled call."""
    for t in range(count):
        k = first + t
        row = ring[k % ring_len]
        for a in range(m):
            u[a] = row[o_u + a]
        for r in range(p):
            y[r] = row[o_y + r]
        prm[0] = row[o_dt]
        prm[5] = coefs[bidx[t]]
        prm[8] = first_mode if t == 0 else 0.0
        prm[10] = float(k % ring_len)
        _fuzzy_ukf_step(blocks[bidx[t]], u, y, prm, st, centres, counts, cons, var, rule_idx,
                        rule_w, wk, out, n, m, p, max_mf)


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


def initial_covariance(model: DiscreteModel) -> Array:
    """A scale-aware initial covariance of the observable state (P0 = None): the Kalman
    filter's stationary posterior covariance at the model's period, else the covariance of
    the state fitted to n noisy output samples (`DiscreteModel.initial_covariance`). The
    model computes it, and refuses to be built without one, when it is made: the rig check
    then guarantees that the estimator starts."""
    return model.initial_covariance()


_P0_CACHE: dict[int, tuple[DiscreteModel, Array]] = {}


def _initial_covariance_of(model: DiscreteModel) -> Array:
    """`initial_covariance` once per model object: the pipeline restarts a node's
    estimator after a long gap or a NaN (one per gap under a flood), and the discrete
    Riccati solve must not be paid at each. The model is kept beside its id, so the id
    cannot be reused while the entry lives."""
    hit = _P0_CACHE.get(id(model))
    if hit is not None and hit[0] is model:
        return hit[1]
    P = initial_covariance(model)
    if len(_P0_CACHE) > 64:
        _P0_CACHE.clear()
    _P0_CACHE[id(model)] = (model, P)
    return P


def steady_start(model: DiscreteModel, u: Array, y: Array) -> tuple[Array, Array]:
    """(x^, V) to start from without a known initial state: the fault-free steady state
    (`start_state` uses it when the first output confirms it).

    A monitor attached to a running motor would otherwise start from x = 0 and read its
    own convergence as a fault. The steady state x_ss = (I - A)^-1 B u (1 - gamma) depends
    on the loss of effectiveness, which is not known yet: the filter starts at gamma^ = 0
    with V = d x_ss / d gamma (zero for the known actuators), so that what the first
    samples say about gamma moves the state with it (the two-stage coupling from the
    start); the first sample is then used once, by the filter's update. A model with an
    integrator among its observable states has no steady state: then x^ is the
    least-squares fit of [I - A; C] x = [B u; y - D u] to the first sample, with V = 0.
    """
    A, B, _ = model.at(model.T)
    n = A.shape[0]
    IA = np.eye(n) - A
    dB = -B * u
    dB[:, [a for a in range(model.m) if a not in model.fault_inputs]] = 0.0
    if np.linalg.cond(IA) < 1e12:
        sol = np.linalg.solve(IA, np.column_stack([B @ u, dB]))
    else:
        rhs = np.concatenate([B @ u, y - model.D @ u])
        fit, *_ = np.linalg.lstsq(np.vstack([IA, model.C]), rhs, rcond=None)
        sol = np.column_stack([fit, np.zeros_like(dB)])
    if not np.all(np.isfinite(sol)):
        return np.zeros(n), np.zeros_like(dB)
    x0: Array = np.array(sol[:, 0], dtype=np.float64)
    V0: Array = np.array(sol[:, 1:], dtype=np.float64)
    return x0, V0


# The steady state of the first input explains the first output when the output it predicts
# is within 3 sigma per output (squared whitened distance 9 p): otherwise the plant is
# somewhere else (at rest, in a transient, faulty), and the filter starts from the output.
_START_GATE = 9.0


@dataclass
class StartState:
    """Where the filter starts without an x0 (`start_state`).

    measured False: x, V, P are the state before the first sample, which the kernel then
    processes like any other (time update (35)-(43) and measurement update (44)-(49)).
    measured True: x, P are the estimate at the first sample itself, the prior x_prior
    conditioned on its output, with V = 0; y_prior, nu and S are that update's predicted
    output, innovation and innovation covariance (the kernel does not run on the sample).
    """

    measured: bool
    x: Array
    V: Array
    P: Array
    x_prior: Array | None = None
    y_prior: Array | None = None
    nu: Array | None = None
    S: Array | None = None


def start_state(model: DiscreteModel, u: Array, y: Array, P_base: Array) -> StartState:
    """The start of the filter without a known initial state: what the first output says.

    A monitor meets a plant in one of two ways: attached to one that runs (at the steady
    state of its command, or of an earlier one, healthy or not), or started with it (at
    rest when the first command comes, the first output one period into the response).
    Starting from the fault-free steady state of the first command in every case made a
    start at rest read as an outage -- current 0 at full voltage is what an outage at
    steady state looks like -- until the filter converged. So:

    1. The steady state of the command, x_c = (I - A)^-1 B u, is the prior. If the output
       it predicts explains the first output (within 3 sigma per output, with the predicted
       output covariance C (A P_base A' + Q) C' + R of (44)-(45)) and rest does not (at the
       sample, or one period into the command's response), the filter starts there,
       coupled to the unknown gamma (`steady_start`, V = d x_c / d gamma), and the kernel
       processes the first sample: a monitor attached to a running healthy motor starts
       without a transient, as before. When both explain it -- a back-EMF dominated motor
       whose steady current is within its sensor's noise -- the output cannot tell: case 2.
    2. Otherwise the output is what is known, at the first sample's own time. The prior
       there is the steady state whose output comes nearest to it, x_k = (I - A)^-1 B v
       with C x_k + D u = y fitted for v (least squares; the smallest change from u when
       there are more inputs than outputs), v kept between rest and the command on each
       actuator (an output no steady state gives -- a fast motor's current one period
       after a step -- must not throw the prior far out of the plant's range). Its
       uncertainty is diagonal on top of P_base, s_i = max(|x_c,i|, |x_k,i|, |e_i|) with
       e = C^+ (y - C x_k - D u): each state anywhere from rest to the larger of the two
       steady states, the outputs as far as the fit misses. That prior is conditioned on
       the first output by the measurement update (44)-(49) -- the Kalman update, the
       model being linear -- without a time update, since the input that acted before the
       first sample is not known. The directions the output pins come out at its noise,
       the others stay wide and the next samples narrow them; the state carries no
       sensitivity to gamma (V = 0), being no steady state of the first input.

    A model with an integrator among its observable states has no steady state: x_k is
    then the least-squares fit of [I - A; C] x = [B u; y - D u] (`steady_start`), x_c = x_k.
    In case 2 the filter gives gamma^ = 0 the small variance `var_start`
    (`FuzzyUKF._init_from_sample`), so that the start-up transient goes to the wide state.
    """
    A, B, Q = model.at(model.T)
    C, D, R = model.C, model.D, model.R
    n = A.shape[0]
    x_s, V_s = steady_start(model, u, y)
    IA = np.eye(n) - A
    steady = bool(np.linalg.cond(IA) < 1e12)
    Du = D @ u
    if steady:
        Sp = C @ (A @ P_base @ A.T + Q) @ C.T + R
        gate = _START_GATE * model.p

        def fits(e: Array) -> bool:
            return float(e @ np.linalg.solve(Sp, e)) <= gate

        # rest explains the output too (a back-EMF dominated motor with a noisy sensor: its
        # steady current is within the noise of none): the output cannot tell them apart
        at_rest = fits(y - Du) or fits(y - C @ B @ u - Du)
        if fits(y - C @ (A @ x_s + B @ u) - Du) and not at_rest:
            return StartState(False, x_s, V_s, P_base.copy())
        Gx = np.linalg.solve(IA, B)  # the steady state per unit of each input
        x_c = Gx @ u
        dv, *_ = np.linalg.lstsq(C @ Gx, y - Du - C @ x_c, rcond=None)
        v = np.clip(u + dv, np.minimum(u, 0.0), np.maximum(u, 0.0))
        x_k = Gx @ v
    else:
        x_c = x_k = x_s
    nu = y - C @ x_k - Du
    s = np.maximum(np.maximum(np.abs(x_c), np.abs(x_k)), np.abs(np.linalg.pinv(C) @ nu))
    Pk = P_base + np.diag(s * s)
    S = C @ Pk @ C.T + R
    S = 0.5 * (S + S.T)
    K = np.linalg.solve(S, C @ Pk).T
    IKC = np.eye(n) - K @ C
    P = IKC @ Pk @ IKC.T + K @ R @ K.T  # Joseph form: symmetric, positive definite
    P = 0.5 * (P + P.T)
    x = x_k + K @ nu
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(P))):
        return StartState(False, x_s, V_s, P_base.copy())
    return StartState(True, x, np.zeros_like(V_s), P, x_k, C @ x_k + Du, nu, S)


def _work_size(n: int, m: int, p: int) -> int:
    return 3 * m + 5 * n + 3 * p + 5 * n * n + 6 * p * p + 2 * n * p + n * m + p * m


class FuzzyUKF:
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
        self._prm = np.concatenate([[0.0, w.delta, w.wi, cfg.q_gamma, cfg.var_max, 0.0,
                                     cfg.var_reopen, cfg.nis_threshold, 0.0, cfg.growth_share,
                                     0.0, cfg.var_rule], lower, upper, [noise_coef]])
        # state: x, P, V, z, the common variance of the consequents (per actuator), the
        # adapted output-noise excess (per output), then the onset ring (one slot per
        # sample, see ring_slot_size)
        head = 2 * n + n * n + n * m + m + p
        self._ring_len = max(2, math.ceil(cfg.onset_window / model.T) + 1)
        slot = ring_slot_size(n, m, p)
        self._st = np.zeros(head + self._ring_len * slot)
        self.x = self._st[:n]
        self.P = self._st[n:n + n * n].reshape(n, n)
        self.V = self._st[n + n * n:n + n * n + n * m].reshape(n, m)
        self._zall = self._st[n + n * n + n * m:head - m - p]
        self.z = self._zall[:nx]  # the fuzzy input: the plant's part
        self.bias = self.x[nx:]  # the bias states (step 8)
        self._bias_q = self.bias_plan.q
        self._bias_var0 = self.bias_plan.var0
        self.common_var = self._st[head - m - p:head - p]
        self.noise_excess = self._st[head - p:head]  # rx: R + diag(rx) is the output noise
        self.common_var[self._faulty] = cfg.var0
        self._ring = self._st[head:].reshape(self._ring_len, slot)
        offs = np.cumsum([0, n, n * n, n * m, n, p, m, m, m, p, 1, n * p, p * p, p, p])
        assert offs[-1] == slot
        self._rf = dict(zip(("x", "P", "V", "z", "ebar", "gamma", "vc", "u", "y", "dt", "K",
                             "Sti", "nu", "rx"), itertools.pairwise(offs), strict=True))
        if x0 is not None:
            x0a = np.asarray(x0, dtype=float)
            if x0a.shape == (model.n_full,):
                self.x[:nx] = model.Wobs @ x0a
            elif x0a.shape == (nx,):
                self.x[:nx] = x0a
            else:
                raise ValueError(f"x0 must have {model.n_full} (full) or {nx} (observable) "
                                 "entries")
        self.P[:nx, :nx] = _initial_covariance_of(model) if cfg.P0 is None \
            else np.eye(nx) * cfg.P0
        self.P[nx:, nx:] = np.diag(self.bias_plan.var_start)
        self._needs_init = x0 is None
        self._wk = np.zeros(_work_size(n, m, p))
        self._out = np.zeros(m + 3 * n + 4 * p + 4)
        ob = self._out
        self._stats = ob[m + 3 * n + 2 * p:m + 3 * n + 2 * p + 4]
        self._ebar = ob[m + 3 * n + 2 * p + 4:m + 3 * n + 3 * p + 4]
        self.out = EstimatorOutput(
            x_hat=self.x[:nx],
            x_tilde=ob[m + n:m + n + nx],
            x_e=ob[m + 2 * n:m + 2 * n + nx],
            gamma=ob[:m],
            fault=ob[m:m + nx],
            y_hat=ob[m + 3 * n:m + 3 * n + p],
            innovation=ob[m + 3 * n + p:m + 3 * n + 2 * p],
            y_est=ob[m + 3 * n + 3 * p + 4:],
            rules=self.fuzzy.rule_count,
            bias=self.bias,
        )
        self._u = np.zeros(m)
        self._y = np.zeros(p)
        self._blocks: dict[float, tuple[Array, float]] = {}
        self.kernel_name, self._kernel = _KERNEL
        self._time = 0.0
        self._last_event = -math.inf
        self._onset_floor = 0  # no onset before the previous event's
        rf = self._rf
        self._glr_offs = np.array([rf["u"][0], rf["dt"][0], rf["K"][0], rf["Sti"][0],
                                   rf["nu"][0]], dtype=np.int64)
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
        flat = np.concatenate([A.ravel(), B.ravel(), Q.ravel(), C.ravel(), D.ravel(),
                               self.model.R.ravel()])
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
        """(A, B, Q, C, D) of the filter's state for a step of dt: the model's (`at`), with
        the bias states (step 8) appended as random walks, [[A, B_d], [0, I]], [B; 0],
        diag(Q, q dt), [C, D_d], D."""
        md = self.model
        A, B, Q = md.at(dt)
        nb = self.bias_plan.count
        if nb == 0:
            return A, B, Q, md.C, md.D
        nx = self._nx
        Bd, Dd = self.bias_plan.entry(self.bias_plan.kind, B, md.D)
        Aa = np.block([[A, Bd], [np.zeros((nb, nx)), np.eye(nb)]])
        Ba = np.vstack([B, np.zeros((nb, B.shape[1]))])
        Qa = scipy.linalg.block_diag(Q, np.diag(self._bias_q * dt))
        Ca = np.hstack([md.C, Dd])
        return Aa, Ba, Qa, Ca, md.D

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
        prm = self._prm
        prm[0] = dt
        prm[5] = blk[1]
        prm[8] = mode
        prm[10] = k % self._ring_len
        fz = self.fuzzy
        n, m, p = self._dims
        self._kernel(blk[0], self._u, self._y, prm, self._st, fz.centres, fz.counts, fz.cons,
                     fz.var, fz.rule_idx, fz.rule_w, self._wk, self._out, n, m, p, fz.max_mf)

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
        prm = self._prm
        prm[0] = dt
        prm[5] = blk[1]
        prm[8] = 1.0 if now - self._last_event >= self.config.dwell else 0.0
        prm[10] = self.steps % self._ring_len
        fz = self.fuzzy
        n, m, p = self._dims
        self._kernel(blk[0], uu, yy, prm, self._st, fz.centres, fz.counts, fz.cons, fz.var,
                     fz.rule_idx, fz.rule_w, self._wk, self._out, n, m, p, fz.max_mf)
        self._time = now
        if self._stats[3] > 0.0 and self._structure_event():
            out.structure_event = True
            out.rules = fz.rule_count
        else:
            out.structure_event = False
        self.steps += 1
        out.nis = self._stats[0]
        return out

    def warm_up(self) -> None:
        """Load (or compile) every compiled function a structure event uses -- the onset
        search and the re-processing -- on this scratch estimator, so that the first event
        on a live bus does not stall the caller for the JIT. Leaves the estimator dirty:
        use a throw-away instance."""
        _, m, p = self._dims
        for _ in range(2):
            self.step(np.zeros(m), np.zeros(p), self.model.T)
        k = self.steps - 1
        j, _, models = self._onset(k)
        self._reprocess(j, k, k - len(models[2]) + 1, models)

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
        a, b = self._rf[name]
        return self._ring[k % self._ring_len, a:b]

    def _ring_models(self, first: int, count: int) -> tuple[Array, Array, IntArray]:
        """The flat model blocks and NIS coefficients of the distinct dt among ring samples
        first .. first + count - 1 (from the `_block` cache; k T after lost samples), and
        each sample's index into them: a few blocks, not one per sample."""
        L = self._ring_len
        dts = self._ring[(first + np.arange(count)) % L, self._rf["dt"][0]]
        if dts.min() == dts.max():  # no loss in the window: one block (the common case)
            blk = self._block(float(dts[0]))
            return blk[0][None, :], np.array([blk[1]]), np.zeros(count, np.int64)
        uniq, inv = np.unique(dts, return_inverse=True)
        entries = [self._block(d) for d in uniq.tolist()]
        return (np.stack([e[0] for e in entries]), np.array([e[1] for e in entries]),
                inv.astype(np.int64).reshape(-1))

    def _onset_stats(self, first: int, count: int, cands: IntArray,
                     models: tuple[Array, Array, IntArray]) -> tuple[Array, Array]:
        """(g, info) of the candidate onsets first + cands (see `_onset`)."""
        n, m, p = self._dims
        F = self._faulty
        f = len(F)
        if self.kernel_name == "jit":
            g = np.zeros((len(cands), f))
            info = np.zeros((len(cands), f, f))
            _onset_glr(models[0], models[2], self._ring, first, count, self._ring_len,
                       self._glr_offs, self._faulty_idx, n, m, p, cands, g, info)
            return g, info
        # Without the JIT (the hardened service's AOT kernel, or interpreted): the same
        # statistics with numpy, every onset of the window at once, then the candidates'
        eye = np.eye(n)
        W = np.zeros((count, n, f))
        ga = np.zeros((count, f))
        ia = np.zeros((count, f, f))
        for t in range(count):
            i = first + t
            u = self._field(i, "u")[F]
            A, B, _, C, D = self._matrices(float(self._field(i, "dt")[0]))
            K = self._field(i, "K").reshape(n, p)
            Sti = self._field(i, "Sti").reshape(p, p)
            nu = self._field(i, "nu")
            Du = D[:, F] * u
            Wm = A @ W[:t + 1] - B[:, F] * u
            Mi = C @ Wm - Du
            SM = Sti @ Mi
            ga[:t + 1] += np.einsum("cpa,p->ca", SM, nu)
            ia[:t + 1] += np.einsum("cpa,cpb->cab", Mi, SM)
            W[:t + 1] = (eye - K @ C) @ Wm + K @ Du
        return ga[cands], ia[cands]

    def _onset_scores(self, g: Array, info: Array) -> tuple[Array, Array]:
        """Log marginal likelihood ratio of a jump at each candidate, and the jump."""
        f = g.shape[1]
        vr = self.config.var_reopen
        if f == 1:  # one fault actuator: the same formulas without batched LAPACK calls
            d = info[:, 0, 0]
            s1 = g / (d + 1.0 / vr)[:, None]
            return 0.5 * g[:, 0] * s1[:, 0] - 0.5 * np.log1p(vr * d), s1
        sol = np.asarray(np.linalg.solve(info + np.eye(f) / vr, g[..., None])[..., 0], np.float64)
        score: Array = 0.5 * np.einsum("ca,ca->c", g, sol) \
            - 0.5 * np.linalg.slogdet(np.eye(f) + vr * info)[1]
        return score, sol

    def _onset(self, k: int) -> tuple[int, Array, tuple[Array, Array, IntArray]]:
        """The most likely onset of the change detected at sample k (20), the jump of
        gamma there (one entry per fault actuator), and the model blocks of the samples from
        the window's first to k (`_ring_models`, for `_reprocess`).

        For every candidate onset j in the ring (after the previous event's), a jump of
        gamma there would have shown in the innovations since as nu_i = M_i(j) dgamma, with
        the sensitivity M_i(j) of the two-stage filter started at j (V = 0 before j). Its
        marginal likelihood against no jump, with the prior dgamma ~ N(0, var_reopen), is
        g' (I + 1/var_reopen)^-1 g / 2 - log det(1 + var_reopen I) / 2 (g = sum M' S^-1 nu,
        I = sum M' S^-1 M): the generalised likelihood ratio of Willsky and Jones (1976)
        with the jump integrated out. The largest wins; its jump is (I + 1/var_reopen)^-1 g.

        Cost bound: the window holds count <= ring_len samples (ring_len = onset_window / T
        + 1; a lost sample is one step of dt = k T, one slot, so loss never lengthens it).
        Every candidate's signature is propagated over the samples after it, so a search
        of all onsets is O(count^2). With more than `max_onsets` samples the search is
        two-stage: every s-th onset (s = ceil(count / max_onsets), and the latest), then
        every onset within s of the best of those -- O(count (max_onsets + 2 s)) -- which
        finds the exact maximiser whenever the score is unimodal over s samples around it
        (the score of an abrupt change peaks at its onset and falls off over the samples
        in between, as the signature overlap does). Compiled with the JIT.
        """
        first = min(max(k - self._ring_len + 1, self._onset_floor, 0), k)
        count = k - first + 1
        models = self._ring_models(first, count)
        cap = max(2, self.config.max_onsets)
        if count <= cap:
            cands = np.arange(count, dtype=np.int64)
        else:
            s = -(-count // cap)
            cands = np.unique(np.append(np.arange(0, count, s), count - 1)).astype(np.int64)
            score, _ = self._onset_scores(*self._onset_stats(first, count, cands, models))
            b = int(cands[int(np.argmax(score))])
            cands = np.arange(max(b - s + 1, 0), min(b + s, count), dtype=np.int64)
        # the refined candidates include the coarse best, so the argmax of this pass is
        # the best of both
        score, sol = self._onset_scores(*self._onset_stats(first, count, cands, models))
        best = int(np.argmax(score))
        return first + int(cands[best]), sol[best], models

    def _reprocess(self, j: int, k: int, first: int,
                   models: tuple[Array, Array, IntArray], bias: bool = False) -> None:
        """Back to the state before sample j, a structure event there -- of gamma, or with
        bias True of the biases (their variance raised by var0, step 8) -- and samples j..k
        again (k - j < ring_len samples; in one compiled call with the JIT). models: the
        model blocks of samples first..k (`_ring_models`)."""
        n, m, p = self._dims
        nx = self._nx
        self.x[:] = self._field(j, "x")
        self.P[:] = self._field(j, "P").reshape(n, n)
        if bias:
            self.P[nx:, nx:] += np.diag(self._bias_var0)
        self.V[:] = self._field(j, "V").reshape(n, m)
        self._zall[:] = self._field(j, "z")
        self._ebar[:] = self._field(j, "ebar")
        self.out.gamma[:] = self._field(j, "gamma")
        self.common_var[:] = self._field(j, "vc")
        self.noise_excess[:] = self._field(j, "rx")
        # the event re-opens every consequent at that output: do it before the rules fire,
        # so that what the samples since taught them under the old fault is forgotten
        self.fuzzy.cons[:, self._faulty] = self.out.gamma[self._faulty]
        if self.kernel_name == "jit":
            rf = self._rf
            fz = self.fuzzy
            _reprocess_loop(models[0], models[1], models[2][j - first:], self._ring, j, k - j + 1,
                            self._ring_len, rf["u"][0], rf["y"][0], rf["dt"][0], self._prm,
                            self._st, fz.centres, fz.counts, fz.cons, fz.var, fz.rule_idx,
                            fz.rule_w, self._wk, self._out, n, m, p, fz.max_mf, self._u,
                            self._y, 0.0 if bias else 2.0)
            return
        for i in range(j, k + 1):
            self._u[:] = self._field(i, "u")
            self._y[:] = self._field(i, "y")
            self._run(i, float(self._field(i, "dt")[0]), 2.0 if i == j and not bias else 0.0)

    def _beyond_bounds(self, gamma: Array, jump: Array) -> bool:
        """Whether the filter has bias states and the jump leaves the bounds of (28) by
        more than min_jump for some fault actuator: a change gamma cannot take."""
        if self.bias_plan.count == 0:
            return False
        m = self._dims[1]
        lo = self._prm[12:12 + m]
        hi = self._prm[12 + m:12 + 2 * m]
        F = self._faulty
        g = gamma[F] + jump
        out = np.maximum(lo[F] - g, g - hi[F])
        return bool(F) and bool(np.any(out > self.config.min_jump))

    def _negligible(self, gamma: Array, jump: Array) -> bool:
        """Whether the jump, projected on the bounds of (28), is below min_jump for every
        fault actuator."""
        m = self._dims[1]
        lo = self._prm[12:12 + m]
        hi = self._prm[12 + m:12 + 2 * m]
        F = self._faulty
        moved = np.clip(gamma[F] + jump, lo[F], hi[F]) - gamma[F]
        return bool(F) and bool(np.all(np.abs(moved) < self.config.min_jump))

    def _structure_event(self) -> bool:
        """(20)-(22): locate the change, re-learn from its onset, add an MF where it shows.

        The test fires some samples after a change began. Its onset is located (_onset),
        the filter goes back to the state before it and processes the samples since
        again, with a structure event first: an actuator's loss of effectiveness is not a
        function of x_e, so no rule's old consequent is worth keeping and all are re-opened
        at the current output (so f^ does not jump, the intent of (23)-(27)); the
        sensitivity of the state to the new gamma starts there. Then an MF is inserted on
        the input with the largest |z| (output-preserving).
        """
        k = self.steps
        j, jump, models = self._onset(k)
        g_j = self._field(j, "gamma")
        if self._negligible(g_j, jump):
            # a jump that the bounds of (28) reduce to less than min_jump -- typically
            # evidence for a gamma below 0 where a fault-free actuator's estimate sits on
            # that bound -- is no change of the loss of effectiveness: it has been looked
            # at (the dwell restarts). Where it leaves the bounds by more than min_jump and
            # the filter has bias states, it is a change of the load or an offset (step 8):
            # the biases are re-opened at its onset and the samples since processed again
            self._ebar[:] = 0.0
            self._last_event = self._time
            if self._beyond_bounds(g_j, jump):
                if self._time > self._bias_armed_until:
                    # the first sight of it: a burst of noise fires the test as well, and
                    # a bias learnt from one is kept (gamma^ takes the difference) --
                    # what persists fires the test again after the dwell time
                    self._bias_armed_until = self._time + _BIAS_CONFIRM * self.config.dwell
                    return False
                self._bias_armed_until = -math.inf
                self._reprocess(j, k, k - len(models[2]) + 1, models, bias=True)
                self._onset_floor = j + 1
                self.bias_events += 1
            return False
        self._reprocess(j, k, k - len(models[2]) + 1, models)
        self._onset_floor = j + 1
        self._last_event = self._time
        self._bias_armed_until = -math.inf
        self.structure_events += 1
        fz = self.fuzzy
        v = int(np.argmax(np.abs(self.z)))
        fz.insert(v, float(self.z[v]), self.config.var_rule)
        fz.var[:, self._known] = 0.0  # known actuators have nothing to learn
        return True


_KERNEL = select_kernel()


# ----------------------------------------------------------------------------- many samples


@njit
def _fuzzy_ukf_loop(
    blocks: Array, coefs: Array, bidx: IntArray, dts: Array, U: Array, Y: Array, prm: Array,
    st: Array, centres: Array, counts: IntArray, cons: Array, var: Array, rule_idx: IntArray,
    rule_w: Array, wk: Array, out: Array, n: int, m: int, p: int, max_mf: int,
    clock: Array, dwell: float, ring_len: int, start: int,
    gamma_out: Array, yest_out: Array, nis_out: Array,
) -> int:
    """`_fuzzy_ukf_step` -- eqs (50)-(54) around (15)-(49), see the module docstring -- for
    samples start, start + 1, ... of (U, Y, dts), in compiled code.

    Sample i runs with model block ``blocks[bidx[i]]`` (the ZOH model (63)-(65) for its
    dt), NIS coefficient ``coefs[bidx[i]]``, structure mode 1 once the dwell time has passed
    since the last event (else 0) and ring slot (steps + i - start) mod ring_len: exactly
    what `FuzzyUKF.step` passes. clock = [time, time of the last structure event, reason,
    steps]. Stops after the first sample that needs Python: the structure test (20) fired
    (clock[2] = 1; the onset search and re-processing are Python's) or gamma^ is NaN
    (clock[2] = 2); returns the index after the last sample run.
    """
    o_stats = m + 3 * n + 2 * p
    o_yest = m + 3 * n + 3 * p + 4
    N = U.shape[0]
    clock[2] = 0.0
    for i in range(start, N):
        b = bidx[i]
        now = clock[0] + dts[i]
        prm[0] = dts[i]
        prm[5] = coefs[b]
        prm[8] = 1.0 if now - clock[1] >= dwell else 0.0
        prm[10] = float(int(clock[3]) % ring_len)
        _fuzzy_ukf_step(blocks[b], U[i], Y[i], prm, st, centres, counts, cons, var, rule_idx,
                        rule_w, wk, out, n, m, p, max_mf)
        clock[0] = now
        nan = False
        for a in range(m):
            gamma_out[i, a] = out[a]
            if out[a] != out[a]:
                nan = True
        for r in range(p):
            yest_out[i, r] = out[o_yest + r]
        nis_out[i] = out[o_stats]
        if out[o_stats + 3] > 0.0:
            clock[2] = 1.0  # steps is counted by the caller, after the event (as step())
            return i + 1
        clock[3] += 1.0
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
    (15)-(49)) that returns to Python only when the structure test (20) fires (the onset
    search and re-processing of `FuzzyUKF._structure_event`) and stops at a NaN gamma^.
    Without the JIT (AOT or interpreted kernel) it calls `est.step` row by row. Leaves
    `est` as the last `step` would, `est.out` included.
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
    first = 0
    if est._needs_init:  # the start (`start_state`) and the first sample, as step() does
        out = est.step(U[0], Y[0], float(dts[0]))
        gamma[0] = out.gamma
        y_est[0] = out.y_est
        nis[0] = out.nis
        rules[0] = out.rules
        event[0] = out.structure_event
        first = 1
        if out.gamma.max() != out.gamma.max():
            return ManySteps(1, gamma, y_est, nis, rules, event, True)
        if N == 1:
            return ManySteps(1, gamma, y_est, nis, rules, event, False)
    uniq, inv = np.unique(dts, return_inverse=True)
    entries = []
    for d in uniq.tolist():
        blk = est._blocks.get(d)
        entries.append(blk if blk is not None else est._block(d))
    blocks = np.ascontiguousarray(np.stack([e[0] for e in entries]))
    coefs = np.array([e[1] for e in entries])
    bidx = inv.astype(np.int64).reshape(-1)
    clock = np.array([est._time, est._last_event, 0.0, float(est.steps)])
    fz = est.fuzzy
    cfg = est.config
    i = first
    nan = False
    while i < N:
        start = i
        i = _fuzzy_ukf_loop(blocks, coefs, bidx, dts, U, Y, est._prm, est._st, fz.centres,
                            fz.counts, fz.cons, fz.var, fz.rule_idx, fz.rule_w, est._wk,
                            est._out, n, m, p, fz.max_mf, clock, cfg.dwell, est._ring_len,
                            start, gamma, y_est, nis)
        rules[start:i] = est.out.rules
        est._time = float(clock[0])
        est.out.structure_event = False
        if clock[2] == 1.0:  # the test fired on sample i - 1: the event, as in step()
            est.steps = int(clock[3])
            est._u[:] = U[i - 1]
            est._y[:] = Y[i - 1]
            if est._structure_event():
                est.out.structure_event = True
                est.out.rules = fz.rule_count
                event[i - 1] = True
            rules[i - 1] = est.out.rules
            # the event may have re-processed: the output of sample i - 1 is the new one
            gamma[i - 1] = est.out.gamma
            y_est[i - 1] = est.out.y_est
            nis[i - 1] = est._stats[0]
            clock[1] = est._last_event
            clock[3] += 1.0
            if gamma[i - 1].max() != gamma[i - 1].max():
                nan = True
        elif clock[2] == 2.0:
            nan = True
        if nan:
            break
    est.steps = int(clock[3])
    est.out.nis = float(nis[i - 1])
    est._u[:] = U[i - 1]
    est._y[:] = Y[i - 1]
    return ManySteps(i, gamma, y_est, nis, rules, event, nan)
