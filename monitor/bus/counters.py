"""Alive-counter supervision of the 4-bit E2E counters, per (kind or message, node) stream.

`CounterTracker.observe` classifies each decoded frame's counter against the previous one
of its stream as `CounterOutcome.OK`, ``REPEATED`` (a duplicate or replay) or ``JUMP``
(frames lost, `CounterCheck.lost` of them); counting the outcomes is the caller's job
(the pipeline's counters).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from monitor.bus.codec import Decoded

__all__ = ["CounterCheck", "CounterOutcome", "CounterTracker"]


class CounterOutcome(StrEnum):
    """Alive-counter verdict for one frame."""

    OK = "ok"  # first frame of its stream, or counter advanced by exactly 1
    REPEATED = "repeated"  # same counter as the previous frame: duplicate or replay
    JUMP = "jump"  # counter advanced by 2..15: frames lost (mod 16)


@dataclass(frozen=True, slots=True)
class CounterCheck:
    """The verdict on one frame's alive counter."""

    outcome: CounterOutcome
    lost: int = 0  # frames missing before this one (JUMP only), 1..14


class CounterTracker:
    """Per (kind, node) alive-counter supervision of the 4-bit E2E counters.

    A 4-bit counter can only tell losses modulo 16: 16 lost frames look like ``ok``, and
    an old frame replayed later looks like a jump. Timeouts catch the former, the CRC and
    timestamps the rest; this class only classifies.
    """

    def __init__(self) -> None:
        self._last: dict[tuple[str, int], int] = {}

    def update(self, kind: str, node: int, counter: int) -> CounterCheck:
        """Classify `counter` against the previous one of the same stream."""
        if not isinstance(counter, int) or not 0 <= counter <= 15:
            raise ValueError(f"alive counter must be an int in 0..15, got {counter!r}")
        key = (kind, node)
        last = self._last.get(key)
        self._last[key] = counter
        if last is None:
            return CounterCheck(CounterOutcome.OK)
        step = (counter - last) % 16
        if step == 1:
            return CounterCheck(CounterOutcome.OK)
        if step == 0:
            return CounterCheck(CounterOutcome.REPEATED)
        return CounterCheck(CounterOutcome.JUMP, step - 1)

    def observe(self, sample: Decoded) -> CounterCheck | None:
        """`update` for a decoded frame; None for frames without a counter (truth)."""
        if sample.counter is None:
            return None
        return self.update(sample.kind, sample.node, sample.counter)
