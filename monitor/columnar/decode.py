"""The rig's messages selected by ID and decoded for a whole chunk at once.

`RouteTable.of(codec)` reads the routes of the per-frame codec it stands beside
(`monitor.bus.route.RouteSource`: `monitor.bus.codec.MotorDatabase` for our bus,
`monitor.bus.rigcodec.RigCodec` for a rig file), so both paths route, check and scale from
the same `monitor.bus.route.Route` objects: the cantools messages with the E2E properties
the codec attached, the node of every ID, the limits, the reserved bits, the signals that
are the model's inputs and outputs. `RouteTable.decode(chunk)` then gives every frame the
verdict the codec's ``decode`` gives it, taking the checks in the one order
`monitor.bus.codec.CHECK_ORDER` declares (error, remote, extended ID as the codec's
``accepts_extended`` says, unknown ID, frame format, length, CRC, reserved bits, limits),
and, for the frames it accepts, the values the pipeline reads off `Decoded`: the model's
inputs (index, value in the model's unit), outputs, a simulator's truth, the alive
counter, as columns. SecOC cannot be columnar (every frame's verdict depends on the
freshness state of its stream): `RouteTable.of` refuses a codec whose ``frame_by_frame``
is set (`NotColumnar`), and the replay runs that file frame by frame. CAN FD messages of up
to 64 bytes are decoded in columns: each signal is read from the 8-byte window of the
payload that holds it (a signal wider than any such window, or E2E on a message over 8
bytes, sends the file frame by frame).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from monitor.bus.codec import CHECK_ORDER, RejectReason
from monitor.bus.route import Route, RouteSource
from monitor.columnar.chunk import FrameChunk
from monitor.columnar.e2e import profile2_ok
from monitor.columnar.signals import SignalExtractor, payload_integers

__all__ = ["REASONS", "DecodedChunk", "NotColumnar", "RouteTable"]

REASONS: tuple[str, ...] = ("", *(str(r) for r in RejectReason))
"""Verdict codes: 0 accepted, i > 0 rejected for REASONS[i]."""
_CODE = {r: i for i, r in enumerate(REASONS)}
OK = 0


class NotColumnar(Exception):
    """This codec or file needs the per-frame path (the message says why)."""


class _Signals:
    """The column extractors of one route's signals, each made when first read."""

    def __init__(self, route: Route) -> None:
        self.route = route
        self.extractors: dict[str, tuple[int, SignalExtractor]] = {}

    def extractor(self, name: str) -> tuple[int, SignalExtractor]:
        """(first byte of the 8-byte window that holds signal `name`, its extractor there)."""
        hit = self.extractors.get(name)
        if hit is None:
            r = self.route
            signal = r.message.get_signal_by_name(name)
            first = window_of(signal, r.length)
            if first is None:
                raise NotColumnar(f"{r.message.name}: {name} spans more than 8 bytes")
            if first:
                signal = copy.copy(signal)
                signal.start -= 8 * first  # byte-aligned shift: either byte order
            hit = (first, SignalExtractor(signal, min(r.length, 8)))
            self.extractors[name] = hit
        return hit


