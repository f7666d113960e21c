"""A route: what one arbitration ID of a bus is and how its frames are read.

Both codecs -- `monitor.bus.codec.MotorDatabase` (our bus, built by
`monitor.bus.scheme.build_routes`) and `monitor.bus.rigcodec.RigCodec` (a rig file) -- build
their routing from `Route` and expose it alike (`RouteSource`: ``routes``, and how a 29-bit
frame is refused, ``accepts_extended``), so the per-frame checks
(`monitor.bus.codec.check_payload`) and the column decoder (`monitor.columnar.decode`) read
the same objects: the cantools message with the E2E and SecOC properties the codec
attached, the node, the limits, the signals that are the model's inputs and outputs.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final, NamedTuple, Protocol, runtime_checkable

from cantools.database.can import Message

from monitor.bus.secoc import SecOCLayout, SyncLayout

__all__ = ["Limit", "Route", "RouteSource"]

_LARGEST: Final = sys.float_info.max  # a limit's infinite end, as a finite bound


class Limit(NamedTuple):
    """A signal's allowed range: [minimum, maximum] as the codec gives it (what a rejection
    says), and [low, high], the same range with an infinite end replaced by the largest
    finite float, so that ``low <= v <= high`` alone fails NaN and inf (one comparison per
    frame, or per column)."""

    signal: str
    low: float
    high: float
    minimum: float
    maximum: float

    @classmethod
    def of(cls, signal: str, minimum: float, maximum: float) -> Limit:
        """The limit [minimum, maximum] of `signal` (either end may be infinite)."""
        return cls(signal, max(minimum, -_LARGEST), min(maximum, _LARGEST), minimum, maximum)


@dataclass(frozen=True, slots=True)
class Route:
    """One arbitration ID of a bus, standard or extended, and how its frames are read.

    `kind` is `Decoded.kind` of its frames (our bus's kind, a rig message's name, "sync" for
    SecOC sync frames); `length` and `fd` the payload length and frame format the message
    has; `e2e` whether AUTOSAR E2E profile 2 protects it (the properties attached to
    `message`); `reserved_mask` the bits of ``int.from_bytes(payload, "little")`` that must
    be 0 (0: none checked); `limits` the signals checked against their range. What the
    estimator takes from a frame: `inputs` (model input index, signal, factor to the model's
    unit), `outputs` ((signal, factor), in output order), `truth` (a simulator's true gamma),
    `counter` (the alive counter's signal), `value` ((signal, factor) of `Decoded.value`;
    None: 0.0). `secoc` / `sync`: where a secured or sync frame carries freshness and MAC.
    """

    frame_id: int
    extended: bool
    message: Message
    node: int
    kind: str
    length: int
    fd: bool
    e2e: bool
    reserved_mask: int
    limits: tuple[Limit, ...]
    counter: str | None
    inputs: tuple[tuple[int, str, float], ...]
    outputs: tuple[tuple[str, float], ...]
    truth: str | None
    value: tuple[str, float] | None
    secoc: SecOCLayout | None = None
    sync: SyncLayout | None = None


@runtime_checkable
class RouteSource(Protocol):
    """What a codec states publicly about its routing (both codecs have it; a decoder
    without it, such as a wrapper of one, is read frame by frame only)."""

    @property
    def routes(self) -> Sequence[Route]:
        """Every route of the bus, in (frame ID, extended) order."""
        ...

    @property
    def accepts_extended(self) -> bool:
        """Whether 29-bit frames are routed by their ID (an ID the bus defines only with
        the other length is ``extended_id``, one it does not define ``unknown_id``);
        False: every 29-bit frame is ``extended_id``, before its ID is looked up."""
        ...

    @property
    def frame_by_frame(self) -> bool:
        """Whether frames must be decoded one at a time, in order (SecOC: a frame's verdict
        depends on its stream's freshness state)."""
        ...
