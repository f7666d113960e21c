"""An input that changes a few times, each a step the plant settles from well inside the
hold, identifies a plant whose time constants are short against the holds (the rig zoo's
seed 16: a PRBS switching every 3 s, 6 changes in the training part, diagnosed right,
refused while 10 were asked for). Fewer than MIN_CHANGES in the training part, or none in
the held-out part that checks the model, is refused in one line."""

from __future__ import annotations

import numpy as np
import pytest

from monitor.identify import identify
from monitor.identify.errors import IdentifyError
from monitor.identify.lti import c2d, dsim
from monitor.identify.validate import MIN_CHANGES

T = 0.01
DURATION = 60.0
POLE, GAIN = -20.0, 2.0  # a first-order plant, 50 ms: settled within each hold


def _steps(levels: list[float]) -> np.ndarray:
    """The input at `levels` in turn, each held an equal share of the capture."""
    N = round(DURATION / T)
    idx = np.minimum(np.arange(N) * len(levels) // N, len(levels) - 1)
    return np.asarray(levels, dtype=float)[idx][:, None]


def _capture(u: np.ndarray) -> np.ndarray:
    Ad, Bd = c2d(np.array([[POLE]]), np.array([[-POLE * GAIN]]), T)
    y = dsim(Ad, Bd, np.eye(1), u, np.array([GAIN * float(u[0, 0])]))
    return y + np.random.default_rng(5).normal(0.0, 0.01, y.shape)


def test_a_few_steps_of_a_fast_plant_identify_it() -> None:
    # 8 holds of 7.5 s: 5 changes in the training 70 %, 2 in the held-out 30 %
    u = _steps([1.0, 3.0, 2.0, 4.5, 1.5, 3.5, 0.5, 2.5])
    ident = identify(u, _capture(u), T, kind="state_space", run_filter=False)
    assert ident.order == 1
    assert ident.report["fit"]["nrmse_holdout_pct"][0] > 90.0
    gain = -ident.model.C[0] @ np.linalg.solve(ident.model.A, ident.model.B[:, 0])
    assert float(gain) == pytest.approx(GAIN, rel=0.02)


def test_too_few_changes_are_refused_in_one_line() -> None:
    u = _steps([1.0, 3.0, 2.0, 4.5, 4.5, 4.5, 1.5, 2.5])  # 3 changes in the training part
    assert MIN_CHANGES > 3
    with pytest.raises(IdentifyError, match=r"^input 'u1' changes only 3 times: record"):
        identify(u, _capture(u), T, kind="state_space", run_filter=False)


def test_an_input_that_stops_before_the_held_out_part_is_refused() -> None:
    u = _steps([1.0, 3.0, 2.0, 4.5, 1.5, 3.5, 2.5, 2.5, 2.5, 2.5])  # still from 42 s on
    with pytest.raises(IdentifyError, match=r"^input 'u1' does not change in the last 1800 "
                                            "samples, which check the model: record"):
        identify(u, _capture(u), T, kind="state_space", run_filter=False)
