"""identify reports how many levels the input took: a binary PRBS checks the model between
its two levels alone (a gain that changes with the level, as an actuator saturating at one
of them gives, goes unseen), which the report says as an advisory check."""

from __future__ import annotations

import numpy as np

from monitor.app.identify_check import ReplayFigures, report_checks
from monitor.identify import validate as V
from monitor.identify.excitation import prbs


def _levels_check(u: np.ndarray) -> tuple[list[int], bool, str, bool]:
    excitation = V.check_excitation(u, 2, ["u"])
    replay = ReplayFigures([], 0.0, 10, 1.0, {"fault_free": 1.0}, 0.0, 1.0, (0.5, 1.5),
                           gamma_max=0.02, f1=0.15)
    check = {c.check: c for c in report_checks({"excitation": excitation}, replay)
             }["input_levels"]
    levels = excitation["input_levels"]
    assert isinstance(levels, list)
    return levels, check.passed, check.advice, check.gating


def test_a_binary_prbs_is_two_levels_and_said_so() -> None:
    u = prbs(60.0, 0.002, level=-19.7, amplitude=3.2, clock=0.1, seed=4)
    levels, passed, advice, gating = _levels_check(u)
    assert levels == [2]
    assert not passed and not gating
    assert "two levels" in advice and "saturates" in advice


def test_random_steps_take_many_levels() -> None:
    rng = np.random.default_rng(1)
    u = np.repeat(rng.uniform(-1.0, 1.0, size=600), 50)[:, None] + 12.0
    levels, passed, advice, _ = _levels_check(u)
    assert levels[0] > 100
    assert passed and advice == ""


def test_levels_closer_than_the_resolution_are_one() -> None:
    u = prbs(60.0, 0.002, level=5.0, amplitude=1.0, clock=0.1, seed=2)
    u = u + 1e-6 * np.random.default_rng(0).standard_normal(u.shape)  # a float's jitter
    assert V.check_excitation(u, 2, ["u"])["input_levels"] == [2]
