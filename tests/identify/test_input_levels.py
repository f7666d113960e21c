"""identify reports how many levels the input took: a binary PRBS checks the model between
its two levels alone (a gain that changes with the level, as an actuator saturating at one
of them gives, goes unseen), which the report says as an advisory check."""

from __future__ import annotations

import numpy as np
import pytest

from monitor.app.identify_check import ReplayFigures, report_checks
from monitor.identify import validate as V
from monitor.identify.excitation import prbs
from sim_ecu.scenario import ScenarioError, scenario_from_dict


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


def test_a_multi_level_prbs_takes_its_levels_and_passes() -> None:
    u = prbs(60.0, 0.002, level=-19.7, amplitude=3.2, clock=0.1, seed=4, levels=5)
    assert set(np.round(np.unique(u), 6)) == set(np.round(-19.7 + 3.2 * np.linspace(-1, 1, 5), 6))
    levels, passed, advice, _ = _levels_check(u)
    assert levels == [5]
    assert passed and advice == ""


def test_a_scenario_asks_for_a_multi_level_prbs_and_a_bad_count_is_one_line() -> None:
    table = {"level": 24.0, "amplitude": 2.0, "clock": 0.2, "seed": 1}
    steps = scenario_from_dict({"name": "s", "duration": 20.0, "voltage": {
        "prbs": table | {"levels": 4}}}).voltage_steps
    assert len({v for _, v in steps}) == 4
    with pytest.raises(ScenarioError, match=r"\[voltage.prbs\]: levels must be a whole "
                                            r"number from 2 to 1000, got 2.5"):
        scenario_from_dict({"name": "s", "duration": 20.0, "voltage": {
            "prbs": table | {"levels": 2.5}}})
