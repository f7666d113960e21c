"""A load that steps while the capture runs (the rig zoo's seeds 55, 61, 76, 79, 90, 91, 92:
a drive's load torque changing every 4-12 s) made every linear fit read it as a change of
the plant: the halves of the capture fit differently and identify refused a healthy
capture. `identify(..., load=True)` estimates the load as a piecewise-constant input bias
from the model's filter (`monitor.identify.load`) and fits with it: the changes are found
where they were made, the gain is the plant's, and a fault in the middle of a capture is
still refused (the steps the refit finds then follow the input: its innovations correlate
with the input)."""

from __future__ import annotations

import numpy as np
import pytest

from monitor.identify import identify
from monitor.identify.errors import PlantChangeError
from monitor.identify.lti import c2d, dsim

T = 0.01
DURATION = 60.0
POLE, GAIN = -5.0, 3.0  # a speed from a torque: 200 ms
CHANGES = [(9.3, 0.25), (21.7, -0.2), (33.1, 0.3), (44.6, 0.05), (52.2, -0.25)]


def _input() -> np.ndarray:
    rng = np.random.default_rng(11)
    N = round(DURATION / T)
    u = np.empty(N)
    k = 0
    level = 1.0
    while k < N:
        hold = int(rng.integers(20, 100))
        u[k:k + hold] = level
        level = 2.0 if level == 1.0 else 1.0
        k += hold
    levels = rng.uniform(0.8, 1.2, N // 20 + 1).repeat(20)[:N]  # several levels, not two
    return (u * levels)[:, None]


def _load(changes: list[tuple[float, float]]) -> np.ndarray:
    N = round(DURATION / T)
    d = np.zeros(N)
    for t, level in changes:
        d[round(t / T):] = level
    return d[:, None]


def _capture(u: np.ndarray, d: np.ndarray, gamma: np.ndarray | None = None) -> np.ndarray:
    Ad, Bd = c2d(np.array([[POLE]]), np.array([[-POLE * GAIN]]), T)
    eff = u * (1.0 - gamma) if gamma is not None else u
    # the load acts from the step after its change: the held input drives the next sample
    y = dsim(Ad, Bd, np.eye(1), np.vstack([eff[:1], eff[:-1]]) + np.vstack([d[:1], d[:-1]]),
             np.array([GAIN * float(eff[0, 0] + d[0, 0])]))
    return y + np.random.default_rng(5).normal(0.0, 0.02, y.shape)


def test_load_steps_are_refused_by_the_linear_fit() -> None:
    u = _input()
    with pytest.raises(PlantChangeError,
                       match=r"the halves of the capture fit different models .*load steps"):
        identify(u, _capture(u, _load(CHANGES)), T, kind="state_space", run_filter=False)


def test_load_steps_are_found_and_the_gain_is_the_plants() -> None:
    u = _input()
    ident = identify(u, _capture(u, _load(CHANGES)), T, kind="state_space", load=True,
                     run_filter=False)
    found = ident.report["load"]["change_times_s"]
    assert len(found) == len(CHANGES), found
    for (t, _), f in zip(CHANGES, found, strict=True):
        assert f == pytest.approx(t, abs=0.05)
    levels = np.diff(np.asarray(ident.report["load"]["levels"])[:, 0])
    assert levels == pytest.approx(np.diff([0.0] + [lvl for _, lvl in CHANGES]), abs=0.03)
    model = ident.model
    gain = -model.C[0] @ np.linalg.solve(model.A, model.B[:, 0])
    assert float(gain) == pytest.approx(GAIN, rel=0.03)
    assert ident.report["fit"]["nrmse_holdout_pct"][0] > 90.0


def test_a_fault_in_the_middle_is_still_refused() -> None:
    u = _input()
    gamma = np.zeros_like(u)
    gamma[u.shape[0] // 2:] = 0.5
    # the refit's steps follow the input (at 1 s apart they mimic the halved gain): refused
    with pytest.raises(PlantChangeError, match=r"the load steps a refit finds follow the "
                                               r"input .* the input's effect changes within "
                                               r"the capture"):
        identify(u, _capture(u, _load([]), gamma), T, kind="state_space", load=True,
                 run_filter=False)
