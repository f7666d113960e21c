"""Model: exact ZOH, descriptor reduction, observability and clear errors (eqs 1-10, 63-73)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import scipy.signal
from hypothesis import given, settings
from hypothesis import strategies as st

from monitor.estimation.model import (
    ContinuousDescriptor,
    DCMotorParameters,
    DiscreteDescriptor,
    DiscreteModel,
    ModelError,
    dc_motor,
    inverse_van_loan,
    model_from_matrices,
    van_loan,
    zoh,
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
    # eigenvalue near 95 (Liu et al., Int. J. Fuzzy Syst. 22(1), 2020, (69); docs/method.md).
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


# ---- general linear models (issue 9): feed-through, discrete models, fault actuators


def test_user_feedthrough_is_kept_and_added_to_the_index1_one() -> None:
    m = _cd(D=[[0.5]])
    assert pytest.approx(np.array([[0.5]])) == m.standard_form().D
    assert m.discretize(0.01).dc_gain[0, 0] == pytest.approx(1.0 + 0.5, rel=1e-6)
    base = dc_motor(DCMotorParameters(La=0.0))
    p = DCMotorParameters()
    with_d = ContinuousDescriptor(E=base.E, A=base.A, B=base.B, C=base.C, Qc=base.Qc,
                                  R=base.R, state_names=base.state_names,
                                  D=np.array([[0.1]]))
    assert with_d.standard_form().D[0, 0] == pytest.approx(0.1 + 1 / p.Ra)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"E": np.eye(3)}, "E has 3 rows, A has 2 states"),
        ({"B": np.ones((3, 1))}, "B has 3 rows, A has 2 states"),
        ({"C": np.ones((1, 3))}, "C has 3 columns, A has 2 states"),
        ({"D": np.ones((2, 1))}, "D has 2 rows, C has 1 outputs"),
        ({"D": np.ones((1, 2))}, "D has 2 columns, B has 1 actuators"),
        ({"Qc": np.eye(3)}, "Q has 3 rows, A has 2 states"),
        ({"R": np.eye(2)}, "R has 2 rows, C has 1 outputs"),
        ({"B": np.ones((2, 0))}, "at least one actuator"),
        ({"input_names": ("u1", "u2")}, "2 input names for 1 actuators"),
        ({"state_names": ("a", "a")}, "state name 'a' appears twice"),
        ({"fault_inputs": (1,)}, "actuator 1, B has 1 actuators"),
        ({"fault_inputs": ("v",)}, "'v', which is not an input"),
        ({"fault_inputs": ()}, "fault_inputs is empty"),
        ({"fault_inputs": (True,)}, "indices or input names"),
        ({"B": np.eye(2), "C": np.eye(2), "R": np.eye(2), "fault_inputs": (0, 0)}, "twice"),
        ({"B": np.eye(2), "fault_inputs": (0, 1)}, "2 actuators but only 1 outputs"),
    ],
)
def test_shape_and_fault_input_errors_name_the_culprit(kwargs: dict[str, object],
                                                       message: str) -> None:
    with pytest.raises(ModelError, match=message) as info:
        _cd(**kwargs)
    assert "\n" not in str(info.value)


def test_fault_inputs_select_actuators_and_take_names() -> None:
    # Two actuators, one output: fine when only one of them can lose effectiveness.
    m = _cd(B=np.eye(2), A=[[-1.0, 0.5], [0.0, -2.0]], input_names=("volt", "load"),
            fault_inputs=["volt"])
    assert m.faults == (0,)
    d = m.discretize(0.01)
    assert d.fault_inputs == (0,) and d.m == 2


def test_observability_is_checked_for_the_fault_actuators_only() -> None:
    # Actuator 1 drives state b, which never reaches the output a: a fault on it cannot be
    # seen, but as a known input it is harmless.
    m = _cd(B=np.eye(2), fault_inputs=(0,))
    assert m.discretize(0.01).fault_inputs == (0,)
    with pytest.raises(ModelError, match=r"\(u2\) does not show .* not observable"):
        _cd(B=np.eye(2), fault_inputs=(1,)).discretize(0.01)


@given(n=st.integers(1, 5), m=st.integers(1, 3), seed=st.integers(0, 2**32 - 1),
       log_T=st.floats(-5.0, 0.0), log_scale=st.floats(-3.0, 3.0))
@settings(max_examples=200, deadline=None, derandomize=True, database=None)
def test_zoh_is_scipy_signals(n: int, m: int, seed: int, log_T: float, log_scale: float
                              ) -> None:
    """The monitor's zero-order hold against scipy.signal.cont2discrete, its peer: random
    stable, unstable, oscillating and integrating plants over five decades of periods."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n)) * 10.0**log_scale
    if seed % 3 == 0:
        A[:, 0] = 0.0  # an integrator (a position)
    B = rng.normal(size=(n, m))
    T = 10.0**log_T
    want_A, want_B, _, _, _ = scipy.signal.cont2discrete((A, B, np.eye(n), np.zeros((n, m))),
                                                         T, method="zoh")
    got_A, got_B = zoh(A, B, T)
    assert got_A == pytest.approx(want_A, rel=1e-12, abs=1e-12 * np.abs(want_A).max())
    assert got_B == pytest.approx(want_B, rel=1e-12, abs=1e-12 * np.abs(want_B).max())


