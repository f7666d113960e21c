"""What one log's replay gives the archive summary: `LogResult`, built from an engine's
`EngineRun` (or from the reason a log could not be read). Plain, picklable data: results
travel back from worker processes and cluster workers."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime

from monitor.archive.engine import EngineRun
from monitor.diagnosis.classifier import HealthState
from monitor.pipeline.events import HEALTH

__all__ = ["STATES", "LogResult", "NodeResult", "Transition", "diagnosis_lines",
           "failed_result", "log_result", "state_timeline"]

STATES: tuple[str, ...] = tuple(s.label for s in HealthState)
"""Every health state's label, in the order of their values on the bus."""

INITIAL_STATE = HealthState.NO_DATA.label
"""A node's state before its first transition (the classifier starts there)."""


@dataclass(frozen=True)
class Transition:
    """A change of a node's health state at bus time `t`."""

    t: float
    previous: str
    state: str
    cause: str
    gamma: float


def state_timeline(transitions: tuple[Transition, ...], t_first: float,
                   t_last: float) -> list[tuple[float, float, str]]:
    """(start, end, state) for every stretch of one state of a node, covering [t_first,
    t_last]; the node is in `INITIAL_STATE` until its first transition."""
    stretches: list[tuple[float, float, str]] = []
    start, state = t_first, INITIAL_STATE
    for tr in transitions:
        at = min(max(tr.t, start), t_last)
        if at > start:
            stretches.append((start, at, state))
        start, state = at, tr.state
    if t_last > start or not stretches:
        stretches.append((start, t_last, state))
    return stretches


@dataclass(frozen=True)
class NodeResult:
    """One node of one log: seconds in each health state between the log's first and last
    frame, its health transitions, estimated samples, worst NIS (NaN without samples), and
    seconds with the model-mismatch flag up (beside the state)."""

    node: int
    seconds_in_state: Mapping[str, float]
    transitions: tuple[Transition, ...]
    samples: int
    worst_nis: float
    seconds_model_mismatch: float = 0.0

    def timeline(self, t_first: float, t_last: float) -> list[tuple[float, float, str]]:
        """(start, end, state) for every stretch of one state, covering [t_first, t_last]."""
        return state_timeline(self.transitions, t_first, t_last)


@dataclass(frozen=True)
class LogResult:
    """One log of the run: replayed (`ok`) or not, with the reason. A log that failed after
    its first frame (damaged, cut short, or nothing decoded) keeps what was read: its
    frames, counters, nodes and outputs are those of the part before the damage."""

    log: str
    ok: bool
    reason: str = ""
    frames: int = 0
    wall_s: float = 0.0
    t_first: float | None = None
    t_last: float | None = None
    counters: Mapping[str, int] = field(default_factory=dict)
    nodes: tuple[NodeResult, ...] = ()
    events: str | None = None
    rrd: str | None = None
    rrd_parts: int = 0
    """How many files the recording took: `rrd`, then ``<stem>-part0002.rrd``... beside it
    (`monitor.sinks.rerun.REPLAY_PART_BYTES`)."""

    @property
    def duration_s(self) -> float:
        """Bus time between the first and the last frame."""
        if self.t_first is None or self.t_last is None:
            return 0.0
        return self.t_last - self.t_first


def failed_result(log: str, reason: str, *, frames: int = 0, wall_s: float = 0.0) -> LogResult:
    return LogResult(log=log, ok=False, reason=reason, frames=frames, wall_s=wall_s)


def log_result(log: str, run: EngineRun, *, wall_s: float, events: str | None,
               rrd: str | None, rrd_parts: int = 0) -> LogResult:
    """The summary of one replayed log from what its engine reported (failed, with the
    engine's reason, when the run has a `failure`)."""
    t_first = run.t_first
    t_last = run.t_last
    nodes: list[NodeResult] = []
    for node in sorted(run.nodes):
        stats = run.nodes[node]
        node_events = [e for e in run.transitions if e.node == node]
        transitions = tuple(Transition(e.t, e.previous, e.state, e.cause, e.gamma)
                            for e in node_events if e.kind == HEALTH)
        seconds = dict.fromkeys(STATES, 0.0)
        flagged = 0.0
        if t_first is not None and t_last is not None:
            for start, end, state in state_timeline(transitions, t_first, t_last):
                seconds[state] = seconds.get(state, 0.0) + (end - start)
            # every event carries the flag after it: the flag's own timeline, from down
            since: float | None = None
            for e in node_events:
                at = min(max(e.t, t_first), t_last)
                if e.model_mismatch and since is None:
                    since = at
                elif not e.model_mismatch and since is not None:
                    flagged += at - since
                    since = None
            if since is not None:
                flagged += t_last - since
        nodes.append(NodeResult(node=node, seconds_in_state=seconds, transitions=transitions,
                                samples=stats.samples, worst_nis=stats.worst_nis,
                                seconds_model_mismatch=flagged))
    return LogResult(log=log, ok=run.failure is None, reason=run.failure or "",
                     frames=run.frames, wall_s=wall_s, t_first=t_first,
                     t_last=t_last, counters=dict(sorted(run.counters.items())),
                     nodes=tuple(nodes), events=events, rrd=rrd, rrd_parts=rrd_parts)


SHOWN_STRETCHES = 8
"""Stretches of a node's diagnosis `diagnosis_lines` lists one by one; more are counted."""


def diagnosis_lines(result: LogResult) -> list[str]:
    """What the replay found, for a person: per node the seconds in each health state and
    every stretch away from ``fault_free`` (its start and end from the log's first frame, its
    length, and gamma^ as it was entered), then the log's start as a date. The events file
    has the same transitions in bus time; this is the reading a user would otherwise do by
    hand."""
    if result.t_first is None or result.t_last is None:
        return []
    t0, t1 = result.t_first, result.t_last
    lines = []
    for nr in result.nodes:
        shares = ", ".join(f"{state} {sec:.2f} s" for state, sec in nr.seconds_in_state.items()
                           if sec > 0)
        mm = (f"; model mismatch flagged {nr.seconds_model_mismatch:.2f} s"
              if nr.seconds_model_mismatch > 0 else "")
        lines.append(f"node {nr.node}: {shares or 'no time'}{mm}")
        gamma_at = {tr.t: tr.gamma for tr in nr.transitions}
        away = [(a, b, st) for a, b, st in nr.timeline(t0, t1)
                if st != "fault_free" and not (st == INITIAL_STATE and a == t0)]
        for a, b, st in away[:SHOWN_STRETCHES]:
            g = gamma_at.get(a)
            at_start = f", gamma^ {g:.2f} at its start" if g is not None and g == g else ""
            lines.append(f"  {st:<10s} {a - t0:9.2f} s -> {b - t0:9.2f} s ({b - a:.2f} s"
                         f"{at_start})")
        if len(away) > SHOWN_STRETCHES:
            lines.append(f"  ... and {len(away) - SHOWN_STRETCHES} more (the events have each)")
    start = datetime.fromtimestamp(t0, UTC) if 0 < t0 < 32503680000 else None
    lines.append("times from the log's first frame" + (
        f" ({start:%Y-%m-%d %H:%M:%S.%f}"[:-3] + " UTC)" if start else f" (t = {t0:.3f} s)"))
    return lines
