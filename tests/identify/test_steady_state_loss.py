"""identify says how far a loss moves the settled output: where the output does not settle at
a level the input sets (a speed held by a spring), a loss shows only in the transients after
the input changes, and a refusal of such a model says so first (the rig zoo's seeds 202 and
209: spring-held speeds whose own capture replayed as faulty, refused with advice to try
other orders, which no order follows)."""

from __future__ import annotations

import numpy as np

from monitor.app.identify_check import (
    STEADY_LOSS_NOISE,
    ReplayFigures,
    failure_cause,
    report_checks,
)
from monitor.estimation.model import ContinuousDescriptor
from monitor.identify import identify
from tests.identify.captures import capture

T = 0.005


def _speed(spring: float) -> ContinuousDescriptor:
    """Current in, speed out of an inertia with viscous friction, held by `spring` (N*m/rad;
    0: free, whose speed settles at a level the current sets)."""
    J, b, Kt = 1e-3, 4e-3, 0.3
    return ContinuousDescriptor(
        E=np.eye(2), A=np.array([[-b / J, -spring / J], [1.0, 0.0]]),
        B=np.array([[Kt / J], [0.0]]), C=np.array([[1.0, 0.0]]), Qc=np.diag([1.0, 1e-6]),
        R=np.array([[1e-4]]), state_names=("speed", "angle"), input_names=("current",),
        output_names=("speed",))


def _report(spring: float) -> dict[str, object]:
    # steps between several levels: a spring-held speed's two-level capture is refused
    # before (nothing in it tells an actuator limit from a gain, `test_limit_ambiguity`)
    holds = np.random.default_rng(3).uniform(-1.0, 1.0, size=100)
    u = (0.6 + 0.25 * np.repeat(holds, round(0.3 / T)))[:, None]
    y = capture(_speed(spring), T, u, seed=2, sigma=0.01)
    return identify(u, y, T, kind="state_space", run_filter=False).report


def _failed_replay() -> ReplayFigures:
    """A replay of the capture that reported a fault, as seeds 202 and 209 did."""
    return ReplayFigures([], 2.0, 100, 1.0, {"fault_free": 0.5, "fault": 0.5}, 0.0, 1.0,
                         (0.8, 1.2), first_fault="identify.log at 4.63 s", gamma_max=0.7,
                         f1=0.15)


def test_a_spring_held_speed_hides_a_loss_at_steady_state_and_the_refusal_says_so() -> None:
    report = _report(0.4)
    per_input = report["steady_state_loss"]["per_input"]  # type: ignore[index]
    assert per_input[0] * 0.3 < 0.1 * STEADY_LOSS_NOISE
    checks = {c.check: c for c in report_checks(report, _failed_replay())}
    steady = checks["steady_state_loss"]
    assert not steady.passed and not steady.gating
    assert "settles at a level the input sets" in steady.advice
    cause = failure_cause([c.as_dict() for c in checks.values()])
    assert cause is not None and cause.startswith("a loss of 0.3 at a constant input")


def test_a_free_speed_shows_a_loss_at_steady_state() -> None:
    report = _report(0.0)
    per_input = report["steady_state_loss"]["per_input"]  # type: ignore[index]
    assert per_input[0] * 0.3 > 10 * STEADY_LOSS_NOISE
    checks = report_checks(report, _failed_replay())
    assert {c.check: c for c in checks}["steady_state_loss"].passed
    # the replay's failure is then the model's: no cause to name before it
    assert failure_cause([c.as_dict() for c in checks]) is None


def test_an_integrating_output_has_no_steady_state_to_judge() -> None:
    checks = report_checks({"dc_gain": None, "steady_state_loss": {"per_input": None}},
                           _failed_replay())
    assert {c.check: c for c in checks}["steady_state_loss"].passed
