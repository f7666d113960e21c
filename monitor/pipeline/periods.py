"""Sample periods between two output samples of a node, from a 4-bit alive counter and the
frames' time stamps, on a sample grid that late frames cannot move.

A 4-bit counter tells the periods k since the previous sample only modulo 16: k = k_c + 16 m
with k_c = lost + 1 in 1..16 (16: the same counter again). The time stamps pick m, and they
are read against the node's *grid*, the time its previous sample was due, not against the
previous frame's arrival: a frame can be late (a sender held up, a driver queue, a loaded
machine's virtual ECU sending its backlog back to back) but never early. So the largest m
whose due time ``grid + k T`` is not after the arrival is the reading that needs no frame to
have come early; a frame up to 15 periods late is read as late, where comparing with the
previous arrival would read a frame 8 periods late as 16 lost.

The grid follows the lower envelope of the arrivals: an arrival before its due time moves
the grid to it (the grid was anchored on a late frame, or the sender's clock is fast), and
one after it pulls the grid by `GRID_CREEP` of the lateness (a slow sender clock), too little
for a burst of late frames to move it.

Plain Python, run per frame by `monitor.pipeline.core.MonitorPipeline`; the columnar engine
compiles the same functions (`monitor.columnar.kernels`).
"""

from __future__ import annotations

import math

__all__ = ["GRID_CREEP", "GRID_TOLERANCE", "advance_grid", "counter_periods", "wrapped"]

GRID_CREEP = 1.0 / 64.0
"""Share of a frame's lateness by which the grid moves towards it."""

GRID_TOLERANCE = 0.5
"""Periods by which a frame may arrive before its due time and still be on it (the sender's
own timing jitter against the lower envelope)."""


def counter_periods(gap: float, k_counter: int) -> int:
    """Periods since the previous sample: ``k_counter + 16 m`` with the largest m >= 0 whose
    due time is not after the arrival; `gap` is the arrival minus the grid, in periods."""
    m = math.floor((gap + GRID_TOLERANCE - k_counter) / 16.0)
    return k_counter + 16 * max(0, m)


def wrapped(gap: float, since_last: float, silence_s: float) -> bool:
    """True if a frame repeating the previous counter is 16 m periods later (16 m - 1
    samples lost) rather than a duplicate or replay: due 16 periods or more after the grid
    (`gap`, in periods), and within the silence timeout of the previous sample
    (`since_last`, seconds). After a silence the counter is not trusted: the frame is taken
    as a replay."""
    return gap + GRID_TOLERANCE >= 16.0 and since_last < silence_s


def advance_grid(grid: float, t: float, k: int, period: float) -> float:
    """The grid after a sample `k` periods on, arriving at `t`."""
    due = grid + k * period
    if t <= due:
        return t
    return due + (t - due) * GRID_CREEP
