"""The fuzzy UKF's step kernel: one sample, eqs (50)-(54) around (15)-(49), compiled.

Per sample k (the paper's order, made sound where Liu et al. 2020 is ambiguous or broken;
Liu, Bao, Xue, Du, Int. J. Fuzzy Systems 22(1), 2020):

1. The fuzzy system (17), (51) evaluated at the previous input z_{k-1} gives gamma^_k and
   the fault function f^_k = -B diag(u_k) gamma^_k (10). The paper's f^ in R^n is not
   observable from one current (rank 3 of 4); f lives in span(B), so the consequents are
   the per-actuator losses gamma and f^ is built from them. When other rules fire than
   at the previous sample, gamma^ changes, and the state follows it (step 6).
2. UKF time update (32)-(43) with the fault term: x^- = A x^ + B u + f^ (35), and the
   sensitivity of the prior to gamma, V^- = A V - B diag(u). A model with Coulomb
   friction adds its term b_f phi as a known input (`monitor.estimation.friction`).
3. UKF measurement update (44)-(49): the innovation nu = y - y^- (the output error e of
   (20) between the plant and the fault model (53)) and its covariance P_yy.
4. The random walk of the fault (11), (14), (54) adds q_gamma dt to the variance of
   gamma, but at most growth_share dt / (M' P_yy^-1 M), and at most twice what the
   sample's evidence takes away: see (e) and (f) below. The innovation
   covariance with the fault's uncertainty is S_tot = P_yy + M pg M', M = C V^- - D diag(u)
   (nu ~ M (gamma - gamma^)), pg the variance of gamma^; NIS = nu' S_tot^-1 nu.
5. Structure-learning test (20), before the adaptation: the paper's test |e| > 1e-5 on
   the raw current error fires every sample (noise sigma is 0.5 A). Here e is whitened
   (w = L^-1 nu, L L' = S_tot) and averaged exponentially over a short window; the
   average's chi-square statistic (p degrees of freedom when the model fits, at any
   sample rate) must exceed a threshold, with a dwell time between two events. Keeping
   the sign makes a persistent bias -- what a changed fault produces -- far more visible
   than the squared NIS would. A second, slow average (`slow_window`, 0.2 s) of
   nu + M (gamma^ - gamma_slow), whitened by the same factor, catches a change whose effect
   grows over many samples (a loss at a low input on a slow armature: about one noise unit
   a sample, under the short average's threshold in every window of it, and partly taken
   up by gamma^'s own least squares as it comes, which the correction by gamma_slow, gamma^'s
   average over the same window, gives back). Its statistic is in units of its own
   long-run spread (SLOW_SPREAD_WINDOWS windows, never below a white innovation's), since
   a model that leaves the innovations coloured makes it wander further than white noise;
   the spread learns only from samples whose statistic is under SLOW_SPREAD_SHARE of its
   threshold, since a change the average is building up to find would otherwise teach it
   its own size (a loss on a learned model under a stepping input: the statistic held at
   12-13 of 14 for 0.4 s while the spread tripled);
   an event that the slow average alone starts must locate a jump at least
   `slow_min_jump` beyond one posterior standard deviation (structure.py). What an event
   does is below (b).
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
   rejects (stat > nis_threshold; not the slow one's, whose window is the learning's
   scale) or a structure event's onset does not adapt, the cap
   bounds what a sample the test has not yet caught can add (R grows at most by 8 d a
   sample), and noise_window (2 s) is far longer than the
   classifier's dwell and the onset window. A persistent bias too small for the test (a
   small unmodelled load) is partly learnt as noise; a large one stays visible to the
   mismatch detector. rx is part of the onset ring: a structure event re-processes from
   the learnt noise of its onset.
5c. Adaptive process noise (`process_noise_gain`; off with `adaptive_noise`): a real plant
   is also disturbed more than the model's Q says (torque ripple, a load that wanders).
   Then the filter tracks too slowly, and the innovations, white under the right Q, are
   positively correlated from sample to sample; their excess variance alone does not tell
   Q from R (step 5b takes it), their correlation does (Mehra, IEEE Trans. Automatic
   Control 15(2), 1970: the innovations of the optimal gain are white). The plant's part
   of Q is scaled by exp(qs) >= 1, and qs follows the correlation:

       qs <- clip(qs + g d clip((w_k-1 - w_mean)' (w_k - w_mean) / p, -1, 1), 0, ln 100)

   w the whitened innovations, w_mean their long-run mean (the same weight d as 5b), g the
   gain. The clipped product is sign-like, 0 in expectation for white innovations of any
   size, and bounds what one sample moves. About the mean, since a load or an offset is a
   mean shift for the bias states (step 8), not process noise; only while the structure
   test watches and passes, as for rx. On the paper's motor with 5x its process noise the
   model's Q left gamma^ wandering to 0.43 with 20 structure events a minute; the scale
   settles near 3.6 within about 10 s and gamma^ stays below 0.12. A model whose
   innovations are coloured for another reason (dynamics it lacks) gets a larger Q too,
   which whitens them at some cost in sensitivity to gamma; the cap keeps some.
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

After the sample, OUT's `output_noise` ((R_ii + rx_i) / R_ii) and `process_noise`
(exp(qs)) give the noises of steps 5b and 5c as factors on the model's, as the next sample
uses them: 1 where the model's noises fit.

Why the update is built this way (the object API, `monitor.estimation.fuzzy_ukf`, gives
the failures on a stiff servo that led here; (a), (b), (g), (i) are the structure event's,
`monitor.estimation.structure`):

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
(f) No evidence, no forgetting: where the output shows nothing of gamma (M = 0: a motor
    idle at 0 V, a speed held by a spring between its input's steps), q_gamma dt a sample
    would widen gamma's variance without bound ("covariance windup" of a forgetting
    estimator, Kulhavy 1987, Automatica 23(5)), and the first noisy samples after the next
    command move gamma^ as far as that variance allows: the paper's motor, healthy, idle
    30 s, read 0.35-0.54 on its restart, and a spring-held speed held 9 s read 0.149. So the
    growth is capped at twice the variance the sample's evidence removes (M' P_yy^-1 M
    vc^2, for a scalar gamma directional forgetting): in the information-rich steady state
    the random walk's own level holds (there the growth equals the removal), below it the
    variance still climbs, and without evidence it stays. An abrupt change during a silence
    of evidence is the structure test's (20) to find when evidence returns (b).

A missed sample is a step with dt = k T: the ZOH model for that span holds the last
voltage, which is what the ECU does, and the covariance grows accordingly.

Any linear model runs (`monitor.estimation.model`: n states, m actuators, p outputs). Only
the actuators in `model.fault_inputs` have a loss of effectiveness; the others are known
inputs. They enter B and D like the rest, but their projection bounds of (28) are
[u_L, u_U] = [0, 0]: the kernel reads an actuator with equal bounds as known, so its gamma
stays exactly 0, its consequents carry no variance (they add nothing to S_tot), are never
adapted and are not re-opened by structure learning.

`fuzzy_ukf_step` runs on the flat buffers of `monitor.estimation.layout`; `step_loop` runs
it over many samples and `reprocess_loop` over the ring again after a structure event, one
compiled call each. `select_kernel` chooses the JIT, the ahead-of-time build
(`monitor.estimation.kernels_aot`) or the interpreted code.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from monitor.estimation.friction import coulomb
from monitor.estimation.fuzzy import fire, infer
from monitor.estimation.layout import FRICTION, KERNEL_LAYOUT, MODEL, OUT, PRM, RING, STATE, WORK
from monitor.estimation.ukf import mat_vec_add, spd_inverse, ukf_predict, ukf_update
from monitor.jit import njit

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["HELD_EVENT", "JUMP_EVENT", "fuzzy_ukf_step", "kernel_layout", "reprocess_loop",
           "select_kernel", "step_loop"]

_log = logging.getLogger(__name__)

# The adaptive output noise (step 5b) lets a sample raise the output noise by at most
# (this - 1) times itself, times the forgetting weight: a burst the mean-shift test has not
# caught yet moves R by a bounded step, and a fitting model loses < 1 % to the cap.
_NOISE_CLIP = 9.0

# The adaptive process noise (step 5c) scales Q by at most e^this (100): a model whose
# innovations stay coloured for another reason (dynamics it lacks) keeps some gain on gamma.
_PROCESS_LOG_MAX = math.log(100.0)

# The long-run spread of the slow average (step 5) is learnt over this many of its windows:
# long enough that a change the slow average must find (within one window) moves it little.
SLOW_SPREAD_WINDOWS = 10.0
# ... and only from samples whose slow statistic is under this share of its threshold: a
# change that builds up over several windows would otherwise raise the spread as fast as
# the average and never cross. Of a Gaussian average's spread this learns 0.92 (one
# output) or 0.83 (two): where it is above a white innovation's (a coloured model), the
# slow test fires a little more often, and its events must still locate a jump.
SLOW_SPREAD_SHARE = 0.5

# The structure modes of a sample (`prm`'s mode) that start with a structure event of
# gamma: a jump at this sample (the two-stage raise of gamma's variance: the state before
# it stays as it was), or gamma^ wrong since before it and the state with it (the variance
# raised alone, V and P kept); which, `monitor.estimation.structure` decides
JUMP_EVENT = 2.0
HELD_EVENT = 3.0

# The random walk of gamma (step 4) adds at most this many times the variance the sample's
# evidence takes away (M' P_yy^-1 M vc^2): old evidence fades as new evidence comes in, and
# a sample that shows nothing of gamma widens nothing (directional forgetting, (f) below).
# Above 1 the variance still climbs from below to the random walk's own level.
_FORGET_PER_EVIDENCE = 2.0

# Where each field starts in `layout.offsets` (its end is the next entry): globals, which
# numba compiles in as constants. numba keys its cache by this file's source, so an edit of
# the tables (which changes `KERNEL_LAYOUT`) must come with an edit here to be recompiled.
(_A, _B, _Q, _C, _D, _R) = MODEL.at_each("A", "B", "Q", "C", "D", "R")
_MODEL_END = MODEL.at("R") + 1  # the model block's size: its FRICTION follows
(_F, _S, _FR) = FRICTION.at_each("F", "S", "fr")
(_DT, _DELTA, _WI, _QG, _VMAX, _NISC, _VREOPEN, _THR, _MODE, _SHARE, _SLOT, _VRULE, _LO, _HI,
 _NOISEC, _SLOWR, _SLOWT, _PROCC) = PRM.at_each(
    "dt", "delta", "wi", "q_gamma", "var_max", "nis_coef", "var_reopen", "nis_threshold",
    "mode", "growth_share", "slot", "var_rule", "lower", "upper", "noise_coef", "slow_ratio",
    "slow_threshold", "process_coef")
(_X, _P, _V, _Z, _VC, _RX, _QS, _WPREV, _WMEAN) = STATE.at_each(
    "x", "P", "V", "z", "vc", "rx", "qs", "w_prev", "w_mean")
_STATE_END = STATE.base + len(STATE)
(_R_X, _R_P, _R_V, _R_Z, _R_EBAR, _R_GAMMA, _R_VC, _R_U, _R_Y, _R_DT, _R_K, _R_STI, _R_NU,
 _R_RX, _R_EBARS, _R_GBAR, _R_VSLOW, _R_QS, _R_WPREV, _R_WMEAN) = RING.at_each(
    "x", "P", "V", "z", "ebar", "gamma", "vc", "u", "y", "dt", "K", "Sti", "nu", "rx",
    "ebar_slow", "gamma_slow", "var_slow", "qs", "w_prev", "w_mean")
_RING_END = RING.base + len(RING)
(_O_GAMMA, _O_FAULT, _O_XTILDE, _O_XE, _O_YHAT, _O_INNOV, _O_STATS, _O_EBAR,
 _O_YEST, _O_GSD, _O_EBARS, _O_GBAR, _O_VSLOW, _O_ONOISE, _O_PNOISE) = OUT.at_each(
    "gamma", "fault", "x_tilde", "x_e", "y_hat", "innovation", "stats", "ebar", "y_est",
    "gamma_sd", "ebar_slow", "gamma_slow", "var_slow", "output_noise", "process_noise")
(_W_UF, _W_DG, _W_PG, _W_B, _W_D, _W_S, _W_XP, _W_XQ, _W_YOFF, _W_DY, _W_NU, _W_L, _W_IKC,
 _W_T1, _W_PP, _W_PQ, _W_LS, _W_PYY, _W_PYY_INV, _W_ST, _W_STI, _W_PXY, _W_K, _W_VP, _W_M,
 _W_RA, _W_WSLOW, _W_QA) = WORK.at_each(
    "uf", "dg", "pg", "b", "d", "s", "xp", "xq", "yoff", "dy", "nu", "L", "IKC", "T1", "Pp",
    "Pq", "Ls", "Pyy", "Pyy_inv", "St", "Sti", "Pxy", "K", "Vp", "M", "Ra", "w_slow", "Qa")


def kernel_layout() -> int:
    """The buffer layout this kernel reads (exported into the AOT module as well)."""
    return KERNEL_LAYOUT


@njit
def _vec(buf: Array, lay: IntArray, f: int, base: int) -> Array:
    """Field f (an index into lay) of a flat buffer whose fields start at `base`."""
    return buf[base + lay[f]:base + lay[f + 1]]


@njit
def _mat(buf: Array, lay: IntArray, f: int, base: int, rows: int, cols: int) -> Array:
    """Field f of a flat buffer as a (rows, cols) matrix (a view)."""
    return buf[base + lay[f]:base + lay[f + 1]].reshape((rows, cols))


@njit
def _rule_variance(var: Array, rule_idx: IntArray, rule_w: Array, nf: int, a: int) -> float:
    """sum xi_j^2 var_j over the firing rules: the part of the variance of the fuzzy output
    gamma^_a = sum xi_j a_j that the rules' own deviations (independent) contribute."""
    acc = 0.0
    for k in range(nf):
        acc += rule_w[k] * rule_w[k] * var[rule_idx[k], a]
    return acc


