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
(`NotColumnar`), and the replay runs that file frame by frame. So does a rig with CAN FD
messages longer than 8 bytes (the columns decode payloads of up to 8 bytes); FD frames on
a rig's classic messages, or on our bus, get their ``fd_frame`` verdict here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from cantools.database.can import Message
from numpy.typing import NDArray

from monitor.bus.codec import MotorDatabase, RejectReason
from monitor.bus.rigcodec import RigCodec
from monitor.columnar.e2e import profile2_ok
from monitor.columnar.reader import FrameChunk
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
    extractors: dict[str, SignalExtractor] = field(default_factory=dict)

    def extractor(self, name: str) -> SignalExtractor:
        ex = self.extractors.get(name)
        if ex is None:
            ex = SignalExtractor(self.message.get_signal_by_name(name), self.length)
            self.extractors[name] = ex
        return ex


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
        if getattr(codec, "secoc_enabled", False):
            raise NotColumnar("SecOC verification keeps per-frame freshness state")
        routes: list[Route] = []
        if isinstance(codec, MotorDatabase):
            for fid, mr in codec._routes.items():
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
            for (fid, ext), rr in codec._routes.items():
                spec = rr.spec
                routes.append(Route(
                    fid, ext, rr.message, rr.node, spec.name, int(rr.message.length), spec.e2e,
                    0, tuple(rr.limits), spec.counter, tuple(spec.inputs),
                    tuple(spec.outputs), spec.truth, bool(rr.message.is_fd)))
            our = False
        else:
            raise NotColumnar(f"no columnar decoder for {type(codec).__name__}")
        for r in routes:
            if not 0 < r.length <= 8:
                fd = "CAN FD " if r.fd else ""
                raise NotColumnar(f"{r.message.name}: {r.length}-byte {fd}frames (the "
                                  "columns decode up to 8 bytes)")
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
            data = c.data[rows, :8]
            if r.e2e:
                ok = profile2_ok(r.message, data, r.length)
                code[rows[~ok]] = _CODE[RejectReason.BAD_CRC]
                rows, data = rows[ok], data[ok]
            le, be = payload_integers(data)
            if r.reserved_mask:
                mask = np.uint64(r.reserved_mask & 0xFFFFFFFFFFFFFFFF)
                bad = (le & mask) != 0
                code[rows[bad]] = _CODE[RejectReason.MALFORMED]
                keep = ~bad
                rows, le, be = rows[keep], le[keep], be[keep]
            if not len(rows):
                continue
            vals = _Values(r, le, be)
            inside = np.ones(len(rows), np.bool_)
            for name, lo, hi in r.limits:
                v = vals.get(name)
                inside &= (lo <= v) & (v <= hi)  # NaN fails, as in the codec
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
    """Signals of one route's payloads, each extracted once."""

    def __init__(self, route: Route, le: NDArray[np.uint64], be: NDArray[np.uint64]) -> None:
        self.route = route
        self.le = le
        self.be = be
        self.cache: dict[str, NDArray[np.float64]] = {}

    def get(self, name: str) -> NDArray[np.float64]:
        v = self.cache.get(name)
        if v is None:
            v = self.route.extractor(name).extract(self.le, self.be)
            self.cache[name] = v
        return v

    def subset(self, keep: NDArray[np.bool_]) -> _Values:
        out = _Values(self.route, self.le[keep], self.be[keep])
        out.cache = {k: v[keep] for k, v in self.cache.items()}
        return out