def _zoh(cont: ContinuousDescriptor, T: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ss = cont.standard_form()
    Ad, Bd, _, _, _ = scipy.signal.cont2discrete((ss.A, ss.B, ss.C, ss.D), T, method="zoh")
    return np.asarray(Ad), np.asarray(Bd), van_loan(ss.A, cont.noise_standard_form(), T)


@pytest.mark.parametrize("T", [0.001, 0.01, 0.1])
def test_inverse_zoh_recovers_the_continuous_motor(T: float) -> None:
    cont = dc_motor()
    ss = cont.standard_form()
    Ad, Bd, Qd = _zoh(cont, T)
    disc = DiscreteDescriptor(A=Ad, B=Bd, C=ss.C, Q=Qd, R=cont.R, T=T,
                              state_names=ss.state_names)
    back = disc.to_continuous()
    assert pytest.approx(ss.A, rel=1e-9, abs=1e-9) == back.A
    assert pytest.approx(ss.B, rel=1e-9, abs=1e-12) == back.B
    assert back.Qc == pytest.approx(cont.noise_standard_form(), rel=1e-9, abs=1e-9)
    model = disc.to_model()
    ref = cont.discretize(T)
    for k in (1, 2, 5):
        for got, want in zip(model.at(k * T), ref.at(k * T), strict=True):
            assert got == pytest.approx(want, rel=1e-9, abs=1e-12)


def test_discrete_model_at_multiples_of_T_is_the_held_input_k_step() -> None:
    # An oscillator (complex eigenvalues) with two outputs, given only in discrete time.
    th = 0.3
    A = 0.95 * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    B = np.array([[0.1], [0.05]])
    Q = np.array([[0.02, 0.004], [0.004, 0.01]])
    model = DiscreteModel.from_discrete(A, B, np.eye(2), Q, np.eye(2) * 0.1, 0.02)
    A1, B1, Q1 = model.at(0.02)
    assert pytest.approx(A, abs=1e-12) == A1 and pytest.approx(B, abs=1e-12) == B1
    assert pytest.approx(Q, abs=1e-12) == Q1
    A2, B2, Q2 = model.at(0.04)
    assert pytest.approx(A @ A, abs=1e-12) == A2
    assert pytest.approx(A @ B + B, abs=1e-12) == B2
    assert pytest.approx(A @ Q @ A.T + Q, abs=1e-12) == Q2
    assert model.state_names == ("x1", "x2") and model.continuous.input_names == ("u",)


def test_inverse_van_loan_round_trips_with_an_integrator() -> None:
    A = np.array([[-1.0, 0.0], [1.0, 0.0]])  # the second state integrates the first
    Qc = np.array([[2.0, 0.1], [0.1, 0.5]])
    assert inverse_van_loan(A, van_loan(A, Qc, 0.05), 0.05) == pytest.approx(Qc, rel=1e-9)


@pytest.mark.parametrize(
    ("A", "message"),
    [
        ([[-0.5]], "eigenvalue -0.5 on the negative real axis.*sample faster"),
        ([[0.5, 0.0], [0.0, -0.2]], "negative real axis"),
        ([[0.0]], "singular"),
        ([[0.9, 1.0], [0.0, 0.0]], "singular"),
    ],
)
def test_discrete_model_without_continuous_equivalent_is_refused(A: list[list[float]],
                                                                message: str) -> None:
    n = len(A)
    with pytest.raises(ModelError, match=message):
        DiscreteModel.from_discrete(A, np.ones((n, 1)), np.eye(n)[:1], np.eye(n), [[1.0]], 0.01)


def test_discrete_shape_errors_name_the_matrix() -> None:
    ok = dict(A=np.eye(2) * 0.9, B=[[1.0], [0.0]], C=[[1.0, 0.0]], Q=np.eye(2), R=[[1.0]],
              T=0.01)
    for key, bad, message in (
        ("A", np.eye(3)[:2], "A must be square"),
        ("B", np.ones((3, 1)), "B has 3 rows, A has 2 states"),
        ("C", np.ones((1, 3)), "C has 3 columns"),
        ("D", np.ones((1, 2)), "D has 2 columns, B has 1 actuators"),
        ("E", np.eye(3), "E has 3 rows"),
        ("Q", np.eye(1), "Q has 1 rows, A has 2 states"),
        ("R", [[-1.0]], "R must be positive definite"),
        ("T", 0.0, "sample period"),
    ):
        with pytest.raises(ModelError, match=message):
            DiscreteDescriptor(**{**ok, key: bad})  # type: ignore[arg-type]


def test_discrete_singular_E_index1_is_reduced() -> None:
    # p(k+1) = 0.7 p + 0.5 q + u;  0 = 0.2 p - q + 0.3 u;  y = q
    # => q = 0.2 p + 0.3 u, p(k+1) = 0.8 p + 1.15 u, y = 0.2 p + 0.3 u
    E = np.diag([1.0, 0.0])
    A = np.array([[0.7, 0.5], [0.2, -1.0]])
    B = np.array([[1.0], [0.3]])
    C, R = np.array([[0.0, 1.0]]), np.array([[0.01]])
    desc = DiscreteDescriptor(E=E, A=A, B=B, C=C, Q=np.diag([0.01, 0.0]), R=R, T=0.01,
                              state_names=("p", "q"))
    ss = desc.standard_form()
    assert ss.state_names == ("p",)
    assert ss.A[0, 0] == pytest.approx(0.7 + 0.5 * 0.2)
    assert ss.B[0, 0] == pytest.approx(1.0 + 0.5 * 0.3)
    assert ss.C[0, 0] == pytest.approx(0.2) and ss.D[0, 0] == pytest.approx(0.3)
    model = desc.to_model()
    A1, B1, Q1 = model.at(0.01)
    assert A1[0, 0] == pytest.approx(0.8, rel=1e-12) and B1[0, 0] == pytest.approx(1.15)
    assert Q1[0, 0] == pytest.approx(0.01, rel=1e-9)
    # a rotated descriptor (non-diagonal E) describes the same plant
    Rot = scipy.linalg.qr(np.random.default_rng(1).normal(size=(2, 2)))[0]
    rot = DiscreteDescriptor(E=Rot @ E, A=Rot @ A, B=Rot @ B, C=C,
                             Q=Rot @ np.diag([0.01, 0.0]) @ Rot.T, R=R, T=0.01)
    assert rot.to_model().dc_gain == pytest.approx(model.dc_gain, rel=1e-9)


def test_model_from_matrices_builds_both_domains_from_lists() -> None:
    cont = model_from_matrices(
        "continuous", E=[[2.0, 0, 0], [0, 0.01, 0], [0, 0, 1]],
        A=[[-2.0, -0.25, 0], [0.25, -0.05, 0], [0, 1, 0]], B=[[1], [0], [0]], C=[[1, 0, 0]],
        Q=(np.diag([2.0, 0.01, 1.0]) @ (1.44 * np.eye(3)) @ np.diag([2.0, 0.01, 1.0])).tolist(),
        R=[[0.25]], T=0.01, state_names=["current", "speed", "angle"],
        input_names=["voltage"], output_names=["current"], fault_inputs=["voltage"],
    )
    ref = dc_motor().discretize(0.01)
    for got, want in zip(cont.at(0.01), ref.at(0.01), strict=True):
        assert got == pytest.approx(want, rel=1e-12, abs=1e-15)
    assert cont.observable_names == ("current", "speed")
    Ad, Bd, Qd = _zoh(dc_motor(), 0.01)
    disc = model_from_matrices("discrete", A=Ad.tolist(), B=Bd.tolist(), C=[[1, 0, 0]],
                               Q=Qd.tolist(), R=[[0.25]], T=0.01)
    for got, want in zip(disc.at(0.02), ref.at(0.02), strict=True):
        assert got == pytest.approx(want, rel=1e-9, abs=1e-12)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"domain": "hybrid"}, "domain must be 'continuous' or 'discrete'"),
        ({"B": [[1.0], [0.0], [0.0]]}, "B has 3 rows, A has 2 states"),
        ({"A": [[1.0, "x"], [0.0, 1.0]]}, "A is not a numeric matrix"),
        ({"A": [[1.0, 2.0], [0.0]]}, "A is not a numeric matrix"),
        ({"state_names": "ab"}, "state_names must be a list of strings"),
        ({"input_names": [1]}, "input_names must be a list of strings"),
        ({"T": -1.0}, "sample period"),
        ({"fault_inputs": ["load"]}, "'load', which is not an input"),
    ],
)
def test_model_from_matrices_errors_are_one_line(kwargs: dict[str, object], message: str
                                                 ) -> None:
    args: dict[str, object] = dict(domain="continuous", A=[[-1.0, 0.0], [0.0, -2.0]],
                                   B=[[1.0], [0.0]], C=[[1.0, 0.0]], Q=[[1.0, 0], [0, 1.0]],
                                   R=[[1.0]], T=0.01)
    args.update(kwargs)
    with pytest.raises(ModelError, match=message) as info:
        model_from_matrices(**args)  # type: ignore[arg-type]
    assert "\n" not in str(info.value)