@njit
def fuzzy_ukf_step(
    mdl: Array, u: Array, y: Array, prm: Array, st: Array,
    centres: Array, counts: IntArray, cons: Array, var: Array, rule_idx: IntArray, rule_w: Array,
    wk: Array, out: Array, lay: IntArray, n: int, m: int, p: int, max_mf: int,
) -> None:
    """One sample of the fuzzy UKF, steps 0-7 of the module docstring, on flat buffers.

    mdl: a `MODEL` block, its `FRICTION` after it; prm: the sample's `PRM` (mode 0: no
    structure test, the dwell time; 1: test, stats[3] = 1 when it fires; JUMP_EVENT (2) or
    HELD_EVENT (3): a structure event at the start of this sample, the caller re-processes
    from the onset of a change;
    slot: this sample's place in the onset ring); st: the `STATE`, then the ring of `RING`
    slots; out: `OUT`; wk: `WORK`; lay: `monitor.estimation.layout.offsets` (n, m, p).
    centres .. rule_w: the rule base (`SelfConstructingFuzzySystem`) over the plant's
    states, the first centres.shape[0] entries of z.
    """
    # ---- views into the flat buffers, by the offsets of `monitor.estimation.layout`
    # (slices and reshapes allocate nothing)
    A = _mat(mdl, lay, _A, 0, n, n)
    B = _mat(mdl, lay, _B, 0, n, m)
    Q = _mat(mdl, lay, _Q, 0, n, n)
    C = _mat(mdl, lay, _C, 0, p, n)
    D = _mat(mdl, lay, _D, 0, p, m)
    R = _mat(mdl, lay, _R, 0, p, p)
    fb = lay[_MODEL_END]
    Fc = _vec(mdl, lay, _F, fb)
    Sf = _vec(mdl, lay, _S, fb)
    fr = _vec(mdl, lay, _FR, fb)
    dt = prm[lay[_DT]]
    delta = prm[lay[_DELTA]]
    wi = prm[lay[_WI]]
    q_gamma = prm[lay[_QG]]
    var_max = prm[lay[_VMAX]]
    nis_coef = prm[lay[_NISC]]
    var_reopen = prm[lay[_VREOPEN]]
    threshold = prm[lay[_THR]]
    mode = prm[lay[_MODE]]
    share = prm[lay[_SHARE]]
    var_rule = prm[lay[_VRULE]]
    # per-actuator projection bounds of (28); lo[a] == hi[a] marks a known actuator (no
    # loss of effectiveness): its consequents are fixed, carry no variance, never adapt
    lo = _vec(prm, lay, _LO, 0)
    hi = _vec(prm, lay, _HI, 0)
    noise_coef = prm[lay[_NOISEC]]
    slow_ratio = prm[lay[_SLOWR]]
    slow_threshold = prm[lay[_SLOWT]]
    process_coef = prm[lay[_PROCC]]
    x = _vec(st, lay, _X, 0)
    P = _mat(st, lay, _P, 0, n, n)
    V = _mat(st, lay, _V, 0, n, m)
    z = _vec(st, lay, _Z, 0)
    vc = _vec(st, lay, _VC, 0)
    rx = _vec(st, lay, _RX, 0)
    qs = _vec(st, lay, _QS, 0)
    w_prev = _vec(st, lay, _WPREV, 0)
    w_mean = _vec(st, lay, _WMEAN, 0)
    # the onset ring follows the state, one slot per sample
    o = lay[_STATE_END] + int(prm[lay[_SLOT]]) * lay[_RING_END]
    r_x = _vec(st, lay, _R_X, o)
    r_P = _mat(st, lay, _R_P, o, n, n)
    r_V = _mat(st, lay, _R_V, o, n, m)
    r_z = _vec(st, lay, _R_Z, o)
    r_ebar = _vec(st, lay, _R_EBAR, o)
    r_gamma = _vec(st, lay, _R_GAMMA, o)
    r_vc = _vec(st, lay, _R_VC, o)
    r_u = _vec(st, lay, _R_U, o)
    r_y = _vec(st, lay, _R_Y, o)
    r_dt = _vec(st, lay, _R_DT, o)
    r_K = _mat(st, lay, _R_K, o, n, p)
    r_Sti = _mat(st, lay, _R_STI, o, p, p)
    r_nu = _vec(st, lay, _R_NU, o)
    r_rx = _vec(st, lay, _R_RX, o)
    r_ebar_slow = _vec(st, lay, _R_EBARS, o)
    r_gamma_slow = _vec(st, lay, _R_GBAR, o)
    r_var_slow = _vec(st, lay, _R_VSLOW, o)
    r_qs = _vec(st, lay, _R_QS, o)
    r_w_prev = _vec(st, lay, _R_WPREV, o)
    r_w_mean = _vec(st, lay, _R_WMEAN, o)
    gamma = _vec(out, lay, _O_GAMMA, 0)
    fhat = _vec(out, lay, _O_FAULT, 0)
    xtilde = _vec(out, lay, _O_XTILDE, 0)
    xe = _vec(out, lay, _O_XE, 0)
    yhat = _vec(out, lay, _O_YHAT, 0)
    innov = _vec(out, lay, _O_INNOV, 0)
    stats = _vec(out, lay, _O_STATS, 0)
    ebar = _vec(out, lay, _O_EBAR, 0)
    yest = _vec(out, lay, _O_YEST, 0)
    gsd = _vec(out, lay, _O_GSD, 0)
    ebar_slow = _vec(out, lay, _O_EBARS, 0)
    gamma_slow = _vec(out, lay, _O_GBAR, 0)
    var_slow = _vec(out, lay, _O_VSLOW, 0)
    onoise = _vec(out, lay, _O_ONOISE, 0)
    pnoise = _vec(out, lay, _O_PNOISE, 0)
    uf = _vec(wk, lay, _W_UF, 0)
    dg = _vec(wk, lay, _W_DG, 0)
    pg = _vec(wk, lay, _W_PG, 0)
    b = _vec(wk, lay, _W_B, 0)
    d = _vec(wk, lay, _W_D, 0)
    s = _vec(wk, lay, _W_S, 0)
    xp = _vec(wk, lay, _W_XP, 0)
    xq = _vec(wk, lay, _W_XQ, 0)
    yoff = _vec(wk, lay, _W_YOFF, 0)
    dy = _vec(wk, lay, _W_DY, 0)
    nu = _vec(wk, lay, _W_NU, 0)
    L = _mat(wk, lay, _W_L, 0, n, n)
    IKC = _mat(wk, lay, _W_IKC, 0, n, n)
    T1 = _mat(wk, lay, _W_T1, 0, n, n)
    Pp = _mat(wk, lay, _W_PP, 0, n, n)
    Pq = _mat(wk, lay, _W_PQ, 0, n, n)
    Ls = _mat(wk, lay, _W_LS, 0, p, p)
    Pyy = _mat(wk, lay, _W_PYY, 0, p, p)
    Pyy_inv = _mat(wk, lay, _W_PYY_INV, 0, p, p)
    St = _mat(wk, lay, _W_ST, 0, p, p)
    Sti = _mat(wk, lay, _W_STI, 0, p, p)
    Pxy = _mat(wk, lay, _W_PXY, 0, n, p)
    K = _mat(wk, lay, _W_K, 0, n, p)
    Vp = _mat(wk, lay, _W_VP, 0, n, m)
    M = _mat(wk, lay, _W_M, 0, p, m)
    Ra = _mat(wk, lay, _W_RA, 0, p, p)
    w_slow = _vec(wk, lay, _W_WSLOW, 0)
    Qa = _mat(wk, lay, _W_QA, 0, n, n)

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
        r_ebar_slow[r] = ebar_slow[r]
        r_var_slow[r] = var_slow[r]
        r_y[r] = y[r]
        r_rx[r] = rx[r]
        r_w_prev[r] = w_prev[r]
        r_w_mean[r] = w_mean[r]
    r_qs[0] = qs[0]
    for a in range(m):
        r_gamma[a] = gamma[a]
        r_gamma_slow[a] = gamma_slow[a]
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
        # of the new one moves the state only as far as the jump has acted on it. A
        # HELD_EVENT (gamma^ wrong all along) raises the variance alone: what is learnt of
        # gamma then moves the state by V, as it would have from the start.
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
            if g1 > 0.0 and mode == JUMP_EVENT:
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
            ebar_slow[r] = 0.0
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
    # Coulomb friction (`monitor.estimation.friction`, (1)): a known input of the step,
    # from the speed the model predicts over it
    phi = coulomb(A, b, x, Sf, fr[0], fr[1], dt)
    if phi != 0.0:
        for r in range(n):
            b[r] += Fc[r] * phi
    for r in range(p):
        yoff[r] = 0.0
    mat_vec_add(D, uf, 1.0, yoff)
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
    # the process noise the innovations have shown: the plant's part of Q scaled by
    # exp(qs) (step 5c), never below the model's; the bias states' random walk as it is.
    # The model's Q itself while nothing has been learnt (no copy on the common path)
    nx = centres.shape[0]
    Qs = Q
    if qs[0] > 0.0:
        scale = math.exp(qs[0])
        for r in range(n):
            for c in range(n):
                Qa[r, c] = Q[r, c] * scale if r < nx and c < nx else Q[r, c]
        Qs = Qa
    rep = ukf_predict(x, P, A, b, Qs, delta, wi, L, d, xp, Pp)
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
        yhat[r] = yoff[r]
    mat_vec_add(C, xp, 1.0, yhat)
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
            fade = _FORGET_PER_EVIDENCE * vis * vc[a] * vc[a]
            if fade < grow:
                grow = fade
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
    # the slow average (step 5 of the module docstring) of the innovation as gamma_slow,
    # gamma^'s own average over the same window, would have left it: gamma^'s least
    # squares takes up part of a slowly growing change as it comes (a creep of a few
    # hundredths a sample) and would hide it from any average of nu. In the dwell time
    # after an event gamma^ re-converges, and gamma_slow follows it at once
    slow = 0.0
    if slow_ratio > 0.0:
        slow_coef = 1.0 - (1.0 - nis_coef) ** slow_ratio
        for a in range(m):
            if mode != 1.0:
                gamma_slow[a] = gamma[a]
        for r in range(p):
            acc = nu[r]
            for a in range(m):
                acc += M[r, a] * (gamma[a] - gamma_slow[a])
            for c in range(r):
                acc -= Ls[r, c] * w_slow[c]
            w_slow[r] = acc / Ls[r, r]
        # each output's average in units of its own long-run spread (SLOW_SPREAD_WINDOWS
        # windows), never below a white innovation's: where the model leaves the innovations
        # coloured (a coarse quantum the output sits on, dynamics it lacks) the average
        # wanders further than white noise would, and a fixed threshold reads that as a
        # change; on a fitting model the spread is the white one's
        white = slow_coef / (2.0 - slow_coef)
        spread_coef = 1.0 - (1.0 - slow_coef) ** (1.0 / SLOW_SPREAD_WINDOWS)
        for r in range(p):
            ebar_slow[r] += slow_coef * (w_slow[r] - ebar_slow[r])
            v = var_slow[r] if var_slow[r] > white else white
            slow += ebar_slow[r] * ebar_slow[r] / v
        if mode == 1.0 and stat <= threshold and slow <= SLOW_SPREAD_SHARE * slow_threshold:
            for r in range(p):
                var_slow[r] += spread_coef * (ebar_slow[r] * ebar_slow[r] - var_slow[r])
        for a in range(m):
            # gamma^'s move is creep where a sample tells little of gamma, evidence where it
            # tells much (a step of the input): there gamma_slow follows as fast as the
            # sample's share of gamma's information, pg M' S_tot^-1 M
            info = 0.0
            for r in range(p):
                for c in range(p):
                    info += M[r, a] * Sti[r, c] * M[c, a]
            w = pg[a] * info
            w = w if w > slow_coef else slow_coef
            gamma_slow[a] += (w if w < 1.0 else 1.0) * (gamma[a] - gamma_slow[a])
    stats[3] = 0.0
    if mode == 1.0:
        if stat > threshold:
            stats[3] = 1.0
        elif slow > slow_threshold:
            stats[3] = 2.0
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
    # 5c. adaptive process noise: the log of Q's scale follows the whitened innovations'
    # correlation with the previous sample's, about their long-run mean, each product
    # clipped to [-1, 1] (a sign-like statistic, 0 in expectation for white innovations
    # whatever their size). A model whose Q is too small tracks too slowly and leaves them
    # positively correlated, one whose Q is too large negatively (Mehra 1970's test of
    # optimality). About the mean: a load or an offset the model lacks is a mean shift,
    # which is the bias states' to take (step 8), not process noise. Only while the
    # structure test watches and passes: a fault is a mean shift, correlated too, for
    # gamma^ to explain, and in the dwell after an event gamma^ re-converges
    if process_coef > 0.0 and mode == 1.0 and stat <= threshold:
        acc = 0.0
        for r in range(p):
            acc += (w_prev[r] - w_mean[r]) * (innov[r] - w_mean[r])
            w_mean[r] += noise_coef * (innov[r] - w_mean[r])
        acc /= p
        acc = 1.0 if acc > 1.0 else (-1.0 if acc < -1.0 else acc)
        v = qs[0] + process_coef * acc
        qs[0] = 0.0 if v < 0.0 else (_PROCESS_LOG_MAX if v > _PROCESS_LOG_MAX else v)
    for r in range(p):
        w_prev[r] = innov[r]
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
        # its standard deviation after the sample: the common part's and the firing
        # rules' own (0 for a known actuator, whose variances are 0)
        vg = vc[a] + _rule_variance(var, rule_idx, rule_w, nf, a) if hi[a] > lo[a] else 0.0
        gsd[a] = math.sqrt(vg) if vg > 0.0 else 0.0
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
    # the noises the next sample's filter uses (steps 5b, 5c), as factors on the model's:
    # what a user reads of the adaptation (a process noise far above the model's: the
    # model misses dynamics, and the state takes up more of a loss)
    for r in range(p):
        onoise[r] = (R[r, r] + rx[r]) / R[r, r] if R[r, r] > 0.0 else 1.0
    pnoise[0] = math.exp(qs[0])


