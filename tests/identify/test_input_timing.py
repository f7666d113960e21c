"""identify says when the input frames go out together with the output frames in either
order: the monitor pairs an input change with the output sample it has not yet acted on or
with the next one, as the bus happens to order them, which no input delay fits (the rig
zoo's seed 209: 15 of 46 changes one sample off, its own capture replayed as faulty, refused
with advice to try other orders). A refusal then names that first."""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from monitor.app.identify import NodeCapture, _row, fit_series
from monitor.app.identify_check import (
    ReplayFigures,
    failure_cause,
    input_timing,
    report_checks,
)
from monitor.bus.codec import Decoded

T = 0.01


def _timing(order: str, n: int = 3000, seed: int = 0) -> dict[str, object]:
    """The input timing of rows collected from an ECU that, every period, sends its output
    frame and, at changes of its command, the command's frame: "input_first" or
    "output_first" always, or "either" at random (both within 3 % of a period)."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-1.0, 1.0, n), rng.integers(3, 40, n))[:n]
    nc = NodeCapture()
    counts: dict[str, int] = defaultdict(int)
    for k in range(n):
        t_out = k * T + 0.02 * T
        first = order == "input_first" or (order == "either" and rng.random() < 0.5)
        t_in = t_out + (-0.01 if first else 0.01) * T
        out = Decoded("out", 1, t_out, 0.0, None, {}, outputs=(float(rng.standard_normal()),))
        cmd = Decoded("in", 1, t_in, float(u[k]), None, {}, inputs=((0, float(u[k])),))
        for d in ((cmd, out) if first else (out, cmd)):
            _row(nc, d, 1, counts)
    s = fit_series(nc, 1, [], counts)
    return input_timing(s.t, s.change_t, s.T)


def _check(timing: dict[str, object]) -> tuple[bool, str, str | None]:
    replay = ReplayFigures([], 2.0, 100, 1.0, {"fault_free": 0.5, "fault": 0.5}, 0.0, 1.0,
                           (0.8, 1.2), first_fault="identify.log at 4.25 s", gamma_max=0.7,
                           f1=0.15)
    checks = report_checks({"input_timing": timing}, replay)
    c = {c.check: c for c in checks}["input_timing"]
    assert not c.gating
    return c.passed, c.advice, failure_cause([c.as_dict() for c in checks])


def test_frames_sent_together_in_either_order_are_said_first() -> None:
    timing = _timing("either")
    n = timing["changes"]
    assert isinstance(n, int) and n > 100
    assert timing["before_output"] + timing["after_output"] == n  # type: ignore[operator]
    assert min(timing["before_output"], timing["after_output"]) > 0.3 * n  # type: ignore
    passed, advice, cause = _check(timing)
    assert not passed
    assert "either order" in advice and "no input delay fits" in advice
    assert cause is not None and cause.startswith(advice)


def test_frames_sent_together_in_one_order_pair_alike() -> None:
    for order in ("input_first", "output_first"):
        timing = _timing(order)
        passed, advice, cause = _check(timing)
        assert passed and advice == "" and cause is None, (order, timing)


def test_an_input_between_the_outputs_is_no_question() -> None:
    t = np.arange(100, dtype=np.float64) * T
    change_t = np.full(100, np.nan)
    change_t[5::10] = t[5::10] - 0.5 * T  # half a period before the sample it is held at
    timing = input_timing(t, change_t, T)
    assert timing["changes"] == 10
    assert timing["before_output"] == timing["after_output"] == 0
    assert _check(timing)[0]
