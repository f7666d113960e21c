"""Alive-counter supervision of the 4-bit E2E counters, per (kind or message, node) stream.

`frames_lost` is the rule, over plain integers (the columnar engine compiles it);
`CounterTracker.observe` classifies each decoded frame's counter against the previous one
of its stream as `CounterOutcome.OK`, ``REPEATED`` (a duplicate or replay) or ``JUMP``
(frames lost, `CounterCheck.lost` of them); counting the outcomes is the caller's job
(the pipeline's counters).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from monitor.bus.codec import Decoded

__all__ = ["REPEATED", "CounterCheck", "CounterOutcome", "CounterTracker", "frames_lost"]

REPEATED = -1
"""`frames_lost` of the same counter again: a duplicate or replay."""


def frames_lost(last: int, counter: int) -> int:
    """Frames lost between a stream's previous alive counter `last` (-1: none yet) and
    `counter`: 0 for the next counter (or the stream's first), 1..14 after a jump,
    `REPEATED` for the same counter again."""
    if last < 0:
        return 0
    step = (counter - last) % 16
    return REPEATED if step == 0 else step - 1


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
        lost = self.lost(kind, node, counter)
        if lost == 0:
            return CounterCheck(CounterOutcome.OK)
        if lost == REPEATED:
            return CounterCheck(CounterOutcome.REPEATED)
        return CounterCheck(CounterOutcome.JUMP, lost)

    def lost(self, kind: str, node: int, counter: int) -> int:
        """`frames_lost` of `counter` in the (kind, node) stream; remembers it."""
        key = (kind, node)
        lost = frames_lost(self._last.get(key, -1), counter)
        self._last[key] = counter
        return lost

    def last(self, streams: Sequence[tuple[str, int]]) -> list[int]:
        """The previous counter of each (kind, node) stream (-1: none yet): where a chunk of
        frames judged in one loop (the columnar engine's) starts from."""
        return [self._last.get(key, -1) for key in streams]

    def remember(self, streams: Sequence[tuple[str, int]], counters: Sequence[int]) -> None:
        """Each stream's latest counter (-1: none yet), where such a loop ended."""
        for key, counter in zip(streams, counters, strict=True):
            if counter >= 0:
                self._last[key] = counter

    def observe(self, sample: Decoded) -> CounterCheck | None:
        """`update` for a decoded frame; None for frames without a counter (truth)."""
        if sample.counter is None:
            return None
        return self.update(sample.kind, sample.node, sample.counter)
