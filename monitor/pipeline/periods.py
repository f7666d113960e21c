"""Sample periods between two output samples of a node, from a 4-bit alive counter and the
time since the previous sample.

A 4-bit counter tells the periods k since the previous sample only modulo 16: k = k_c + 16 m
with k_c = lost + 1 in 1..16 (16: the same counter again). The time stamps pick m. A frame
can be late (a sender held up, a driver queue, a loaded machine's virtual ECU sending its
backlog back to back) but never early, so m is the largest number of whole counter wraps
that fit in the time since the previous sample: a frame up to 15 periods late is read as
late. (Rounding to the nearest wrap, as before, read a frame 8 periods late as 16 lost: on
a loaded machine, dozens of times an hour.) A frame that is 16 periods late or more cannot
be told from one after 16 lost by its counter and time alone; it is read as the latter.

Plain Python, run per frame by `monitor.pipeline.core.MonitorPipeline`; the columnar engine
compiles the same functions (`monitor.columnar.kernels`).
"""

from __future__ import annotations

import math

__all__ = ["EARLY_TOLERANCE", "counter_periods", "wrapped"]

EARLY_TOLERANCE = 0.5
"""Periods by which a frame may come before its due time and still count as on it (the
previous frame's own lateness, sender jitter)."""


def counter_periods(k_time: float, k_counter: int) -> int:
    """Periods since the previous sample: ``k_counter + 16 m`` with the largest m >= 0 that
    fits in `k_time`, the time since the previous sample in periods."""
    m = math.floor((k_time + EARLY_TOLERANCE - k_counter) / 16.0)
    return k_counter + 16 * max(0, m)


def wrapped(dt: float, rate: float, silence_s: float) -> bool:
    """True if a frame repeating the previous counter is 16 m periods later (16 m - 1
    samples lost) rather than a duplicate or replay: `dt` seconds after the previous sample
    is 16 periods at `rate` or more, and within the silence timeout. After a silence the
    counter is not trusted: the frame is taken as a replay."""
    return dt * rate + EARLY_TOLERANCE >= 16.0 and dt < silence_s