def window_of(signal: Any, length: int) -> int | None:
    """The first byte of an 8-byte window of a `length`-byte payload holding `signal`
    (0 for payloads of up to 8 bytes), None if no such window holds it."""
    if length <= 8:
        return 0
    n = int(signal.length)
    if signal.byte_order == "little_endian":
        lo, hi = signal.start // 8, (signal.start + n - 1) // 8
    else:  # Motorola: from the MSB's byte on, in big-endian bit order
        msb = 8 * (signal.start // 8) + 7 - signal.start % 8
        lo, hi = signal.start // 8, (msb + n - 1) // 8
    if hi - lo >= 8 or hi >= length:
        return None
    return min(lo, length - 8)


@dataclass
class DecodedChunk:
    """Verdicts of every frame of a chunk and, for accepted ones, their values.

    `code`: 0 accepted, else the index of the reject reason in `REASONS` (error frames have
    their own handling and get ``error_frame`` here). `route`: index into the table's
    routes (-1 for none). Per accepted frame (rows where code == 0; other rows hold
    garbage): `u` (n, m) with NaN where the frame does not carry that input, `y` (n, p),
    `truth`, `counter` (-1 without one).
    """

    code: NDArray[np.int64]
    route: NDArray[np.int64]
    u: NDArray[np.float64]
    y: NDArray[np.float64]
    truth: NDArray[np.float64]
    counter: NDArray[np.int64]


_FrameCheck = Callable[["RouteTable", FrameChunk, NDArray[np.int64], NDArray[np.int64]],
                       NDArray[np.bool_]]
_PayloadCheck = Callable[[Route, FrameChunk, NDArray[np.int64], "_Values"], NDArray[np.bool_]]


class RouteTable:
    """All routes of a codec, looked up by (ID, extended) for whole columns.

    `routes` are the codec's own; `route_stream[i]` the alive-counter stream (kind, node)
    of route i, an index into `streams`."""

    def __init__(self, routes: tuple[Route, ...], *, m: int, p: int,
                 accepts_extended: bool) -> None:
        self.routes = routes
        self.m = m
        self.p = p
        self.accepts_extended = accepts_extended
        keys = np.array([r.frame_id * 2 + int(r.extended) for r in routes], np.int64)
        order = np.argsort(keys)
        self._keys = keys[order]
        self._idx = order.astype(np.int64)
        self._signals = [_Signals(r) for r in routes]
        streams: dict[tuple[str, int], int] = {}
        self.route_stream = [streams.setdefault((r.kind, r.node), len(streams))
                             for r in routes]
        self.streams = list(streams)

    @classmethod
    def of(cls, codec: object, m: int, p: int) -> RouteTable:
        """The table of a codec's routes (`RouteSource`) for a model with m inputs and p
        outputs. `NotColumnar` for another decoder, SecOC, or messages whose signals no
        8-byte window holds."""
        if not isinstance(codec, RouteSource):
            raise NotColumnar(f"no columnar decoder for {type(codec).__name__}")
        if codec.frame_by_frame:
            raise NotColumnar("SecOC verification keeps per-frame freshness state")
        routes = tuple(codec.routes)
        for r in routes:
            if not 0 < r.length <= 64:
                raise NotColumnar(f"{r.message.name}: {r.length}-byte frames")
            if r.length > 8 and r.e2e:
                raise NotColumnar(f"{r.message.name}: E2E on {r.length}-byte CAN FD frames")
            if r.length > 8:
                used = [s for _, s, _ in r.inputs] + [s for s, _ in r.outputs] + \
                    [lim.signal for lim in r.limits]
                used += [x for x in (r.truth, r.counter) if x is not None]
                for name in dict.fromkeys(used):
                    if window_of(r.message.get_signal_by_name(name), r.length) is None:
                        raise NotColumnar(f"{r.message.name}: {name} spans more than 8 bytes")
            if any(i >= m for i, _, _ in r.inputs) or len(r.outputs) > p:
                raise NotColumnar(f"{r.message.name}: more signals than the model has")
        return cls(routes, m=m, p=p, accepts_extended=bool(codec.accepts_extended))

    def _lookup(self, key: NDArray[np.int64]) -> NDArray[np.int64]:
        if not len(self._keys):
            return np.full(key.shape, -1, np.int64)
        pos = np.searchsorted(self._keys, key)
        pos = np.minimum(pos, len(self._keys) - 1)
        hit = self._keys[pos] == key
        return np.where(hit, self._idx[pos], -1)

    # the checks of CHECK_ORDER: which frames fail each (of those still in play)

    def _extended(self, c: FrameChunk, rows: NDArray[np.int64],
                  route: NDArray[np.int64]) -> NDArray[np.bool_]:
        ext = c.extended[rows]
        if not self.accepts_extended:
            return ext
        other = self._lookup(c.arbitration_id[rows] * 2 + (~ext).astype(np.int64))
        return (route[rows] < 0) & (other >= 0)

    def decode(self, c: FrameChunk) -> DecodedChunk:
        """Every frame's verdict and values (see `DecodedChunk`)."""
        n = len(c)
        code = np.zeros(n, np.int64)
        route = self._lookup(c.arbitration_id * 2 + c.extended.astype(np.int64))
        rows = np.arange(n, dtype=np.int64)
        for reason in CHECK_ORDER:  # the frame's flags and ID, for every frame at once
            check = _FRAME.get(reason)
            if check is not None:
                bad = check(self, c, rows, route)
                code[rows[bad]] = _CODE[reason]
                route[rows[bad]] = -1
                rows = rows[~bad]
        u = np.full((n, self.m), np.nan)
        y = np.full((n, self.p), np.nan)
        truth = np.full(n, np.nan)
        counter = np.full(n, -1, np.int64)
        present = np.unique(route[route >= 0])
        for ri in present.tolist():
            r = self.routes[ri]
            rows = np.flatnonzero(route == ri)
            vals = _Values(self._signals[ri], c.data[rows, :max(8, r.length)])
            for reason in CHECK_ORDER:  # the payload, route by route
                check_payload = _PAYLOAD.get(reason)
                if check_payload is None or not len(rows):
                    continue
                bad = check_payload(r, c, rows, vals)
                if bad.any():
                    code[rows[bad]] = _CODE[reason]
                    keep = ~bad
                    rows, vals = rows[keep], vals.subset(keep)
            if not len(rows):
                continue
            for i, name, f in r.inputs:
                u[rows, i] = vals.get(name) * f
            for j, (name, f) in enumerate(r.outputs):
                y[rows, j] = vals.get(name) * f
            if r.truth is not None:
                truth[rows] = vals.get(r.truth)
            if r.counter is not None:
                cv = np.trunc(vals.get(r.counter))
                if ((cv < 0) | (cv > 15)).any():
                    bad_c = cv[(cv < 0) | (cv > 15)][0]
                    raise ValueError(f"alive counter must be an int in 0..15, got {int(bad_c)}")
                counter[rows] = cv.astype(np.int64)
        return DecodedChunk(code, route, u, y, truth, counter)


_FRAME: dict[RejectReason, _FrameCheck] = {
    RejectReason.ERROR_FRAME: lambda t, c, rows, route: c.error[rows],
    RejectReason.REMOTE_FRAME: lambda t, c, rows, route: c.remote[rows],
    RejectReason.EXTENDED_ID: lambda t, c, rows, route: t._extended(c, rows, route),
    RejectReason.UNKNOWN_ID: lambda t, c, rows, route: route[rows] < 0,
}
"""The checks of `CHECK_ORDER` on a frame's flags and ID (`rows`: the frames still in play;
`route`: each frame's route by its ID and length, -1 for none)."""


def _crc_fails(r: Route, c: FrameChunk, rows: NDArray[np.int64], vals: _Values
               ) -> NDArray[np.bool_]:
    if not r.e2e:
        return np.zeros(len(rows), np.bool_)
    return ~profile2_ok(r.message, vals.data[:, :8], r.length)


def _reserved_set(r: Route, c: FrameChunk, rows: NDArray[np.int64], vals: _Values
                  ) -> NDArray[np.bool_]:
    if not r.reserved_mask:
        return np.zeros(len(rows), np.bool_)
    mask = np.uint64(r.reserved_mask & 0xFFFFFFFFFFFFFFFF)
    return (vals.window(0)[0] & mask) != 0


def _outside_limits(r: Route, c: FrameChunk, rows: NDArray[np.int64], vals: _Values
                    ) -> NDArray[np.bool_]:
    inside = np.ones(len(rows), np.bool_)
    for lim in r.limits:
        v = vals.get(lim.signal)
        inside &= (lim.low <= v) & (v <= lim.high)  # finite bounds: NaN and inf fail
    return ~inside


_PAYLOAD: dict[RejectReason, _PayloadCheck] = {
    RejectReason.FD_FRAME: lambda r, c, rows, vals: c.is_fd[rows] != r.fd,
    RejectReason.WRONG_LENGTH: lambda r, c, rows, vals: c.length[rows] != r.length,
    RejectReason.BAD_CRC: _crc_fails,
    RejectReason.MALFORMED: _reserved_set,  # reserved bits set
    RejectReason.OUT_OF_RANGE: _outside_limits,
}
"""The payload checks of `CHECK_ORDER` on columns (SecOC's never run: `RouteTable.of`)."""


class _Values:
    """Signals of one route's payloads (rows of `data`, at least 8 bytes wide), each
    extracted once, from the 8-byte window that holds it."""

    def __init__(self, signals: _Signals, data: NDArray[np.uint8]) -> None:
        self.signals = signals
        self.data = data
        self.windows: dict[int, tuple[NDArray[np.uint64], NDArray[np.uint64]]] = {}
        self.cache: dict[str, NDArray[np.float64]] = {}

    def window(self, first: int) -> tuple[NDArray[np.uint64], NDArray[np.uint64]]:
        """(little-endian, big-endian) integers of bytes first..first+7 of every payload."""
        w = self.windows.get(first)
        if w is None:
            w = payload_integers(self.data[:, first:first + 8])
            self.windows[first] = w
        return w

    def get(self, name: str) -> NDArray[np.float64]:
        v = self.cache.get(name)
        if v is None:
            first, ex = self.signals.extractor(name)
            v = ex.extract(*self.window(first))
            self.cache[name] = v
        return v

    def subset(self, keep: NDArray[np.bool_]) -> _Values:
        out = _Values(self.signals, self.data[keep])
        out.windows = {k: (le[keep], be[keep]) for k, (le, be) in self.windows.items()}
        out.cache = {k: v[keep] for k, v in self.cache.items()}
        return out