@njit
def step_loop(
    blocks: Array, coefs: Array, bidx: IntArray, dts: Array, U: Array, Y: Array, prm: Array,
    st: Array, centres: Array, counts: IntArray, cons: Array, var: Array, rule_idx: IntArray,
    rule_w: Array, wk: Array, out: Array, lay: IntArray, n: int, m: int, p: int, max_mf: int,
    clock: Array, dwell: float, ring_len: int, start: int,
    gamma_out: Array, yest_out: Array, nis_out: Array, gsd_out: Array, onoise_out: Array,
    pnoise_out: Array,
) -> int:
    """`fuzzy_ukf_step` -- eqs (50)-(54) around (15)-(49) -- for samples start, start + 1,
    ... of (U, Y, dts), in compiled code.

    Sample i runs with model block ``blocks[bidx[i]]`` (the ZOH model (63)-(65) for its
    dt), NIS coefficient ``coefs[bidx[i]]``, structure mode 1 once the dwell time has passed
    since the last event (else 0) and ring slot (steps + i - start) mod ring_len: exactly
    what `FuzzyUKF.step` passes. clock = [time, time of the last structure event, reason,
    steps]. Stops after the first sample that needs Python: the structure test (20) fired
    (clock[2] = 1; the onset search and re-processing are Python's) or gamma^ is NaN
    (clock[2] = 2); returns the index after the last sample run. Row i of the ``*_out``
    arrays is sample i's `OUT`: gamma^, y_est, the NIS, gamma_sd, output_noise and
    process_noise.
    """
    o_gamma = lay[_O_GAMMA]
    o_stats = lay[_O_STATS]
    o_yest = lay[_O_YEST]
    o_gsd = lay[_O_GSD]
    o_onoise = lay[_O_ONOISE]
    o_pnoise = lay[_O_PNOISE]
    N = U.shape[0]
    clock[2] = 0.0
    for i in range(start, N):
        b = bidx[i]
        now = clock[0] + dts[i]
        prm[lay[_DT]] = dts[i]
        prm[lay[_NISC]] = coefs[b]
        prm[lay[_MODE]] = 1.0 if now - clock[1] >= dwell else 0.0
        prm[lay[_SLOT]] = float(int(clock[3]) % ring_len)
        fuzzy_ukf_step(blocks[b], U[i], Y[i], prm, st, centres, counts, cons, var, rule_idx,
                       rule_w, wk, out, lay, n, m, p, max_mf)
        clock[0] = now
        nan = False
        for a in range(m):
            g = out[o_gamma + a]
            gamma_out[i, a] = g
            gsd_out[i, a] = out[o_gsd + a]
            if g != g:
                nan = True
        for r in range(p):
            yest_out[i, r] = out[o_yest + r]
            onoise_out[i, r] = out[o_onoise + r]
        pnoise_out[i] = out[o_pnoise]
        nis_out[i] = out[o_stats]
        if out[o_stats + 3] > 0.0:
            clock[2] = 1.0  # steps is counted by the caller, after the event (as step())
            return i + 1
        clock[3] += 1.0
        if nan:
            clock[2] = 2.0
            return i + 1
    return N


