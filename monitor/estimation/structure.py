"""Structure learning of the fuzzy UKF (20)-(22): the onset of a change, re-learning from
it, and a new membership function where it shows.

The kernel (`monitor.estimation.kernel`, step 5) runs the test (20) on every sample; when it
fires, `structure_event` locates the change's onset over the ring of past samples
(`locate_onset`, the GLR of Willsky and Jones 1976, compiled in `onset_glr`), goes back to
the state before it and processes the samples since again with the event first
(`reprocess`), then inserts a membership function (`SelfConstructingFuzzySystem.insert`,
output-preserving (23)-(27)). A jump the bounds of (28) cannot take is a bias event
(`monitor.estimation.bias`, step 8). Why (Liu, Bao, Xue, Du, Int. J. Fuzzy Systems 22(1),
2020, made sound on a small, stiff, back-EMF dominated motor -- a 24 V servo at 1 kHz:
J = 2e-5, b = 1e-5, Ke = Ki = 0.03, Ra = 1, La = 1e-3, sensor sigma 0.01 A):

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
(i) An event has a second reading: no jump, but gamma^ wrong since before the window and
    the state with it, as the filter's sensitivity V says -- the same likelihood ratio with
    the signature started from V at the window's first sample instead of 0 at an onset,
    the same prior. Where it scores higher than every onset's jump and its correction
    stands `HELD_MIN_Z` posterior standard deviations from 0, the event raises gamma's
    variance alone at the window's first sample, V and P kept (`HELD_EVENT`), and the
    samples since are processed again. Why:
    where the output shows gamma and the state only together while the input holds (a
    speed held by a spring: the angle settles where the actuator's torque puts it,
    whatever gamma^ says, and the speed is 0 either way), a gamma^ learnt wrong leaves the
    state at the equilibrium of the wrong torque. At the input's next step gamma^'s update
    moves both back, but the jump reading puts gamma^ back again, since from that state
    the step's response is what the old gamma^ predicts: the rig zoo's seed 24 (a
    spring-held speed on two masses, a learned model of order 5) held a false 0.25 for
    4.9 s after an outage, events at three steps putting it back each time; read as held,
    the first step clears it.
(g) Cost, bounded per sample whatever the frame loss (an unbounded cost starves a
    one-CPU daemon under a CAN flood). A sample costs one kernel call (35)-(54) plus its
    ring slot. The structure test (20) can fire at most once per dwell time (a negligible
    jump restarts the dwell too), and only then does a sample pay for the onset search and
    the re-processing, both over the ring: ring_len = onset_window / T + 1 samples, where a
    lost stretch is one slot (one step of dt = k T), so loss never lengthens it. A firing of
    the slow average alone whose jump is negligible restarts that average from 0, not the
    dwell: it fires again only once its average has built up anew from innovations that
    keep the short test quiet, whose mean is then under sqrt(nis_window / slow_window) =
    1/2 of what the slow test needs, so that building up takes ln 2 = 0.69 of its window
    (about 0.14 s) at any rate: the searches stay about as rare. The search
    is O(ring_len^2) up to `max_onsets` samples and two-stage above (a coarse grid of onsets,
    then around its best: O(ring_len (max_onsets + 2 ring_len / max_onsets))); with the JIT
    it and the re-processing (at most ring_len kernel calls) run compiled, one call each.
    The estimator's restart after a long gap reuses the model's stationary covariance.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from monitor.estimation.bias import BIAS_CONFIRM, beyond_bounds
from monitor.estimation.kernel import HELD_EVENT, JUMP_EVENT, reprocess_loop
from monitor.estimation.layout import MODEL, RING
from monitor.estimation.state import FilterState
from monitor.jit import njit

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["StructureLearning", "onset_glr", "onset_scores"]

# Where the fields onset_glr reads start in `layout.offsets`. numba compiles them in and
# caches the result against this file alone: a change of layout's tables that moves them
# (a field added to any table before RING) must come with an edit of this file, or a
# cache from before keeps the old places
_R_U, _R_K, _R_STI, _R_NU = (RING.at(f) for f in ("u", "K", "Sti", "nu"))
_A, _B, _C, _D = (MODEL.at(f) for f in ("A", "B", "C", "D"))

HELD_MIN_Z = 5.0
"""An event is read as gamma^ wrong since before the window rather than as a jump at an
onset where that reading scores higher and its correction of gamma^ is at least this many
posterior standard deviations: it moves the state with gamma^, so a weak preference is not
enough. On the rig zoo, misreadings were corrections at 2.7-3.4 standard deviations
(scores 3.2-5.0; seed 80, a current with friction and an offset: a true loss of 0.3 pulled
down to 0.03-0.09 for 0.15-0.19 s, three times; seed 73, a DC motor's current: an outage
read as a loss of 0.62 for 1.2 s), the one it is for at 9 (seed 24, below)."""


@njit
def _product_less(out: Array, block: Array, at: int, X: Array, less: Array) -> None:
    """out = F X - less, with F the out.shape[0] x X.shape[0] matrix stored row by row in
    block[at:] (a model block's A or C): the signature's two steps W <- A W - B_F u and
    M = C W - D_F u of `onset_glr`."""
    inner = X.shape[0]
    for r in range(out.shape[0]):
        for a in range(out.shape[1]):
            acc = -less[r, a]
            for q in range(inner):
                acc += block[at + r * inner + q] * X[q, a]
            out[r, a] = acc


@njit
def onset_glr(
    blocks: Array, bidx: IntArray, ring: Array, first: int, count: int, ring_len: int,
    lay: IntArray, faulty: IntArray, n: int, m: int, p: int, cands: IntArray, W: Array,
    g: Array, info: Array,
) -> None:
    """The sufficient statistics of the onset search (20) over ring samples first ..
    first + count - 1 (see `locate_onset`), in compiled code: for every candidate onset
    first + cands[c] (cands sorted, in [0, count)), g[c] = sum_i M_i(c)' S_i^-1 nu_i and
    info[c] = sum_i M_i(c)' S_i^-1 M_i(c), with the signature of a jump at the candidate
    propagated through the filter as it ran (K, S_tot^-1, nu of each sample from the
    ring, eqs (44)-(49)): W <- A W - B_F u (the response of the prior (35)-(39)),
    M = C W - D_F u, W <- (I - K C) W + K D_F u. W[c] holds candidate c's state
    sensitivity before its onset (n x f; zero for a jump at the onset, the filter's own V
    for a gamma wrong since before it) and is overwritten. blocks[bidx[t]] is the flat
    model block of sample first + t (`layout.MODEL`, one per distinct dt), the ring's
    slots `layout.RING` (lay: `layout.offsets`). O(count len(cands) n^2 f) flops.
    """
    f = faulty.shape[0]
    nc = cands.shape[0]
    Wm = np.zeros((n, f))
    Mi = np.zeros((p, f))
    SM = np.zeros((p, f))
    Du = np.zeros((p, f))
    Bu = np.zeros((n, f))
    o_u, o_K, o_Sti, o_nu = lay[_R_U], lay[_R_K], lay[_R_STI], lay[_R_NU]
    oA, oB, oC, oD = lay[_A], lay[_B], lay[_C], lay[_D]
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
            _product_less(Wm, mdl, oA, Wc, Bu)
            _product_less(Mi, mdl, oC, Wm, Du)
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


def onset_scores(g: Array, info: Array, vr: float) -> tuple[Array, Array]:
    """Log marginal likelihood ratio of a jump at each candidate, and the jump."""
    f = g.shape[1]
    if f == 1:  # one fault actuator: the same formulas without batched LAPACK calls
        d = info[:, 0, 0]
        s1 = g / (d + 1.0 / vr)[:, None]
        return 0.5 * g[:, 0] * s1[:, 0] - 0.5 * np.log1p(vr * d), s1
    sol = np.asarray(np.linalg.solve(info + np.eye(f) / vr, g[..., None])[..., 0], np.float64)
    score: Array = 0.5 * np.einsum("ca,ca->c", g, sol) \
        - 0.5 * np.linalg.slogdet(np.eye(f) + vr * info)[1]
    return score, sol


def posterior_sd(info: Array, vr: float) -> Array:
    """The posterior standard deviation of each fault actuator's jump, from one candidate's
    information `info` (f x f) and the prior variance vr (`onset_scores`'s jump)."""
    return np.asarray(np.sqrt(np.diag(np.linalg.inv(info + np.eye(info.shape[0]) / vr))),
                      np.float64)


class StructureLearning(FilterState):
    """The fuzzy UKF's structure learning (20)-(22), as methods of the filter
    (`monitor.estimation.fuzzy_ukf.FuzzyUKF` inherits them): they read and rewind the
    filter's own state, its onset ring and kernel buffers."""

    def _ring_models(self, first: int, count: int) -> tuple[Array, Array, IntArray]:
        """The flat model blocks and NIS coefficients of the distinct dt among ring samples
        first .. first + count - 1 (from the `_block` cache; k T after lost samples), and
        each sample's index into them: a few blocks, not one per sample."""
        L = self._ring_len
        dts = self._ring[(first + np.arange(count)) % L, RING.span("dt", *self._dims)[0]]
        if dts.min() == dts.max():  # no loss in the window: one block (the common case)
            blk = self._block(float(dts[0]))
            return blk[0][None, :], np.array([blk[1]]), np.zeros(count, np.int64)
        uniq, inv = np.unique(dts, return_inverse=True)
        entries = [self._block(d) for d in uniq.tolist()]
        return (np.stack([e[0] for e in entries]), np.array([e[1] for e in entries]),
                inv.astype(np.int64).reshape(-1))

    def _onset_stats(self, first: int, count: int, cands: IntArray,
                     models: tuple[Array, Array, IntArray], held: bool = False
                     ) -> tuple[Array, Array]:
        """(g, info) of the candidate onsets first + cands (see `locate_onset`): of a jump
        at each, or with `held` (cands then [0]) of a gamma wrong since before the window,
        whose signature starts from the filter's own sensitivity V there."""
        n, m, p = self._dims
        F = self._faulty
        f = len(F)
        start = self._field(first, "V").reshape(n, m)[:, F] if held else np.zeros((n, f))
        if self.kernel_name == "jit":
            g = np.zeros((len(cands), f))
            info = np.zeros((len(cands), f, f))
            W0 = np.empty((len(cands), n, f))
            W0[:] = start
            onset_glr(models[0], models[2], self._ring, first, count, self._ring_len,
                       self._lay, self._faulty_idx, n, m, p, cands, W0, g, info)
            return g, info
        # Without the JIT (the hardened service's AOT kernel, or interpreted): the same
        # statistics with numpy, every onset of the window at once (the held reading's
        # alone: it has one), then the candidates'
        eye = np.eye(n)
        rows = 1 if held else count
        W = np.zeros((rows, n, f))
        W[0] = start
        ga = np.zeros((rows, f))
        ia = np.zeros((rows, f, f))
        for t in range(count):
            h = min(t + 1, rows)  # the onsets started by this sample
            i = first + t
            u = self._field(i, "u")[F]
            A, B, _, C, D = self._matrices(float(self._field(i, "dt")[0]))
            K = self._field(i, "K").reshape(n, p)
            Sti = self._field(i, "Sti").reshape(p, p)
            nu = self._field(i, "nu")
            Du = D[:, F] * u
            Wm = A @ W[:h] - B[:, F] * u
            Mi = C @ Wm - Du
            SM = Sti @ Mi
            ga[:h] += np.einsum("cpa,p->ca", SM, nu)
            ia[:h] += np.einsum("cpa,cpb->cab", Mi, SM)
            W[:h] = (eye - K @ C) @ Wm + K @ Du
        return ga[cands], ia[cands]

    def _onset(self, k: int) -> tuple[int, Array, Array, float,
                                      tuple[Array, Array, IntArray]]:
        """The most likely onset of the change detected at sample k (20), the jump of
        gamma there and its posterior standard deviation (one entry per fault actuator),
        its score (the log marginal likelihood ratio against no jump), and the model
        blocks of the samples from the window's first to k (`ring_models`, for
        `reprocess`).

        For every candidate onset j in the ring (after the previous event's), a jump of
        gamma there would have shown in the innovations since as nu_i = M_i(j) dgamma, with
        the sensitivity M_i(j) of the two-stage filter started at j (V = 0 before j). Its
        marginal likelihood against no jump, with the prior dgamma ~ N(0, var_reopen), is
        g' (I + 1/var_reopen)^-1 g / 2 - log det(1 + var_reopen I) / 2 (g = sum M' S^-1 nu,
        I = sum M' S^-1 M): the generalised likelihood ratio of Willsky and Jones (1976)
        with the jump integrated out. The largest wins; its jump is (I + 1/var_reopen)^-1 g,
        with the posterior covariance (I + 1/var_reopen)^-1.

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
        vr = self.config.var_reopen
        count = k - first + 1
        models = self._ring_models(first, count)
        cap = max(2, self.config.max_onsets)
        if count <= cap:
            cands = np.arange(count, dtype=np.int64)
        else:
            s = -(-count // cap)
            cands = np.unique(np.append(np.arange(0, count, s), count - 1)).astype(np.int64)
            score, _ = onset_scores(*self._onset_stats(first, count, cands, models), vr)
            b = int(cands[int(np.argmax(score))])
            cands = np.arange(max(b - s + 1, 0), min(b + s, count), dtype=np.int64)
        # the refined candidates include the coarse best, so the argmax of this pass is
        # the best of both
        g, info = self._onset_stats(first, count, cands, models)
        score, sol = onset_scores(g, info, vr)
        best = int(np.argmax(score))
        return (first + int(cands[best]), sol[best], posterior_sd(info[best], vr),
                float(score[best]), models)

    def _held_error(self, first: int, k: int, models: tuple[Array, Array, IntArray]
                    ) -> tuple[float, Array, Array]:
        """The other reading of a change detected at sample k: gamma^ wrong by a constant
        since before the window's first sample, and the state with it, as the filter's
        sensitivity V says (`_onset`'s signature started from V at the window's first sample,
        not from 0 at an onset). Its score, the correction of gamma^ and its posterior
        standard deviation, with the same prior as a jump's."""
        vr = self.config.var_reopen
        g, info = self._onset_stats(first, k - first + 1, np.zeros(1, np.int64), models,
                                    held=True)
        score, sol = onset_scores(g, info, vr)
        return float(score[0]), sol[0], posterior_sd(info[0], vr)

    def _reprocess(self, j: int, k: int, first: int,
                  models: tuple[Array, Array, IntArray], bias: bool = False,
                  held: bool = False) -> None:
        """Back to the state before sample j, a structure event there -- of gamma (with
        held True: gamma's variance raised alone, V and P kept, `HELD_EVENT`), or with
        bias True of the biases (their variance raised by var0, step 8) -- and samples j..k
        again (k - j < ring_len samples; in one compiled call with the JIT). models: the
        model blocks of samples first..k (`ring_models`)."""
        n, m, p = self._dims
        nx = self._nx
        self.x[:] = self._field(j, "x")
        self.P[:] = self._field(j, "P").reshape(n, n)
        if bias:
            self.P[nx:, nx:] += np.diag(self._bias_var0)
        self.V[:] = self._field(j, "V").reshape(n, m)
        self._zall[:] = self._field(j, "z")
        self._ebar[:] = self._field(j, "ebar")
        self._ebar_slow[:] = self._field(j, "ebar_slow")
        self._gamma_slow[:] = self._field(j, "gamma_slow")
        self._var_slow[:] = self._field(j, "var_slow")
        self.out.gamma[:] = self._field(j, "gamma")
        self.common_var[:] = self._field(j, "vc")
        self.noise_excess[:] = self._field(j, "rx")
        self._process_log_scale[:] = self._field(j, "qs")
        self._w_prev[:] = self._field(j, "w_prev")
        self._w_mean[:] = self._field(j, "w_mean")
        # the event re-opens every consequent at that output: do it before the rules fire,
        # so that what the samples since taught them under the old fault is forgotten
        self.fuzzy.cons[:, self._faulty] = self.out.gamma[self._faulty]
        mode = 0.0 if bias else (HELD_EVENT if held else JUMP_EVENT)
        if self.kernel_name == "jit":
            fz = self.fuzzy
            reprocess_loop(models[0], models[1], models[2][j - first:], self._ring, j, k - j + 1,
                           self._ring_len, self._prm, self._st, fz.centres, fz.counts, fz.cons,
                           fz.var, fz.rule_idx, fz.rule_w, self._wk, self._out, self._lay, n, m, p,
                           fz.max_mf, self._u, self._y, mode)
            return
        for i in range(j, k + 1):
            self._u[:] = self._field(i, "u")
            self._y[:] = self._field(i, "y")
            self._run(i, float(self._field(i, "dt")[0]), mode if i == j else 0.0)

    def _negligible(self, gamma: Array, jump: Array, least: float, sd: Array | None = None
                    ) -> bool:
        """Whether the jump, projected on the bounds of (28), is below `least` for every
        fault actuator; with `sd` (the jump's posterior standard deviation), whether it
        less that is below `least` (not clearly that large)."""
        F = self._faulty
        moved = np.abs(np.clip(gamma[F] + jump, self._lower[F], self._upper[F]) - gamma[F])
        if sd is not None:
            moved = moved - sd
        return bool(F) and bool(np.all(moved < least))

    def _structure_event(self) -> bool:
        """(20)-(22): locate the change, re-learn from its onset, add an MF where it shows.

        The test fires some samples after a change began. Its onset is located (`locate_onset`),
        the filter goes back to the state before it and processes the samples since
        again, with a structure event first: an actuator's loss of effectiveness is not a
        function of x_e, so no rule's old consequent is worth keeping and all are re-opened
        at the current output (so f^ does not jump, the intent of (23)-(27)); the
        sensitivity of the state to the new gamma starts there. Then an MF is inserted on
        the input with the largest |z| (output-preserving).
        """
        k = self.steps
        slow_only = self._stats[3] == 2.0
        j, jump, sd, score, models = self._onset(k)
        first = k - len(models[2]) + 1
        held_score, held_jump, held_sd = self._held_error(first, k, models)
        held = held_score > score and \
            bool(np.max(np.abs(held_jump) / held_sd) >= HELD_MIN_Z)
        if held:
            j, jump, sd = first, held_jump, held_sd
        g_j = self._field(j, "gamma")
        if slow_only and self._negligible(g_j, jump, self.config.slow_min_jump, sd):
            # the slow average's mean shift without a jump worth the name: what a model that
            # fits a little less than perfectly gives, looked at. The slow average restarts
            # from 0 and the short one's test goes on (a change that follows is not kept
            # waiting): see (g) for why the searches stay bounded
            self._ebar_slow[:] = 0.0
            return False
        if self._negligible(g_j, jump, self.config.min_jump):
            # a jump that the bounds of (28) reduce to less than min_jump -- typically
            # evidence for a gamma below 0 where a fault-free actuator's estimate sits on
            # that bound -- is no change of the loss of effectiveness: it has been looked
            # at (the dwell restarts). Where it leaves the bounds by more than min_jump and
            # the filter has bias states, it is a change of the load or an offset (step 8):
            # the biases are re-opened at its onset and the samples since processed again
            self._ebar[:] = 0.0
            self._ebar_slow[:] = 0.0
            self._last_event = self._time
            if self.bias_plan.count and beyond_bounds(g_j, jump, self._lower, self._upper,
                                                     self._faulty, self.config.min_jump):
                if self._time > self._bias_armed_until:
                    # the first sight of it: a burst of noise fires the test as well, and
                    # a bias learnt from one is kept (gamma^ takes the difference) --
                    # what persists fires the test again after the dwell time
                    self._bias_armed_until = self._time + BIAS_CONFIRM * self.config.dwell
                    return False
                self._bias_armed_until = -math.inf
                self._reprocess(j, k, first, models, bias=True)
                self._onset_floor = j + 1
                self.bias_events += 1
            return False
        self._reprocess(j, k, first, models, held=held)
        self._onset_floor = j + 1
        self._last_event = self._time
        self._bias_armed_until = -math.inf
        self.structure_events += 1
        fz = self.fuzzy
        v = int(np.argmax(np.abs(self.z)))
        fz.insert(v, float(self.z[v]), self.config.var_rule)
        fz.var[:, self._known] = 0.0  # known actuators have nothing to learn
        return True
