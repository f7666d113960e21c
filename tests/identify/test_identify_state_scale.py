"""A black box of a slow plant sampled fast reaches the estimator in balanced states: in
the fit's own coordinates (B some 1e-4, C some 1e2) the estimator's test that a loss shows
in the outputs called it unobservable, and identify fell back to an order too small for
the plant (the rig zoo's seed 6: current -> load speed of a two-mass drive at 250 Hz)."""

from __future__ import annotations

import numpy as np
import scipy.linalg

from monitor.estimation.model import ContinuousDescriptor
from monitor.identify.core import _balanced_scale

T = 0.004
# the order-2 fit of that capture, as the prediction-error refinement left it
AC = np.array([[-2.47641427, -0.18113427], [-0.39275733, -0.01748336]])
BC = np.array([[-3.76608381e-04], [-6.10953416e-05]])
C = np.array([[-345.31108863, 29.37261199]])
QC = np.diag([2e-3, 5e-5])


def _model(A: np.ndarray, B: np.ndarray, Cm: np.ndarray, Q: np.ndarray) -> ContinuousDescriptor:
    return ContinuousDescriptor(E=np.eye(2), A=A, B=B, C=Cm, Qc=Q, R=np.array([[0.02]]),
                                state_names=("x1", "x2"), input_names=("ISet",),
                                output_names=("Speed",))


def _pbh_ratio(A: np.ndarray, B: np.ndarray, Cm: np.ndarray) -> float:
    """Smallest over largest singular value of [[A - I, B], [C, 0]] of the discrete model,
    relative to its largest entry (the estimator's rank test's scale)."""
    dm = _model(A, B, Cm, QC).standard_form()
    n = dm.A.shape[0]
    M = np.zeros((n + 2, n + 1))
    Phi = scipy.linalg.expm(np.block([[dm.A, dm.B], [np.zeros((1, n + 1))]]) * T)
    M[:n, :n] = Phi[:n, :n] - np.eye(n)
    M[:n, n:] = Phi[:n, n:]
    M[n:n + 1, :n] = dm.C
    s = np.linalg.svd(M, compute_uv=False)
    return float(s[-1] / np.abs(M).max())


def test_balanced_states_keep_the_model_and_let_the_estimator_see_the_loss() -> None:
    A2, B2, C2, Q2 = _balanced_scale(AC, BC, C, QC)
    # the same plant: poles, DC gain and a frequency response point unchanged
    assert np.allclose(np.sort(np.linalg.eigvals(A2)), np.sort(np.linalg.eigvals(AC)))
    for w in (0.0, 1.0, 30.0):
        g1 = C @ np.linalg.solve(1j * w * np.eye(2) - AC, BC)
        g2 = C2 @ np.linalg.solve(1j * w * np.eye(2) - A2, B2)
        assert np.allclose(g1, g2, rtol=1e-10)
    # the noise maps with the states: the filter's output covariance is the same
    assert np.allclose(C @ QC @ C.T, C2 @ Q2 @ C2.T, rtol=1e-10)
    # B's rows and C's columns balanced, the rank test far from its 1e-9 tolerance
    assert np.allclose(np.linalg.norm(B2, axis=1), np.linalg.norm(C2, axis=0))
    assert _pbh_ratio(AC, BC, C) < 1e-9 < 1e-6 < _pbh_ratio(A2, B2, C2)
    _model(A2, B2, C2, Q2).discretize(T)  # raises ModelError where the loss does not show


def test_a_state_without_input_or_output_keeps_its_scale() -> None:
    B = np.array([[1.0], [0.0]])
    Cm = np.array([[2.0, 3.0]])
    A2, B2, C2, _ = _balanced_scale(AC, B, Cm, QC)
    assert np.isfinite(A2).all() and np.isfinite(B2).all() and np.isfinite(C2).all()
    assert C2[0, 1] == 3.0 and B2[1, 0] == 0.0
