"""The fuzzy UKF's bias states (step 8 of `monitor.estimation.fuzzy_ukf`; our extension,
not Liu, Bao, Xue, Du, Int. J. Fuzzy Systems 22(1), 2020):

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
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from monitor.estimation.model import BiasPlan, DiscreteModel

Array = NDArray[np.float64]

__all__ = ["BIAS_CONFIRM", "augmented_matrices", "beyond_bounds"]

BIAS_CONFIRM = 10.0
"""A bias event needs the change gamma cannot take seen twice, the second time within this
many dwell times of the first: a burst of noise that fires the test (3.7 sigma) is seldom
followed by another within 2 s, a load that the outputs keep showing is."""


def augmented_matrices(model: DiscreteModel, plan: BiasPlan, dt: float
                       ) -> tuple[Array, Array, Array, Array, Array]:
    """(A, B, Q, C, D) of the filter's state for a step of dt: the model's (`at`), with
    the bias states appended as random walks, [[A, B_d], [0, I]], [B; 0], diag(Q, q dt),
    [C, D_d], D."""
    A, B, Q = model.at(dt)
    nb = plan.count
    if nb == 0:
        return A, B, Q, model.C, model.D
    Bd, Dd = plan.entry(plan.kind, B, model.D)
    Aa = np.block([[A, Bd], [np.zeros((nb, A.shape[0])), np.eye(nb)]])
    Ba = np.vstack([B, np.zeros((nb, B.shape[1]))])
    Qa = scipy.linalg.block_diag(Q, np.diag(plan.q * dt))
    Ca = np.hstack([model.C, Dd])
    return Aa, Ba, Qa, Ca, model.D


def beyond_bounds(gamma: Array, jump: Array, lower: Array, upper: Array,
                  faulty: list[int], min_jump: float) -> bool:
    """Whether the jump of gamma leaves the bounds of (28) by more than min_jump for some
    fault actuator: a change gamma cannot take, which a filter with bias states reads as a
    bias event."""
    g = gamma[faulty] + jump
    out = np.maximum(lower[faulty] - g, g - upper[faulty])
    return bool(faulty) and bool(np.any(out > min_jump))
