"""`diagnosis_lines`: what a replay found, read back from a result with known stretches."""

from __future__ import annotations

from monitor.archive.result import (
    SHOWN_STRETCHES,
    LogResult,
    NodeResult,
    Transition,
    diagnosis_lines,
)


def _result(transitions: tuple[Transition, ...], t_first: float = 1.78e9,
            t_last: float = 1.78e9 + 60.0) -> LogResult:
    node = NodeResult(node=3, seconds_in_state={"fault_free": 45.0, "fault": 15.0},
                      transitions=transitions, samples=6000, worst_nis=2.0,
                      seconds_model_mismatch=0.0)
    return LogResult(log="run.mf4", ok=True, t_first=t_first, t_last=t_last, nodes=(node,))


def test_each_stretch_away_from_fault_free_is_listed_from_the_log_start() -> None:
    t0 = 1.78e9
    lines = diagnosis_lines(_result((
        Transition(t0, "no_data", "fault_free", "estimate", 0.0),
        Transition(t0 + 25.04, "fault_free", "fault", "estimate", 0.396),
        Transition(t0 + 40.04, "fault", "fault_free", "estimate", 0.0),
    )))
    assert lines[0] == "node 3: fault_free 45.00 s, fault 15.00 s"
    assert lines[1] == "  fault          25.04 s ->     40.04 s (15.00 s, gamma^ 0.40 at its start)"
    assert lines[2] == "times from the log's first frame (2026-05-28 20:26:40.000 UTC)"
    assert len(lines) == 3


def test_a_node_that_flaps_gets_a_count_not_a_page() -> None:
    t0 = 1.78e9
    flaps = []
    for k in range(SHOWN_STRETCHES + 3):
        flaps += [Transition(t0 + 2 * k + 1, "fault_free", "fault", "estimate", 0.5),
                  Transition(t0 + 2 * k + 2, "fault", "fault_free", "estimate", 0.0)]
    lines = diagnosis_lines(_result(tuple(flaps)))
    assert sum(x.startswith("  fault ") for x in lines) == SHOWN_STRETCHES
    assert "  ... and 3 more (the events have each)" in lines


def test_a_log_without_frames_says_nothing() -> None:
    assert diagnosis_lines(LogResult(log="empty.log", ok=False)) == []
