"""Self-constructing fuzzy system, eqs (15)-(29).

Rules (16), (22): "if x_1 is A_1^{i1} and ... and x_N is A_N^{iN} then f^ = a_{i1...iN}",
one rule per combination of membership functions (a grid), each consequent a vector with
one entry per actuator (the loss of effectiveness gamma of that actuator).

* Membership functions are triangles forming a *partition of unity* on each input: the
  triangle of centre c_j rises from c_{j-1} and falls to c_{j+1}; the outermost ones are
  shoulders (1 beyond the outer centres). At most two are non-zero on an input.
* Product inference and weighted-mean defuzzification (17), (29): f^ = sum a_j xi_j with
  the fuzzy basis functions xi_j = prod_i mu / sum prod mu (19). With a partition on every
  input the denominator is exactly 1 and f^ is the multilinear interpolation of the
  consequent grid, so at most 2^N rules fire at a time.
* Structure learning (20)-(22) adds a membership function to one input at a given point;
  the rules that it creates get consequents equal to the old system's output at their grid
  points. Because the old output is linear between neighbouring centres, this leaves the
  output unchanged *everywhere*, which is what (23)-(27) asks of a_new at the current point.
  Growth is bounded: a maximum count per input and a minimum spacing between centres.
* Adaptation (28) is a continuous-time projection law; per sample it becomes
  a_j <- clip(a_j + r_j e, u_L, u_U): the consequents stay in the bounds [u_L, u_U]
  ([0, 1] for gamma). The gains r_j are chosen by the fuzzy UKF (see fuzzy_ukf): a
  consequent is a part common to all rules (its variance lives in the estimator) plus
  the rule's own part, whose variance is `var` here.

Storage uses a fixed stride of `max_mf` per input so the numba kernels need no
allocation; consequents live in `cons` of shape (max_mf ** N, m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from monitor.jit import njit

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["FuzzyConfig", "SelfConstructingFuzzySystem", "fire", "memberships"]


@njit
def memberships(z: float, centres: Array, count: int) -> tuple[int, int, float, float]:
    """Triangular partition on one input: (j0, j1, mu0, mu1), mu0 + mu1 = 1.

    Only MFs j0 and j1 are non-zero at z; every other MF of the input is 0 there.
    """
    if count == 1 or z <= centres[0]:
        return 0, 0, 1.0, 0.0
    if z >= centres[count - 1]:
        return count - 1, count - 1, 1.0, 0.0
    j = 0
    while centres[j + 1] < z:
        j += 1
    w1 = (z - centres[j]) / (centres[j + 1] - centres[j])
    return j, j + 1, 1.0 - w1, w1


@njit
def fire(
    z: Array, centres: Array, counts: IntArray, max_mf: int,
    rule_idx: IntArray, rule_w: Array,
) -> int:
    """Firing rules and basis functions xi (19) at input z; returns how many fire.

    Writes up to 2^N (flat rule index, xi) pairs into rule_idx / rule_w, skipping zero
    weights. The xi sum to one (product of partitions).
    """
    N = z.shape[0]
    nf = 1
    rule_idx[0] = 0
    rule_w[0] = 1.0
    stride = 1
    for v in range(N):
        j0, j1, m0, m1 = memberships(z[v], centres[v], counts[v])
        if m1 > 0.0 and j1 != j0:
            for k in range(nf):
                rule_idx[nf + k] = rule_idx[k] + j1 * stride
                rule_w[nf + k] = rule_w[k] * m1
                rule_idx[k] = rule_idx[k] + j0 * stride
                rule_w[k] = rule_w[k] * m0
            nf *= 2
        else:
            for k in range(nf):
                rule_idx[k] = rule_idx[k] + j0 * stride
        stride *= max_mf
    return nf


@njit
def infer(cons: Array, rule_idx: IntArray, rule_w: Array, nf: int, out: Array) -> None:
    """Weighted-mean output (17), (29), (51) of the firing rules into out (m,)."""
    m = cons.shape[1]
    den = 0.0
    for k in range(nf):
        den += rule_w[k]
    for a in range(m):
        acc = 0.0
        for k in range(nf):
            acc += cons[rule_idx[k], a] * rule_w[k]
        out[a] = acc / den


@dataclass(frozen=True)
class FuzzyConfig:
    """Structure of the rule base.

    initial_mf: MF centres per input at start (a single centre is a constant MF).
    max_mf: bound on MFs per input, so at most max_mf ** N rules.
    min_spacing: no new centre closer than this to an existing one (input units).
    z_max: inputs are clipped to [-z_max, z_max] where new centres are placed.
    lower, upper: projection bounds u_L, u_U of (28) on every consequent.
    """

    initial_mf: tuple[tuple[float, ...], ...] = ((-3.0, 3.0), (0.0,))
    max_mf: int = 5
    min_spacing: float = 1.0
    z_max: float = 6.0
    lower: float = 0.0
    upper: float = 1.0


class SelfConstructingFuzzySystem:
    """The rule base: centres, consequents and the variances of the rules' own parts of
    the consequents (for adaptive gains)."""

    def __init__(self, n_inputs: int, n_outputs: int, config: FuzzyConfig | None = None,
                 initial_output: float = 0.0, initial_variance: float = 0.05) -> None:
        cfg = config or FuzzyConfig()
        if n_inputs < 1 or n_outputs < 1:
            raise ValueError("a fuzzy system needs at least one input and one output")
        init = list(cfg.initial_mf[:n_inputs])
        while len(init) < n_inputs:
            init.append((0.0,))
        if any(len(c) > cfg.max_mf or len(c) < 1 for c in init):
            raise ValueError("initial MF counts must lie in [1, max_mf]")
        if any(list(c) != sorted(c) or len(set(c)) != len(c) for c in init):
            raise ValueError("initial MF centres must be strictly increasing")
        self.config = cfg
        self.n_inputs = n_inputs
        self.n_outputs = n_outputs
        self.max_mf = cfg.max_mf
        self.centres = np.zeros((n_inputs, cfg.max_mf))
        self.counts = np.zeros(n_inputs, dtype=np.int64)
        for v, c in enumerate(init):
            self.centres[v, : len(c)] = c
            self.counts[v] = len(c)
        size = cfg.max_mf**n_inputs
        self.cons = np.full((size, n_outputs), float(initial_output))
        self.var = np.full((size, n_outputs), float(initial_variance))
        self.rule_idx = np.zeros(2**n_inputs, dtype=np.int64)
        self.rule_w = np.zeros(2**n_inputs)
        self.insertions = 0

    @property
    def rule_count(self) -> int:
        """Number of rules R = prod_i (MFs on input i), eq (21)-(22)."""
        return int(np.prod(self.counts))

    def evaluate(self, z: Array) -> Array:
        """f^(z) (17)/(29), allocation aside; for tests and plotting."""
        nf = fire(np.asarray(z, dtype=float), self.centres, self.counts, self.max_mf,
                  self.rule_idx, self.rule_w)
        out = np.zeros(self.n_outputs)
        infer(self.cons, self.rule_idx, self.rule_w, nf, out)
        return out

    def basis(self, z: Array) -> dict[int, float]:
        """The non-zero fuzzy basis functions xi_j (19) at z, by flat rule index."""
        nf = fire(np.asarray(z, dtype=float), self.centres, self.counts, self.max_mf,
                  self.rule_idx, self.rule_w)
        return {int(self.rule_idx[k]): float(self.rule_w[k]) for k in range(nf)}

    def _grid(self, arr: Array) -> Array:
        return arr.reshape((self.max_mf,) * self.n_inputs + (self.n_outputs,), order="F")

    def can_insert(self, v: int, c: float) -> bool:
        k = int(self.counts[v])
        if k >= self.max_mf:
            return False
        cs = self.centres[v, :k]
        return bool(np.all(np.abs(cs - c) >= self.config.min_spacing))

    def insert(self, v: int, c: float, new_variance: float) -> bool:
        """Add an MF centred at c on input v (20)-(22); output-preserving (23)-(27).

        Returns False (and changes nothing) when the bound or the spacing forbids it.
        The new rules' consequents are the old interpolant at their grid points, i.e.
        (27) a_new = f(t) evaluated there; their variances are set to `new_variance`
        so that they learn fast.
        """
        c = float(np.clip(c, -self.config.z_max, self.config.z_max))
        if not self.can_insert(v, c):
            return False
        k = int(self.counts[v])
        cs = self.centres[v, :k]
        pos = int(np.searchsorted(cs, c))
        # Interpolation weights of the new centre between its neighbours on input v.
        if pos == 0:
            lo, hi, wlo = 0, 0, 1.0
        elif pos == k:
            lo, hi, wlo = k - 1, k - 1, 1.0
        else:
            lo, hi = pos - 1, pos
            wlo = (cs[hi] - c) / (cs[hi] - cs[lo])
        g = self._grid(self.cons)
        gv = self._grid(self.var)
        sl_lo = [slice(None)] * (self.n_inputs + 1)
        sl_hi = list(sl_lo)
        sl_lo[v] = slice(lo, lo + 1)
        sl_hi[v] = slice(hi, hi + 1)
        new_slab = wlo * g[tuple(sl_lo)] + (1.0 - wlo) * g[tuple(sl_hi)]
        new_var = np.full_like(new_slab, new_variance)
        g_new = np.insert(g, pos, np.take(new_slab, 0, axis=v), axis=v)
        gv_new = np.insert(gv, pos, np.take(new_var, 0, axis=v), axis=v)
        take = [slice(None)] * (self.n_inputs + 1)
        take[v] = slice(0, self.max_mf)
        self.cons[:] = g_new[tuple(take)].reshape(self.cons.shape, order="F")
        self.var[:] = gv_new[tuple(take)].reshape(self.var.shape, order="F")
        self.centres[v, pos + 1 : k + 1] = cs[pos:k].copy()
        self.centres[v, pos] = c
        self.counts[v] = k + 1
        self.insertions += 1
        return True
