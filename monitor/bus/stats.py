"""Traffic statistics of the bus, the way an operator watches it: frames per second and
period jitter per arbitration ID, and the bus load (the share of time the frames take on the
wire, counted with the bits of each frame including stuffing at its worst: a classic frame
at the nominal bit rate, a CAN FD frame's data phase at the data bit rate when it switches).
Fed every received frame (a python-can `Listener`); read by the metrics sink."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import can

__all__ = ["BusStats", "IdStats", "fd_frame_bits", "frame_bits", "frame_time_s"]

FD_TRAILER_BITS = 12
"""ACK slot, ACK delimiter, end of frame (7) and intermission (3), at the nominal rate."""


def frame_bits(msg: can.Message) -> int:
    """Bits of a classic CAN data frame on the wire, worst-case stuffing (Davis et al. 2007:
    g + 8 s + 13 + floor((g + 8 s - 1) / 4), g = 34 standard, 54 extended)."""
    g = 54 if msg.is_extended_id else 34
    s = 0 if msg.is_remote_frame else min(len(msg.data), 8)
    return g + 8 * s + 13 + (g + 8 * s - 1) // 4


def fd_frame_bits(msg: can.Message) -> tuple[int, int]:
    """(bits at the nominal rate, bits in the data phase) of a CAN FD frame, worst-case
    stuffing (ISO 11898-1:2015).

    Arbitration phase, SOF to BRS: 17 bits standard, 36 extended. Data phase: ESI, DLC and
    the data (1 + 4 + 8 n), dynamically stuffed like everything before them (at most one
    stuff bit per 4 bits after the first, those of the arbitration bits counted there);
    the stuff count (4) and the CRC (17 bits up to 16 data bytes, else 21) with their fixed
    stuff bits (one before the stuff count, one after every fourth bit); the CRC
    delimiter, where the rate switches back. Then `FD_TRAILER_BITS` at the nominal rate.
    """
    n = len(msg.data)
    head = 36 if msg.is_extended_id else 17
    body = 1 + 4 + 8 * n
    crc = 17 if n <= 16 else 21
    head_stuff = (head - 1) // 4
    body_stuff = (head + body - 1) // 4 - head_stuff
    fixed = 1 + (4 + crc - 1) // 4
    return head + head_stuff + FD_TRAILER_BITS, body + body_stuff + 4 + crc + fixed + 1


def frame_time_s(msg: can.Message, nominal_bitrate: float,
                 data_bitrate: float | None = None) -> float:
    """Seconds `msg` takes on the wire (worst-case stuffing): a classic frame at the nominal
    rate; a CAN FD frame's data phase at `data_bitrate` if it switches rates (BRS) and one
    is given, else at the nominal rate too."""
    if not msg.is_fd:
        return frame_bits(msg) / nominal_bitrate
    nominal, data = fd_frame_bits(msg)
    fast = data_bitrate if data_bitrate and msg.bitrate_switch else nominal_bitrate
    return nominal / nominal_bitrate + data / fast


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
    """Counts every frame; `load` is the bus load over the last completed second (`bitrate`
    the nominal bit rate, `data_bitrate` a CAN FD bus's data-phase rate, None: the same)."""

    bitrate: float = 500_000.0
    data_bitrate: float | None = None
    ids: dict[tuple[int, bool], IdStats] = field(default_factory=dict)
    frames: int = 0
    error_frames: int = 0
    busy_s: float = 0.0  # time on the wire of every frame counted
    _window_busy_s: float = 0.0
    _window_start: float | None = None
    load: float = 0.0  # share of the time over the last completed second

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
        busy = frame_time_s(msg, self.bitrate, self.data_bitrate)
        self.busy_s += busy
        if self._window_start is None:
            self._window_start = t
        if t - self._window_start >= 1.0:
            self.load = self._window_busy_s / (t - self._window_start)
            self._window_busy_s = 0.0
            self._window_start = t
        self._window_busy_s += busy
