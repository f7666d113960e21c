"""Model: exact ZOH, descriptor reduction, observability and clear errors (eqs 1-10, 63-73)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg

from monitor.estimation.model import (
    ContinuousDescriptor,
    DCMotorParameters,
    ModelError,
    dc_motor,
    van_loan,
)
from sim_ecu.plant import simulate
from sim_ecu.scenario import load_scenario


def test_dc_motor_continuous_eigenvalues_match_notes() -> None:
    ss = dc_motor().standard_form()
    eig = np.sort(np.linalg.eigvals(ss.A).real)
    assert eig == pytest.approx([-3.9354, -2.0646, 0.0], abs=1e-4)


def test_zoh_is_exact_matrix_exponential() -> None:
    model = dc_motor()
    d = model.discretize(0.01)
    ss = model.standard_form()
    Ad = scipy.linalg.expm(ss.A * 0.01)
    A, B, _ = d.at(0.01)
    assert pytest.approx(Ad[:2, :2], abs=1e-12) == A
    # B = int_0^T expm(A s) ds B, checked by the augmented-matrix identity
    M = np.zeros((4, 4))
    M[:3, :3] = ss.A
    M[:3, 3:] = ss.B
    E = scipy.linalg.expm(M * 0.01)
    assert pytest.approx(E[:2, 3:], abs=1e-12) == B


def test_paper_euler_step_is_unstable_but_zoh_is_not() -> None:
    # The printed matrices of section 5.2 (from (69) with T = 1 s): E^-1 A has an
    # eigenvalue near 95 (NOTES.md).
    E = np.diag([1.0, 0.01, 1.0])
    A = np.array([[0.0, 0.125, 0.0], [0.25, 0.95, 0.0], [0.0, 0.0, 1.0]])
    assert np.max(np.abs(np.linalg.eigvals(np.linalg.solve(E, A)))) == pytest.approx(95, abs=1)
    # A correct forward Euler step I + T E^-1 A is stable only for T < 2/3.9354 = 0.508 s.
    Ac = dc_motor().standard_form().A[:2, :2]
    for T, stable in ((0.5, True), (0.52, False), (1.0, False)):
        rho = np.max(np.abs(np.linalg.eigvals(np.eye(2) + T * Ac)))
        assert (rho < 1) == stable
    A_zoh, _, _ = dc_motor().discretize(1.0).at(1.0)
    assert np.max(np.abs(np.linalg.eigvals(A_zoh))) < 1


def test_dc_gain_and_steady_state_match_notes() -> None:
    d = dc_motor().discretize(0.01)
    assert d.dc_gain[0, 0] == pytest.approx(0.3077, abs=1e-4)
    run = simulate(dc_motor(q=0.0), load_scenario("healthy"), 0.01, seed=0)
    assert run.x[-1, 0] == pytest.approx(67.69, abs=0.01)
    assert run.x[-1, 1] == pytest.approx(338.46, abs=0.05)


def test_angle_is_split_off_as_unobservable() -> None:
    d = dc_motor().discretize(0.01)
    assert d.n == 2 and d.n_full == 3
    assert d.observable_names == ("current", "speed")


def test_singular_E_index1_reduces_to_standard_form_with_feedthrough() -> None:
    # La = 0: Ra i + Ke w = u is algebraic; y = i = (u - Ke w) / Ra.
    model = dc_motor(DCMotorParameters(La=0.0))
    ss = model.standard_form()
    assert ss.state_names == ("speed", "angle")
    p = DCMotorParameters()
    assert ss.D[0, 0] == pytest.approx(1 / p.Ra)
    assert ss.C[0, 0] == pytest.approx(-p.Ke / p.Ra)
    # The reduced speed dynamics: J w' = -b w + Ki (u - Ke w)/Ra
    assert ss.A[0, 0] == pytest.approx((-p.b - p.Ki * p.Ke / p.Ra) / p.J)
    d = model.discretize(0.01)
    assert d.dc_gain[0, 0] == pytest.approx(0.3077, abs=1e-4)  # same DC gain as La > 0


def test_singular_E_with_rotated_basis_matches_diagonal_case() -> None:
    base = dc_motor(DCMotorParameters(La=0.0))
    Rot = scipy.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))[0]
    rotated = ContinuousDescriptor(
        E=Rot @ base.E, A=Rot @ base.A, B=Rot @ base.B, C=base.C, Qc=base.Qc, R=base.R,
        state_names=base.state_names,
    )
    g1 = base.discretize(0.01).dc_gain
    g2 = rotated.discretize(0.01).dc_gain
    assert g1 == pytest.approx(g2, rel=1e-9)


def test_van_loan_small_step_is_q_times_t() -> None:
    A = np.array([[-1.0, 0.2], [0.1, -3.0]])
    Qc = np.array([[2.0, 0.3], [0.3, 1.0]])
    assert van_loan(A, Qc, 1e-6) == pytest.approx(Qc * 1e-6, rel=1e-4)


def _cd(**kw: object) -> ContinuousDescriptor:
    base = dict(E=np.eye(2), A=-np.eye(2), B=[[1.0], [0.0]], C=[[1.0, 0.0]], Qc=np.eye(2),
                R=[[1.0]], state_names=("a", "b"))
    base.update(kw)
    return ContinuousDescriptor(**base)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"A": np.ones((2, 3))}, "square"),
        ({"B": np.ones((3, 1))}, "rows"),
        ({"C": np.ones((1, 3))}, "columns"),
        ({"R": [[0.0]]}, "positive definite"),
        ({"Qc": [[1.0, 2.0], [0.0, 1.0]]}, "symmetric"),
        ({"A": [[np.nan, 0], [0, 1]]}, "NaN"),
        ({"E": np.zeros((2, 2)), "A": np.zeros((2, 2))}, "singular pencil"),
        ({"B": np.eye(2)}, "2 actuators but only 1 outputs"),
        ({"state_names": ("a",)}, "state names"),
    ],
)
def test_invalid_models_raise_clear_errors(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(ModelError, match=message):
        _cd(**kwargs)


def test_non_index1_singular_E_is_rejected() -> None:
    # E = [[0, 1], [0, 0]], A = I: nilpotent pencil of index 2
    with pytest.raises(ModelError, match="index 1"):
        _cd(E=[[0.0, 1.0], [0.0, 0.0]], A=np.eye(2)).standard_form()


def test_fault_not_observable_is_rejected() -> None:
    # The actuator drives state b, which never reaches the output a.
    m = _cd(B=[[0.0], [1.0]])
    with pytest.raises(ModelError, match="not observable"):
        m.discretize(0.01)


def test_bad_sample_period_is_rejected() -> None:
    with pytest.raises(ModelError, match="sample period"):
        dc_motor().discretize(0.0)


def test_negative_motor_parameter_is_rejected() -> None:
    with pytest.raises(ModelError, match="Ra"):
        dc_motor(DCMotorParameters(Ra=-1.0))
