"""A capture whose input took two levels alone, the output's levels not in their ratio, is
refused in one line: an actuator that clips the larger level (the rig zoo's seed 200:
voltage -> speed, a two-level PRBS at -16.5 and -22.9 V, the actuator's limit at 21.7 V)
looks like a smaller gain plus an offset, which the fit carries on a slow mode (fit 98 %),
and fresh runs at other levels then meet the model wrong (the mismatch flag up 97 % of the
time, false alarms). The same two levels through a plant without a limit, and random steps
through the limited actuator, are accepted."""

from __future__ import annotations

import numpy as np
import pytest

from monitor.identify import identify, prbs
from monitor.identify.errors import IdentifyError
from monitor.identify.lti import c2d, dsim

T = 0.004
DURATION = 40.0
LEVEL, AMPLITUDE = -19.7, 3.2
LIMIT = 21.7  # the actuator clips |u| here: the larger level's 22.9 V
POLE, GAIN = -8.0, 0.5  # a first-order speed, 0.5 (rad/s)/V settled


def _capture(u: np.ndarray, limit: float | None) -> np.ndarray:
    """The speed under the command u, the actuator clipping |u| at `limit` (None: none),
    with sensor noise 1 % of the output's swing."""
    delivered = u if limit is None else np.clip(u, -limit, limit)
    Ad, Bd = c2d(np.array([[POLE]]), np.array([[-POLE * GAIN]]), T)
    x0 = np.array([GAIN * float(delivered[0, 0])])
    y = dsim(Ad, Bd, np.eye(1), delivered, x0)
    return y + np.random.default_rng(2).normal(0.0, 0.01 * GAIN * 2 * AMPLITUDE, y.shape)


def _two_levels() -> np.ndarray:
    return prbs(DURATION, T, level=LEVEL, amplitude=AMPLITUDE, clock=0.4, seed=4)


def test_two_levels_through_a_limit_are_refused_in_one_line() -> None:
    u = _two_levels()
    with pytest.raises(IdentifyError) as err:
        identify(u, _capture(u, LIMIT), T, kind="state_space")
    msg = str(err.value)
    assert "\n" not in msg
    assert "two levels" in msg and "limit" in msg and "record steps between several levels" in msg


def test_the_same_two_levels_without_a_limit_are_accepted() -> None:
    u = _two_levels()
    ident = identify(u, _capture(u, None), T, kind="state_space")
    assert ident.report["excitation"]["input_levels"] == [2]


def test_random_steps_through_the_limit_are_not_refused_for_it() -> None:
    rng = np.random.default_rng(1)
    holds = rng.uniform(-1.0, 1.0, size=round(DURATION / 0.4))
    u = (LEVEL + AMPLITUDE * np.repeat(holds, round(0.4 / T)))[:, None]
    try:
        identify(u, _capture(u, LIMIT), T, kind="state_space")
    except IdentifyError as exc:
        assert "two levels" not in str(exc)


def _spring_held_speed(u: np.ndarray, limit: float | None) -> np.ndarray:
    """A speed held by a spring (poles -5 and -40 1/s, a zero at s = 0: it settles at zero
    whatever the input), the actuator clipping |u| at `limit`, with sensor noise."""
    delivered = u if limit is None else np.clip(u, -limit, limit)
    A = np.array([[0.0, 1.0], [-200.0, -45.0]])
    Ad, Bd = c2d(A, np.array([[0.0], [1.0]]), T)
    y = dsim(Ad, Bd, np.array([[0.0, 40.0]]), delivered - delivered[0])
    return y + np.random.default_rng(3).normal(0.0, 0.02 * float(np.ptp(y)), y.shape)


def test_two_levels_of_a_speed_held_by_a_spring_are_refused_in_one_line() -> None:
    u = prbs(DURATION, T, level=-14.2, amplitude=4.0, clock=0.4, seed=4)
    with pytest.raises(IdentifyError) as err:
        identify(u, _spring_held_speed(u, 17.7), T, kind="state_space")
    msg = str(err.value)
    assert "\n" not in msg
    assert "does not settle" in msg and "record steps between several levels" in msg


def _fast_speed(u: np.ndarray, limit: float) -> np.ndarray:
    """A fast first-order speed (10 ms) under the command u (T = 2 ms), the actuator
    clipping |u| at `limit`, with sensor noise 1 % of the output's swing."""
    delivered = np.clip(u, -limit, limit)
    pole, gain = -110.0, 0.42
    Ad, Bd = c2d(np.array([[pole]]), np.array([[-pole * gain]]), 0.002)
    y = dsim(Ad, Bd, np.eye(1), delivered, np.array([gain * float(delivered[0, 0])]))
    return y + np.random.default_rng(6).normal(0.0, 0.01 * gain * 38.0, y.shape)


def test_a_limit_the_fit_averages_into_its_gain_is_refused() -> None:
    """The rig zoo's seed 52: a fast speed whose actuator clips the larger of two levels
    (-3.3 and -41.2 V) by 5 %. The fit goes through zero with a gain between the two
    levels' (no offset of its own: the model's offset reads 0), so the data's offset is
    what shows the limit; accepted, a healthy run at other levels had the mismatch flag up
    69 % of the time and 14 false alarms. Without the limit the same capture is accepted."""
    u = prbs(DURATION, 0.002, level=-22.2, amplitude=18.95, clock=0.023, seed=5)
    with pytest.raises(IdentifyError) as err:
        identify(u, _fast_speed(u, 39.1), 0.002, kind="state_space")
    msg = str(err.value)
    assert "\n" not in msg
    assert "two levels" in msg and "limit" in msg and "record steps between several levels" in msg
    ident = identify(u, _fast_speed(u, 100.0), 0.002, kind="state_space")
    assert ident.report["excitation"]["input_levels"] == [2]
