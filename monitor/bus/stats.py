"""Traffic statistics of the bus, the way an operator watches it: frames per second and
period jitter per arbitration ID, and the bus load (the share of the bit rate the frames
take, counted with the bits of a classic CAN frame including stuffing at its worst).
Fed every received frame (a python-can `Listener`); read by the metrics sink."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import can

__all__ = ["BusStats", "IdStats", "frame_bits"]


def frame_bits(msg: can.Message) -> int:
    """Bits of a classic CAN data frame on the wire, worst-case stuffing (Davis et al. 2007:
    g + 8 s + 13 + floor((g + 8 s - 1) / 4), g = 34 standard, 54 extended)."""
    g = 54 if msg.is_extended_id else 34
    s = 0 if msg.is_remote_frame else min(len(msg.data), 8)
    return g + 8 * s + 13 + (g + 8 * s - 1) // 4


@dataclass
class IdStats:
    """One arbitration ID: frames, and the spacing of their timestamps (Welford)."""

    frames: int = 0
    last_t: float | None = None
    n: int = 0
    mean: float = 0.0
    m2: float = 0.0

    def add(self, t: float) -> None:
        self.frames += 1
        if self.last_t is not None and t > self.last_t:
            d = t - self.last_t
            self.n += 1
            delta = d - self.mean
            self.mean += delta / self.n
            self.m2 += delta * (d - self.mean)
        self.last_t = t

    @property
    def period_s(self) -> float:
        return self.mean if self.n else math.nan

    @property
    def jitter_s(self) -> float:
        """Standard deviation of the spacing of consecutive frames."""
        return math.sqrt(self.m2 / (self.n - 1)) if self.n > 1 else math.nan


@dataclass
class BusStats(can.Listener):
    """Counts every frame; `load(window)` is the bus load over the last window."""

    bitrate: float = 500_000.0
    ids: dict[tuple[int, bool], IdStats] = field(default_factory=dict)
    frames: int = 0
    error_frames: int = 0
    bits: int = 0
    _window_bits: int = 0
    _window_start: float | None = None
    load: float = 0.0  # share of the bit rate over the last completed second

    def on_message_received(self, msg: can.Message) -> None:
        self.frames += 1
        t = float(msg.timestamp)
        if msg.is_error_frame:
            self.error_frames += 1
            return
        key = (msg.arbitration_id, msg.is_extended_id)
        st = self.ids.get(key)
        if st is None:
            st = self.ids[key] = IdStats()
        st.add(t)
        b = frame_bits(msg)
        self.bits += b
        if self._window_start is None:
            self._window_start = t
        if t - self._window_start >= 1.0:
            self.load = self._window_bits / ((t - self._window_start) * self.bitrate)
            self._window_bits = 0
            self._window_start = t
        self._window_bits += b