@njit
def reprocess_loop(
    blocks: Array, coefs: Array, bidx: IntArray, ring: Array, first: int, count: int,
    ring_len: int, prm: Array, st: Array, centres: Array, counts: IntArray, cons: Array,
    var: Array, rule_idx: IntArray, rule_w: Array, wk: Array, out: Array, lay: IntArray,
    n: int, m: int, p: int, max_mf: int, u: Array, y: Array, first_mode: float,
) -> None:
    """Samples first .. first + count - 1 of the ring again through `fuzzy_ukf_step`, the
    first in first_mode (JUMP_EVENT or HELD_EVENT: a structure event of gamma; 0: none, a
    bias event having re-opened the biases), the others without the test (mode 0): what
    `FuzzyUKF._reprocess` does one Python call per sample, in one compiled call."""
    o_u = lay[_R_U]
    o_y = lay[_R_Y]
    o_dt = lay[_R_DT]
    for t in range(count):
        k = first + t
        row = ring[k % ring_len]
        for a in range(m):
            u[a] = row[o_u + a]
        for r in range(p):
            y[r] = row[o_y + r]
        prm[lay[_DT]] = row[o_dt]
        prm[lay[_NISC]] = coefs[bidx[t]]
        prm[lay[_MODE]] = first_mode if t == 0 else 0.0
        prm[lay[_SLOT]] = float(k % ring_len)
        fuzzy_ukf_step(blocks[bidx[t]], u, y, prm, st, centres, counts, cons, var, rule_idx,
                       rule_w, wk, out, lay, n, m, p, max_mf)


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
        return "python", getattr(fuzzy_ukf_step, "py_func", fuzzy_ukf_step)
    return ("python" if jit_off else "jit"), fuzzy_ukf_step

