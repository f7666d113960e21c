"""Scoring a replay's diagnosis events against the true gamma of a run.

The events file holds one JSON object per transition (as `replay --events` writes them:
`t` in the capture's time, `node`, `state`, `previous`, `gamma`, `cause`, ...). A node's
reported state is `no_data` until its first event, then the state of its latest event.
Model mismatch has been reported two ways while the monitor changed: as a state
(`"state": "model_mismatch"`) and as a flag beside the state (`"model_mismatch": true`,
events of `"kind": "model_mismatch"` when only the flag changes). Both are read: the state
is what accuracy compares, and the mismatch share counts the time either says mismatch.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .plant import step_gamma

GRACE_S = 0.3
SKIP_S = 2.0
ALARM = ("fault", "outage")


def true_state(gamma: float) -> str:
    if gamma <= 0.0:
        return "fault_free"
    if gamma >= 1.0:
        return "outage"
    return "fault"


@dataclass
class NodeTruth:
    """A node's true gamma in the capture's time: value from each step's time on."""

    start: float  # capture time of the run's start (for this node)
    duration: float
    steps: list[tuple[float, float]]  # (capture time, gamma from then on)

    def gamma_at(self, t: np.ndarray) -> np.ndarray:
        return step_gamma(self.steps, t)


@dataclass
class NodeScore:
    accuracy: float
    mismatch_share: float  # of the scored time spent in model_mismatch
    no_data_share: float
    false_alarms: int
    delays: list[float]  # onset to the first fault/outage, per loss (inf: missed)
    states: dict[str, float] = field(default_factory=dict)  # share of scored time per state


Event = tuple[float, str, bool]  # (t, state, model-mismatch flag)


def read_events(path: Path) -> tuple[dict[int, list[Event]], int]:
    """Per node, its transitions (t, new state, mismatch flag); and unreadable lines. A
    drive's own reports (kind ``drive``) are no transition."""
    out: dict[int, list[Event]] = {}
    bad = 0
    if not path.exists():
        return out, 0
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        try:
            ev = json.loads(line)
            if ev.get("kind") == "drive":  # what a CANopen drive says: no state of the node
                continue
            state = str(ev["state"])
            flag = bool(ev.get("model_mismatch", False)) or state == "model_mismatch"
            out.setdefault(int(ev["node"]), []).append((float(ev["t"]), state, flag))
        except (ValueError, KeyError, TypeError):
            bad += 1
    for v in out.values():
        v.sort(key=lambda e: e[0])
    return out, bad


def score_node(events: list[Event], truth: NodeTruth, dt: float = 1e-3) -> NodeScore:
    t = np.arange(truth.start + SKIP_S, truth.start + truth.duration, dt)
    g = truth.gamma_at(t)
    true = np.array([true_state(float(x)) for x in (0.0, 0.5, 1.0)])
    true_idx = np.where(g <= 0.0, 0, np.where(g >= 1.0, 2, 1))
    true_s = true[true_idx]
    rep = np.full(t.size, "no_data", dtype=object)
    flag = np.zeros(t.size, dtype=bool)
    for te, st, fl in events:
        rep[t >= te] = st
        flag[t >= te] = fl
    keep = np.ones(t.size, dtype=bool)
    prev = 0.0
    trans: list[tuple[float, float, float]] = []  # (time, old gamma, new gamma)
    for t0, v in truth.steps:
        if v != prev:
            trans.append((t0, prev, v))
            keep &= ~((t >= t0) & (t < t0 + GRACE_S))
        prev = v
    n = int(keep.sum())
    acc = float(np.mean(rep[keep] == true_s[keep])) if n else math.nan
    states = {s: float(np.mean(rep[keep] == s)) for s in set(rep[keep])} if n else {}
    # false alarms: a transition into fault/outage while the node is truly healthy
    fa = 0
    for te, st, _ in events:
        if st not in ALARM or te < truth.start + SKIP_S:
            continue
        gi = truth.gamma_at(np.array([te]))[0]
        in_grace = any(t0 <= te < t0 + GRACE_S for t0, _, _ in trans)
        if gi <= 0.0 and not in_grace:
            fa += 1
    # detection delays: from each onset of a loss >= 0.3 to the first fault/outage state
    delays: list[float] = []
    for i, (t0, old, new) in enumerate(trans):
        if not (old <= 0.0 and new >= 0.3):
            continue
        t_end = trans[i + 1][0] if i + 1 < len(trans) else truth.start + truth.duration
        state_at = "no_data"
        for te, st, _ in events:
            if te <= t0:
                state_at = st
        if state_at in ALARM:
            delays.append(0.0)
            continue
        hit = [te for te, st, _ in events if t0 < te < t_end and st in ALARM]
        delays.append(hit[0] - t0 if hit else math.inf)
    mism = float(np.mean(flag[keep])) if n else math.nan
    return NodeScore(accuracy=acc, mismatch_share=mism,
                     no_data_share=states.get("no_data", 0.0), false_alarms=fa,
                     delays=delays, states=states)
