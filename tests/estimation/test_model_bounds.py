"""Models at the edges of what a rig file can hold (issue 17): no value a TOML file can give
ends in a traceback. A model the rig check refuses is one line naming the file, the key and
what is wrong (exit status 2, also from `run` before any bus opens); a model it accepts is
one the estimator takes and steps without raising.

The values: a 200-state diagonal of -35 (35^200 overflows), entries of 1e308 and 1e-308,
rates far below and above what the monitor can use, stiff, unstable and integrating models,
singular E (index 1 and not), NaN.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

from monitor.app.cli import main
from monitor.estimation.fuzzy import FuzzyConfig
from monitor.estimation.fuzzy_ukf import FuzzyUKF, FuzzyUKFConfig
from monitor.estimation.model import (
    ESTIMATOR_MAX_MF,
    ESTIMATOR_ONSET_WINDOW_S,
    ContinuousDescriptor,
    DCMotorParameters,
    ModelError,
    dc_motor,
    inverse_van_loan,
    model_from_matrices,
    van_loan,
)
from monitor.pipeline import MonitorConfig
from monitor.rig import RigError, build_model, load_rig, model_of
from monitor.rig.load import MAX_RATE_HZ, MIN_RATE_HZ
from tests.support import BIN
from tests.support.paths import TEST_RIGS

CapFD = pytest.CaptureFixture[str]
CapLog = pytest.LogCaptureFixture
SERVO = TEST_RIGS / "servo.toml"
SERVO_MOTOR = ("J = 2e-5\nb = 1e-5\nKe = 0.03\nKi = 0.03\nRa = 1.0\nLa = 1e-3\n"
               "process_noise = 1e-4\noutput_sigma = 0.01\n")


# A silence timeout that spans two periods of the slowest rate, so that the rig check's
# own rule on it (tests/rig/test_rig_file.py) leaves these rigs to the model's checks.
SLOW_SILENCE = "[diagnosis]\nsilence_timeout_s = 30.0"


def _toml(value: object) -> str:
    if isinstance(value, str):
        return value  # written as is (nan, inf)
    return repr([[float(v) for v in row] for row in np.atleast_2d(np.asarray(value))])


def _state_space(tmp: Path, rate: float = 1000.0, domain: str = "continuous",
                 **matrices: object) -> Path:
    """The servo rig (one input, one output) with a state-space model of these matrices."""
    (tmp / "servo.dbc").write_text((SERVO.parent / "servo.dbc").read_text())
    model = "\n".join(f"{k} = {_toml(v)}" for k, v in matrices.items())
    text = SERVO.read_text().replace(SERVO_MOTOR, "").replace(
        'kind = "dc_motor"', f'kind = "state_space"\ndomain = "{domain}"\n{model}').replace(
        "rate = 1000.0", f"rate = {rate!r}").replace("[diagnosis]", SLOW_SILENCE)
    path = tmp / "rig.toml"
    path.write_text(text)
    return path


def _servo(tmp: Path, old: str = "", new: str = "") -> Path:
    (tmp / "servo.dbc").write_text((SERVO.parent / "servo.dbc").read_text())
    path = tmp / "rig.toml"
    text = SERVO.read_text().replace(old, new) if old else SERVO.read_text()
    path.write_text(text.replace("[diagnosis]", SLOW_SILENCE))
    return path


def _diag(n: int, v: float) -> np.ndarray:
    return v * np.eye(n)


N = 200
E1 = np.eye(1, N)  # the first state measured
TWO = {"B": [[1.0], [1.0]], "C": [[1.0, 1.0]], "Q": np.eye(2), "R": [[0.01]]}

# (name, rig writer arguments, the key and words the one line holds)
REFUSED = [
    ("an entry of 1e308 in A", {"A": [[-1e308, 0.0], [0.0, -1.0]], **TWO},
     "model: A has an entry of 1e+308"),
    ("an entry of 1e308 in R", {"A": _diag(2, -1.0), **{**TWO, "R": [[1e308]]}},
     "model: R has an entry of 1e+308"),
    ("a measurement noise of 1e-308", {"A": _diag(2, -1.0), **{**TWO, "R": [[1e-308]]}},
     "model: R has an eigenvalue of 1e-308"),
    ("NaN in A", {"A": "[[nan, 0.0], [0.0, -1.0]]", **TWO}, "model: A contains NaN"),
    ("an unstable mode too fast for the rate", {"A": [[300.0]], "B": [[1.0]],
                                                "C": [[1.0]], "Q": [[1.0]], "R": [[0.01]],
                                                "rate": 0.5},
     "model.rate: a mode of the model grows by e^600"),
    ("a singular E of index 2", {"E": [[0.0, 1.0], [0.0, 0.0]], "A": np.eye(2), **TWO},
     "model: singular E with a singular algebraic block"),
    ("a singular pencil", {"E": np.zeros((2, 2)), "A": np.zeros((2, 2)), **TWO},
     "model: singular pencil"),
    ("outputs that see no state", {"A": _diag(2, -1.0), **{**TWO, "C": [[0.0, 0.0]]}},
     "model: no state of the model reaches its outputs"),
    ("a discrete integrator of 20 states", {"domain": "discrete", "A": np.eye(20),
                                             "B": np.ones((20, 1)), "C": np.eye(1, 20),
                                             "Q": np.eye(20), "R": [[0.01]]},
     "give the continuous model"),
]


@pytest.mark.parametrize(("what", "kw", "needle"), REFUSED, ids=[r[0] for r in REFUSED])
def test_refused_models_are_one_line_naming_the_key(tmp_path: Path, what: str,
                                                     kw: dict[str, object],
                                                     needle: str) -> None:
    path = _state_space(tmp_path, **kw)  # type: ignore[arg-type]
    with pytest.raises(RigError) as info:
        load_rig(path)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(f"rig file {path}: "), msg
    assert needle in msg, msg


@pytest.mark.parametrize(("rate", "words"), [
    (1e-6, "must be at least 0.2 Hz"), (1e-100, "must be at least 0.2 Hz"),
    (1e6, "must be at most 100000 Hz"), ("nan", "must be a finite number"),
    ("inf", "must be a finite number")])
def test_rates_the_monitor_cannot_use_are_refused(tmp_path: Path, rate: object,
                                                  words: str) -> None:
    path = _servo(tmp_path, "rate = 1000.0", f"rate = {rate}")
    with pytest.raises(RigError, match=f"model.rate: {words}"):
        load_rig(path)


def test_the_slowest_rate_is_one_the_pipeline_estimates() -> None:
    # a period above max_gap_s restarts the estimator at every sample
    assert MonitorConfig().max_gap_s >= 1.0 / MIN_RATE_HZ
    assert MAX_RATE_HZ <= 1e6  # the estimator keys its steps by the microsecond


ACCEPTED = [
    ("a 200-state diagonal of -35", {"A": _diag(N, -35.0), "B": np.ones((N, 1)), "C": E1,
                                     "Q": np.eye(N), "R": [[0.01]]}),
    ("an entry of 1e-308 in A", {"A": [[-1e-308, 0.0], [0.0, -1.0]], **TWO}),
    ("a stiff model", {"A": [[-1e9, 0.0], [0.0, -1e-9]], **TWO}),
    ("an unstable model", {"A": [[1.0]], "B": [[1.0]], "C": [[1.0]], "Q": [[1.0]],
                           "R": [[0.01]]}),
    ("an integrator without process noise", {"A": [[0.0]], "B": [[1.0]], "C": [[1.0]],
                                             "Q": [[0.0]], "R": [[0.01]]}),
    ("a singular E of index 1", {"E": [[1.0, 0.0], [0.0, 0.0]], "A": _diag(2, -1.0), **TWO}),
    ("a discrete model of 30 states", {"domain": "discrete", "A": _diag(30, 0.5),
                                        "B": np.ones((30, 1)), "C": np.eye(1, 30),
                                        "Q": np.eye(30), "R": [[0.01]]}),
    ("the slowest rate", {"A": [[-1.0]], "B": [[1.0]], "C": [[1.0]], "Q": [[1.0]],
                          "R": [[0.01]], "rate": MIN_RATE_HZ}),
    ("the fastest rate", {"A": [[-1.0]], "B": [[1.0]], "C": [[1.0]], "Q": [[1.0]],
                          "R": [[0.01]], "rate": MAX_RATE_HZ}),
]


@pytest.mark.parametrize(("what", "kw"), ACCEPTED, ids=[a[0] for a in ACCEPTED])
def test_accepted_models_run_in_the_estimator(tmp_path: Path, what: str,
                                              kw: dict[str, object]) -> None:
    rig = load_rig(_state_space(tmp_path, **kw))  # type: ignore[arg-type]
    model = build_model(rig).discretize(1.0 / model_of(rig)[1])
    est = FuzzyUKF(model)
    T = model.T
    # a sample, a gap of 3 periods, the longest gap the pipeline predicts through
    for dt in (T, 3 * T, T, MonitorConfig().max_gap_s):
        est.step(np.ones(model.m), np.full(model.p, 0.1), dt)


@pytest.mark.parametrize("rate", [MIN_RATE_HZ, 1.0, MAX_RATE_HZ])
def test_the_servo_at_any_accepted_rate(tmp_path: Path, rate: float) -> None:
    # at 1 Hz its 1 kHz pole made Van Loan's expm(-A T) overflow (e^1000): NaN Q, then a
    # LinAlgError in the estimator's initial covariance
    rig = load_rig(_servo(tmp_path, "rate = 1000.0", f"rate = {rate!r}"))
    model = build_model(rig).discretize(1.0 / model_of(rig)[1])
    _, _, Q = model.at(model.T)
    assert np.all(np.isfinite(Q)) and np.all(np.linalg.eigvalsh(Q) >= 0)
    FuzzyUKF(model).step([24.0], [0.5], model.T)


def test_van_loan_over_periods_long_against_the_modes() -> None:
    # a mode at -1000/s over 10 s: the stationary covariance q / (2 a) per state
    A = np.diag([-1000.0, -1.0])
    Qc = np.diag([2.0, 2.0])
    Qd = van_loan(A, Qc, 10.0)
    assert Qd[0, 0] == pytest.approx(1.0 / 1000.0, rel=1e-9)
    assert Qd[1, 1] == pytest.approx(1.0 - np.exp(-20.0), rel=1e-9)


def test_model_errors_name_the_rate_when_the_period_is_the_culprit() -> None:
    one = np.eye(1)
    unstable = ContinuousDescriptor(E=one, A=300.0 * one, B=one, C=one, Qc=one,
                                    R=0.01 * one, state_names=("x",))
    with pytest.raises(ModelError) as info:
        unstable.discretize(2.0)
    assert info.value.key == "rate"
    unstable.discretize(0.01)  # the same model sampled fast enough
    with pytest.raises(ModelError) as info:
        model_from_matrices("continuous", A=[[np.nan]], B=[[1.0]], C=[[1.0]], Q=[[1.0]],
                            R=[[1.0]], T=0.01)
    assert info.value.key is None


def test_motor_parameters_in_other_units_are_one_line() -> None:
    with pytest.raises(ModelError, match=r"motor parameter J is 1e\+200"):
        dc_motor(DCMotorParameters(J=1e200))
    with pytest.raises(ModelError, match=r"J = 1e\+100 kg m\^2.*check the units"):
        dc_motor(DCMotorParameters(J=1e100))


# ---- the command line: run exits 2 before any bus opens, --rate is bounded


def _run(*args: str) -> tuple[int, list[str]]:
    """The installed command (its stderr is every line the user sees, the log included), on
    python-can's virtual bus: a run that got as far as the bus would monitor it until the
    timeout, so the test fails rather than hangs."""
    res = subprocess.run([str(BIN / "motor-monitor"), "run", "--interface", "virtual",
                          "--channel", "x", *args], capture_output=True, text=True,
                         timeout=120)
    return res.returncode, res.stderr.strip().splitlines()


@pytest.mark.parametrize("kw", [REFUSED[0][1], REFUSED[4][1]], ids=["1e308", "unstable"])
def test_run_exits_2_before_the_bus_on_a_model_it_cannot_use(tmp_path: Path,
                                                             kw: dict[str, object]) -> None:
    path = _state_space(tmp_path, **kw)  # type: ignore[arg-type]
    rc, err = _run("--rig", str(path))
    assert rc == 2 and len(err) == 1, err
    assert err[0].startswith(f"motor-monitor: error: rig file {path}: model"), err


def test_run_exits_2_on_a_model_too_large_for_the_estimator(tmp_path: Path) -> None:
    # 200 states, every one observable (a chain measured at its end): the estimator's
    # fuzzy rule base over the observable state would hold 5^200 rules
    A = -35.0 * np.eye(N) + np.eye(N, k=-1)
    path = _state_space(tmp_path, A=A, B=np.eye(N, 1, -(N - 1)), C=np.eye(1, N, N - 1),
                        Q=np.eye(N), R=[[0.01]])
    rc, err = _run("--rig", str(path))
    assert rc == 2 and len(err) == 1, err
    assert f"rig file {path}: model: the estimator of this model's 200 observable states" \
        in err[0] and "at most 10" in err[0], err


def test_the_model_check_sizes_the_estimator_it_builds() -> None:
    # the check sizes the default estimator (without importing it): the same defaults
    assert FuzzyConfig().max_mf == ESTIMATOR_MAX_MF
    assert FuzzyUKFConfig().onset_window == ESTIMATOR_ONSET_WINDOW_S
    # ten observable states and one input fit; an onset ring of 100 outputs at 100 kHz
    # does not, and the rate is to blame
    chain = -35.0 * np.eye(10) + np.eye(10, k=-1)
    ok = model_from_matrices("continuous", A=chain, B=np.eye(10, 1, -9), C=np.eye(1, 10, 9),
                             Q=np.eye(10), R=[[0.01]], T=1.0 / MAX_RATE_HZ)
    assert ok.n == 10
    FuzzyUKF(ok)
    with pytest.raises(ModelError, match=r"onset ring.*lower the rate") as info:
        model_from_matrices("continuous", A=-np.eye(10), B=np.ones((10, 1)),
                            C=np.ones((100, 10)), Q=np.eye(10), R=np.eye(100),
                            T=1.0 / MAX_RATE_HZ)
    assert info.value.key == "rate"
    # a configuration larger than the default is sized again by the estimator itself
    with pytest.raises(ModelError, match="max_mf"):
        FuzzyUKF(ok, FuzzyUKFConfig(fuzzy=FuzzyConfig(max_mf=9)))


@pytest.mark.parametrize(("rate", "words"), [("1e-6", "at least 0.2 Hz"),
                                             ("2e5", "at most 100000 Hz"), ("x", "invalid")])
def test_run_rate_option_is_bounded(capfd: CapFD, rate: str, words: str) -> None:
    with pytest.raises(SystemExit) as info:
        main(["run", "--interface", "virtual", "--channel", "x", "--rate", rate])
    assert info.value.code == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "argument --rate" in err[0] and words in err[0], err


def test_inverse_van_loan_of_many_states_round_trips() -> None:
    # above KRON_STATES the Stein equation replaces the O(n^6) Kronecker solve
    rng = np.random.default_rng(1)
    n = 20
    A = -3.0 * np.eye(n) + 0.5 * rng.standard_normal((n, n))
    L = rng.standard_normal((n, n))
    Qc = L @ L.T / n
    assert inverse_van_loan(A, van_loan(A, Qc, 0.05), 0.05) == pytest.approx(Qc, abs=1e-12)
