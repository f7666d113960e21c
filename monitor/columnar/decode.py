"""The rig's messages selected by ID and decoded for a whole chunk at once.

`RouteTable.of(codec)` reads the routing table of the per-frame codec it stands beside --
`monitor.bus.codec.MotorDatabase` (our bus) or `monitor.bus.rigcodec.RigCodec` (a rig file)
-- so both paths route, check and scale from the same objects: the cantools messages with
the E2E properties the codec attached, the node of every ID, the signals' [min, max] limits
the codec checks, the reserved bits of our bus. `RouteTable.decode(chunk)` then gives every
frame the verdict the codec's ``decode`` gives it, in the codec's order of checks:

* our bus: error, remote, extended, unknown ID, a CAN FD frame (``fd_frame``), length !=
  8, CRC, reserved bits set (``malformed``), limits (``out_of_range``);
* a rig: error, remote, ID of the other length (``extended_id``) or unknown, frame format
  not the message's (``fd_frame``), length != the message's, CRC (E2E messages), limits.

and, for the frames it accepts, the values the pipeline reads off `Decoded`: the model's
inputs (index, value in the model's unit), outputs, a simulator's truth, the alive
counter, as columns. SecOC cannot be columnar (every frame's verdict depends on the
freshness state of its stream): `RouteTable.of` refuses a codec with a key
(`NotColumnar`), and the replay runs that file frame by frame. CAN FD messages of up to
64 bytes are decoded in columns: each signal is read from the 8-byte window of the payload
that holds it (a signal wider than any such window, or E2E on a message over 8 bytes, sends
the file frame by frame); FD frames on a rig's classic messages, or on our bus, get their
``fd_frame`` verdict here.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from cantools.database.can import Message
from numpy.typing import NDArray

from monitor.bus.codec import MotorDatabase, RejectReason
from monitor.bus.rigcodec import RigCodec
from monitor.columnar.chunk import FrameChunk
from monitor.columnar.e2e import profile2_ok
from monitor.columnar.signals import SignalExtractor, payload_integers

__all__ = ["REASONS", "DecodedChunk", "NotColumnar", "Route", "RouteTable"]

REASONS: tuple[str, ...] = ("", *(str(r) for r in RejectReason))
"""Verdict codes: 0 accepted, i > 0 rejected for REASONS[i]."""
_CODE = {r: i for i, r in enumerate(REASONS)}
OK = 0


class NotColumnar(Exception):
    """This codec or file needs the per-frame path (the message says why)."""


@dataclass
class Route:
    """One arbitration ID of the bus (standard or extended) as the codec routes it."""

    frame_id: int
    extended: bool
    message: Message
    node: int
    kind: str  # Decoded.kind: our bus's kind, or the rig message's name
    length: int
    e2e: bool
    reserved_mask: int
    limits: tuple[tuple[str, float, float], ...]
    counter: str | None
    inputs: tuple[tuple[int, str, float], ...]  # (input index, signal, factor)
    outputs: tuple[tuple[str, float], ...]  # (signal, factor)
    truth: str | None
    fd: bool = False  # a CAN FD message in the DBC
    stream: int = 0  # alive-counter stream (kind, node)
    extractors: dict[str, tuple[int, SignalExtractor]] = field(default_factory=dict)

    def extractor(self, name: str) -> tuple[int, SignalExtractor]:
        """(first byte of the 8-byte window that holds signal `name`, its extractor there)."""
        hit = self.extractors.get(name)
        if hit is None:
            signal = self.message.get_signal_by_name(name)
            first = window_of(signal, self.length)
            if first is None:
                raise NotColumnar(f"{self.message.name}: {name} spans more than 8 bytes")
            if first:
                signal = copy.copy(signal)
                signal.start -= 8 * first  # byte-aligned shift: either byte order
            hit = (first, SignalExtractor(signal, min(self.length, 8)))
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


class RouteTable:
    """All routes of a codec, looked up by (ID, extended) for whole columns."""

    def __init__(self, routes: list[Route], *, m: int, p: int, our_bus: bool) -> None:
        self.routes = routes
        self.m = m
        self.p = p
        self.our_bus = our_bus
        keys = np.array([r.frame_id * 2 + int(r.extended) for r in routes], np.int64)
        order = np.argsort(keys)
        self._keys = keys[order]
        self._idx = order.astype(np.int64)
        streams: dict[tuple[str, int], int] = {}
        for r in routes:
            r.stream = streams.setdefault((r.kind, r.node), len(streams))
        self.streams = list(streams)

    @classmethod
    def of(cls, codec: Any, m: int, p: int) -> RouteTable:
        """The table of a `MotorDatabase` or `RigCodec` for a model with m inputs and p
        outputs. `NotColumnar` for SecOC, other codecs, or messages over 8 bytes."""
        if getattr(codec, "secoc_enabled", False) or getattr(codec, "secured", False):
            # (a rig's sync frames, even unverified, are counted as the per-frame path does)
            raise NotColumnar("SecOC verification keeps per-frame freshness state")
        routes: list[Route] = []
        if isinstance(codec, MotorDatabase):
            for fid, mr in codec.routes.items():
                kind = str(mr.kind)
                routes.append(Route(
                    fid, False, mr.message, mr.node, kind, 8, mr.data_id is not None,
                    mr.reserved_mask, tuple(mr.limits),
                    "Counter" if mr.data_id is not None else None,
                    ((0, mr.value_signal, 1.0),) if kind == "voltage" else (),
                    ((mr.value_signal, 1.0),) if kind == "current" else (),
                    mr.value_signal if kind == "truth" else None))
            our = True
        elif isinstance(codec, RigCodec):
            for (fid, ext), rr in codec.routes.items():
                spec = rr.spec
                routes.append(Route(
                    fid, ext, rr.message, rr.node, spec.name, int(rr.message.length), spec.e2e,
                    0, tuple(rr.limits), spec.counter, tuple(spec.inputs),
                    tuple(spec.outputs), spec.truth, bool(rr.message.is_fd)))
            our = False
        else:
            raise NotColumnar(f"no columnar decoder for {type(codec).__name__}")
        for r in routes:
            if not 0 < r.length <= 64:
                raise NotColumnar(f"{r.message.name}: {r.length}-byte frames")
            if r.length > 8 and r.e2e:
                raise NotColumnar(f"{r.message.name}: E2E on {r.length}-byte CAN FD frames")
            if r.length > 8:
                used = [s for _, s, _ in r.inputs] + [s for s, _ in r.outputs] + \
                    [name for name, _, _ in r.limits]
                used += [x for x in (r.truth, r.counter) if x is not None]
                for name in dict.fromkeys(used):
                    if window_of(r.message.get_signal_by_name(name), r.length) is None:
                        raise NotColumnar(f"{r.message.name}: {name} spans more than 8 bytes")
            if any(i >= m for i, _, _ in r.inputs) or len(r.outputs) > p:
                raise NotColumnar(f"{r.message.name}: more signals than the model has")
        return cls(routes, m=m, p=p, our_bus=our)

    def _lookup(self, key: NDArray[np.int64]) -> NDArray[np.int64]:
        if not len(self._keys):
            return np.full(key.shape, -1, np.int64)
        pos = np.searchsorted(self._keys, key)
        pos = np.minimum(pos, len(self._keys) - 1)
        hit = self._keys[pos] == key
        return np.where(hit, self._idx[pos], -1)

    def decode(self, c: FrameChunk) -> DecodedChunk:
        """Every frame's verdict and values (see `DecodedChunk`)."""
        n = len(c)
        code = np.zeros(n, np.int64)
        ids = c.arbitration_id
        ext = c.extended
        route = self._lookup(ids * 2 + ext.astype(np.int64))
        if self.our_bus:
            # extended IDs are refused before the lookup
            route = np.where(ext, -1, route)
            code[route < 0] = _CODE[RejectReason.UNKNOWN_ID]
            code[ext] = _CODE[RejectReason.EXTENDED_ID]
        else:
            other = self._lookup(ids * 2 + (~ext).astype(np.int64))
            code[route < 0] = np.where(other[route < 0] >= 0, _CODE[RejectReason.EXTENDED_ID],
                                       _CODE[RejectReason.UNKNOWN_ID])
        code[c.remote] = _CODE[RejectReason.REMOTE_FRAME]
        route[c.remote] = -1
        code[c.error] = _CODE[RejectReason.ERROR_FRAME]
        route[c.error] = -1
        u = np.full((n, self.m), np.nan)
        y = np.full((n, self.p), np.nan)
        truth = np.full(n, np.nan)
        counter = np.full(n, -1, np.int64)
        present = np.unique(route[route >= 0])
        for ri in present.tolist():
            r = self.routes[ri]
            rows = np.flatnonzero(route == ri)
            bad = c.is_fd[rows] != r.fd
            code[rows[bad]] = _CODE[RejectReason.FD_FRAME]
            rows = rows[~bad]
            bad = c.length[rows] != r.length
            code[rows[bad]] = _CODE[RejectReason.WRONG_LENGTH]
            rows = rows[~bad]
            if not len(rows):
                continue
            data = c.data[rows, :max(8, r.length)]
            if r.e2e:
                ok = profile2_ok(r.message, data[:, :8], r.length)
                code[rows[~ok]] = _CODE[RejectReason.BAD_CRC]
                rows, data = rows[ok], data[ok]
            vals = _Values(r, data)
            if r.reserved_mask:
                mask = np.uint64(r.reserved_mask & 0xFFFFFFFFFFFFFFFF)
                bad = (vals.window(0)[0] & mask) != 0
                code[rows[bad]] = _CODE[RejectReason.MALFORMED]
                keep = ~bad
                rows, vals = rows[keep], vals.subset(keep)
            if not len(rows):
                continue
            inside = np.ones(len(rows), np.bool_)
            for name, lo, hi in r.limits:
                v = vals.get(name)
                inside &= (lo <= v) & (v <= hi) & np.isfinite(v)  # as in the codec
            code[rows[~inside]] = _CODE[RejectReason.OUT_OF_RANGE]
            rows = rows[inside]
            if not len(rows):
                continue
            vals = vals.subset(inside)
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


class _Values:
    """Signals of one route's payloads (rows of `data`, at least 8 bytes wide), each
    extracted once, from the 8-byte window that holds it."""

    def __init__(self, route: Route, data: NDArray[np.uint8]) -> None:
        self.route = route
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
            first, ex = self.route.extractor(name)
            v = ex.extract(*self.window(first))
            self.cache[name] = v
        return v

    def subset(self, keep: NDArray[np.bool_]) -> _Values:
        out = _Values(self.route, self.data[keep])
        out.windows = {k: (le[keep], be[keep]) for k, (le, be) in self.windows.items()}
        out.cache = {k: v[keep] for k, v in self.cache.items()}
        return out
