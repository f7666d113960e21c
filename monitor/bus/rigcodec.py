"""Frames of a user's own bus, described by a rig file, as typed samples (and back).

`RigCodec` reads any DBC through cantools (float and big-endian signals, standard or 29-bit
IDs, as the DBC defines them) and routes each frame to a node by the rig's layout:
``<message>_N<node>`` names, a node number in bits of the arbitration ID (the DBC lists
node 0's messages), or an explicit table per node. Each rig message has its protection:
none, or AUTOSAR E2E profile 2 checked by `cantools.autosar.end_to_end` (CRC in byte 0,
alive counter in the low nibble of byte 1, a data ID per message), each with or without
SecOC (below). CAN FD messages (the
DBC's ``VFrameFormat`` StandardCAN_FD / ExtendedCAN_FD, up to 64 bytes) are decoded like
classic ones; a frame whose format is not the message's (FD for a classic message, or
the reverse) is ``fd_frame``, before its length is looked at. Decoding never raises:
every frame is `Decoded` (the model's inputs and outputs converted to the model's units)
or `Rejected` with a reason from `RejectReason`, like `monitor.bus.codec.MotorDatabase`
for our own bus, whose checks of a routed frame (`monitor.bus.codec.check_payload`, no
reserved bits here) it runs in the same order.

SecOC (`monitor.bus.secoc`, as on our own bus): a secured message carries a truncated
freshness value and a truncated AES-CMAC in signals the rig names (`RigSecOC`); its SecOC
data ID is its arbitration ID's low 16 bits (so each node's stream has its own), and with
E2E the CRC byte is written after the MAC and left out of it. One sync message per node
(`RigSync`: SyncKind, SyncFreshness, SyncAuthenticator in signals the rig names) carries
the full freshness of each stream, SyncKind telling which. With a key (`secoc_key`) the
codec signs what it encodes and rejects, inside `decode`, what does not verify
(``bad_mac``, ``stale_freshness``, ``unsynced``); without one, secured frames decode
unverified and sync frames are plain ``sync`` samples, as on our bus.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Final, NamedTuple

import cantools.database
import numpy as np
from cantools.autosar.end_to_end import apply_profile2_crc
from cantools.database.can import Database, Message, Signal
from cantools.database.can.formats.arxml import AutosarEnd2EndProperties, AutosarMessageSpecifics
from numpy.typing import NDArray

from monitor.bus.codec import (
    VERDICT_REASON,
    Decoded,
    PayloadCheck,
    Rejected,
    RejectReason,
    load_dbcs,
    screen_frame,
)
from monitor.bus.errors import CodecError, SecOCError
from monitor.bus.route import Limit, Route
from monitor.bus.secoc import DEFAULT_WINDOW, SecOC, SecOCHolder, SecOCLayout, SyncLayout
from monitor.errors import one_line

if TYPE_CHECKING:
    import can

    from monitor.bus.canopen import CanopenNode
    from monitor.bus.route import RouteSource

__all__ = ["Quantisation", "Resolver", "RigCodec", "RigMessage", "RigSecOC", "RigSync",
           "load_rig_dbcs", "output_quantisation"]


@dataclass(frozen=True)
class RigSecOC:
    """A message's SecOC: its freshness and MAC signals, the full freshness length (bits),
    the SyncKind value of its stream and the stream's name in the freshness counters (a
    lower-case word: ``rx/<stream>/<node>`` in a state file)."""

    freshness: str
    authenticator: str
    freshness_length: int
    sync_kind: int
    stream: str


@dataclass(frozen=True)
class RigSync:
    """The rig's SecOC sync message (as the rig names it) and its signals."""

    message: str
    kind: str
    freshness: str
    authenticator: str
    freshness_length: int


@dataclass(frozen=True)
class RigMessage:
    """How the codec reads one rig message: which signals are which model input/output,
    their unit factors, and the protection."""

    name: str  # as the rig names it
    inputs: tuple[tuple[int, str, float], ...] = ()  # (input index, signal, unit factor)
    outputs: tuple[tuple[str, float], ...] = ()  # (signal, unit factor), in output order
    truth: str | None = None
    e2e: bool = False
    counter: str | None = None
    crc: str | None = None
    data_id: int | None = None  # None: frame_id & 0xFF
    secoc: RigSecOC | None = None


Resolver = Callable[[str, int], "tuple[Message, int] | None"]
"""(rig message, node) -> (the node's DBC message, its arbitration ID), None if absent. With
a node number in the ID bits every node shares node 0's DBC message: the resolver hands out
a copy per node, so that each carries its own E2E data ID."""


def load_rig_dbcs(paths: Sequence[Path]) -> Database:
    """`load_dbcs`, and at least one message in them."""
    db = load_dbcs(paths)
    if not db.messages:
        raise CodecError(f"{', '.join(map(str, paths))}: no messages")
    return db


class RigCodec(SecOCHolder):
    """Routes and decodes the frames of a rig's bus.

    `messages` says how to read each rig message; `resolve(name, node)` gives the DBC
    message of a rig message for a node and the frame's arbitration ID (None if the node
    has no such message); `nodes` are the nodes to route; `sync` is the SecOC sync message
    (needed when a message has SecOC), `secoc_key` the key that signs and verifies. Built
    and checked by `monitor.rig.check`.
    """

    accepts_extended: Final = True
    """29-bit frames are routed by their ID (`monitor.bus.route.RouteSource`)."""

    def __init__(self, db: Database, source: str, messages: Sequence[RigMessage],
                 resolve: Resolver, nodes: Sequence[int], *, sync: RigSync | None = None,
                 secoc_key: bytes | None = None, secoc_window: int = DEFAULT_WINDOW) -> None:
        self._db = db
        self.source = source
        self.specs: dict[str, RigMessage] = {m.name: m for m in messages}
        self.sync = sync
        self.drives: tuple[CanopenNode, ...] = ()
        """A CANopen rig's drives, whose EMCY, heartbeat and statusword frames the engines
        read beside the rig's messages (`monitor.bus.cia402.drive_watch`)."""
        self._by_key: dict[tuple[int, bool], Route] = {}
        self._by_name: dict[tuple[str, int], Route] = {}
        self._sync_streams = {m.secoc.sync_kind: m.secoc.stream
                              for m in messages if m.secoc is not None}
        if self._sync_streams and sync is None:
            raise CodecError(f"{source}: SecOC needs a sync message")
        data_ids: dict[int, str] = {}
        names: dict[tuple[int, bool], str] = {}  # each ID's rig message, for a clash
        sync_spec = None if sync is None else RigMessage(sync.message)
        for spec in (*messages, *(() if sync_spec is None else (sync_spec,))):
            for node in nodes:
                found = resolve(spec.name, node)
                if found is None:
                    continue
                message, frame_id = found
                is_sync = spec is sync_spec
                route = self._secured(
                    _route(message, frame_id, spec, node, sync if is_sync else None), spec,
                    is_sync)
                key = (frame_id, message.is_extended_frame)
                other = self._by_key.get(key)
                if other is not None:
                    raise CodecError(f"{source}: {spec.name} of node {node} and "
                                     f"{names[key]} of node {other.node} share ID "
                                     f"0x{frame_id:X}")
                self._by_key[key] = route
                names[key] = spec.name
                self._by_name[(spec.name, node)] = route
                if spec.e2e:
                    _attach_e2e(message, frame_id if spec.data_id is None else spec.data_id)
                if route.secoc is not None:
                    _attach_secoc(message, route.secoc)
                layout = route.secoc or route.sync
                if layout is not None:
                    if layout.data_id in data_ids:
                        raise CodecError(f"{source}: {message.name} of node {node} and "
                                         f"{data_ids[layout.data_id]} have the same SecOC data "
                                         f"ID 0x{layout.data_id:04X} (the ID's low 16 bits)")
                    data_ids[layout.data_id] = f"{message.name} of node {node}"
        self._secoc = None
        if secoc_key is not None:
            if not self._sync_streams:
                raise CodecError(f"{source}: a SecOC key, but no rig message has SecOC")
            self._secoc = SecOC(secoc_key, window=secoc_window)
        self._routes = tuple(self._by_key[k] for k in sorted(self._by_key))
        secured = self._secoc is not None
        self._checks: dict[tuple[int, bool], tuple[PayloadCheck, Route]] = {
            (r.frame_id, r.extended): (PayloadCheck.of(
                r, partial(self._verify, r) if secured and (r.secoc or r.sync) else None), r)
            for r in self._routes}

    def _secured(self, route: Route, spec: RigMessage, is_sync: bool) -> Route:
        """`route` with its SecOC or sync layout (data ID: the frame ID's low 16 bits)."""
        msg, sec, data_id = route.message, spec.secoc, route.frame_id & 0xFFFF
        try:
            if is_sync:
                assert self.sync is not None
                s = self.sync
                kind, fv, auth = (msg.get_signal_by_name(n)
                                  for n in (s.kind, s.freshness, s.authenticator))
                return replace(route, sync=SyncLayout.from_signals(
                    msg, kind, fv, auth, data_id=data_id, freshness_bits=s.freshness_length))
            if sec is None:
                return route
            fv, auth = (msg.get_signal_by_name(n) for n in (sec.freshness, sec.authenticator))
            layout = SecOCLayout.from_signals(msg, fv, auth, data_id=data_id,
                                              freshness_bits=sec.freshness_length,
                                              crc_byte=spec.e2e)
            return replace(route, secoc=layout)
        except KeyError as exc:
            raise CodecError(f"{msg.name}: no signal {exc.args[0]} for SecOC") from None
        except SecOCError as exc:
            raise CodecError(str(exc)) from None

    @property
    def routes(self) -> tuple[Route, ...]:
        """Every (arbitration ID, extended) of the rig and how it is read, in that order
        (`monitor.bus.route.RouteSource`)."""
        return self._routes

    @property
    def secured(self) -> bool:
        """Whether any rig message has SecOC (verified only with a key)."""
        return bool(self._sync_streams)

    @property
    def frame_by_frame(self) -> bool:
        """Whether frames must be decoded one at a time, in order: with a key a frame's
        verdict depends on its stream's freshness state (`monitor.bus.route.RouteSource`)."""
        return self._secoc is not None

    @property
    def nodes(self) -> tuple[int, ...]:
        return tuple(sorted({n for _, n in self._by_name}))

    def frame_id(self, name: str, node: int) -> int:
        """The arbitration ID of rig message `name` of `node`."""
        return self._lookup(name, node).frame_id

    def message(self, name: str, node: int) -> Message:
        return self._lookup(name, node).message

    def sync_message(self, node: int) -> Message:
        """`node`'s SecOC sync message (`CodecError` if the rig has none)."""
        if self.sync is None:
            raise CodecError("this rig has no SecOC sync message")
        return self.message(self.sync.message, node)

    def _lookup(self, name: str, node: int) -> Route:
        hit = self._by_name.get((name, node))
        if hit is None:
            raise CodecError(f"no message {name} for node {node} on this rig")
        return hit

    # -- encoding (the rig's virtual ECU) ---------------------------------------------

    def encode(self, name: str, node: int, values: Mapping[str, float],
               counter: int | None = None) -> tuple[int, bool, bytes]:
        """(arbitration ID, extended?, payload) of rig message `name` for `node` carrying
        `values` (DBC signal name -> physical value in the DBC's unit); signals not given
        are sent at 0 (or the nearest value their range allows); with E2E, `counter`
        (0..15) and the CRC are applied."""
        route = self._lookup(name, node)
        msg, frame_id = route.message, route.frame_id
        spec = self.specs[name] if name in self.specs else RigMessage(name)  # the sync message
        signals: dict[str, float] = {}
        for s in msg.signals:
            lo = s.minimum if s.minimum is not None else -math.inf
            hi = s.maximum if s.maximum is not None else math.inf
            signals[s.name] = min(max(0.0, lo), hi)
        for k, v in values.items():
            if not math.isfinite(v):
                raise CodecError(f"{msg.name}: {k} must be a finite number, got {v!r}")
            signals[k] = v
        if spec.e2e:
            if counter is None or not 0 <= counter <= 15:
                raise CodecError(f"{msg.name}: counter must be an int in 0..15, got {counter!r}")
            assert spec.counter is not None and spec.crc is not None
            signals[spec.counter] = counter
            signals[spec.crc] = 0
        try:
            payload = msg.encode(signals, scaling=True, padding=False, strict=True)
        except (cantools.database.EncodeError, ValueError, OverflowError) as exc:
            raise CodecError(f"{msg.name}: {one_line(exc)}") from None
        if route.secoc is not None and self._secoc is not None:
            assert spec.secoc is not None
            payload = self._secoc.sign(route.secoc, (spec.secoc.stream, node), payload)
        if spec.e2e:
            protected = apply_profile2_crc(payload, msg)
            if protected is None:
                raise CodecError(f"{msg.name}: cantools did not apply the E2E profile 2 CRC")
            payload = bytes(protected)
        return frame_id, msg.is_extended_frame, bytes(payload)

    def encode_sync(self, name: str, node: int) -> tuple[int, bool, bytes]:
        """The sync frame announcing the freshness of rig message `name`'s stream of `node`
        (the value of the last frame signed on it, 0 before the first; key needed)."""
        spec = self.specs[name]
        if spec.secoc is None or self.sync is None:
            raise CodecError(f"{name} has no SecOC")
        if self._secoc is None:
            raise CodecError(f"{self.sync.message}: sync frames need a SecOC key")
        route = self._lookup(self.sync.message, node)
        assert route.sync is not None
        frame_id, ext, payload = self.encode(self.sync.message, node,
                                             {self.sync.kind: spec.secoc.sync_kind})
        return frame_id, ext, self._secoc.sign_sync(route.sync, (spec.secoc.stream, node),
                                                    payload)

    def encode_sample(self, name: str, node: int, u: Sequence[float] | NDArray[np.float64],
                      y: Sequence[float] | NDArray[np.float64],
                      truth: float | None = None, counter: int | None = None
                      ) -> tuple[int, bool, bytes]:
        """`encode` of rig message `name` from model-unit inputs `u` and outputs `y` (and a
        true gamma): each signal the message carries, converted to the DBC's unit."""
        spec = self.specs[name]
        values: dict[str, float] = {s: float(u[i]) / f for i, s, f in spec.inputs}
        values.update({s: float(v) / f for (s, f), v in zip(spec.outputs, y, strict=False)})
        if spec.truth is not None and truth is not None:
            values[spec.truth] = truth
        return self.encode(name, node, values, counter)

    # -- decoding -----------------------------------------------------------------------

    def decode(self, arbitration_id: int, data: bytes, is_extended: bool, is_remote: bool,
               is_error: bool, timestamp: float, is_fd: bool = False) -> Decoded | Rejected:
        """Classify one received frame; never raises."""
        found = screen_frame(self._checks.get((arbitration_id, is_extended)), arbitration_id,
                             data, is_remote, is_error, timestamp, is_fd)
        if found is None:
            if (arbitration_id, not is_extended) in self._by_key:
                return Rejected(RejectReason.EXTENDED_ID, arbitration_id, timestamp,
                                detail="the DBC defines this ID with the other ID length")
            return Rejected(RejectReason.UNKNOWN_ID, arbitration_id, timestamp,
                            detail=f"not a rig message in {self.source}")
        if isinstance(found, Rejected):
            return found
        signals, route = found
        inputs = tuple((i, float(signals[s]) * f) for i, s, f in route.inputs)
        outputs = tuple(float(signals[s]) * f for s, f in route.outputs)
        truth = None if route.truth is None else float(signals[route.truth])
        value = 0.0 if route.value is None else float(signals[route.value[0]]) * route.value[1]
        return Decoded(route.kind, route.node, timestamp, value,
                       None if route.counter is None else int(signals[route.counter]),
                       signals, inputs, outputs, truth)

    def _verify(self, route: Route, data: bytes) -> tuple[RejectReason, str] | None:
        """Why a secured or sync frame is rejected (None: authentic and fresh)."""
        assert self._secoc is not None
        if route.secoc is not None:
            secoc = self.specs[route.kind].secoc
            assert secoc is not None
            failed = self._secoc.verify(route.secoc, (secoc.stream, route.node), data)
        else:
            assert route.sync is not None
            index = route.sync.kind_index(data)
            stream = self._sync_streams.get(index)
            if stream is None:
                return RejectReason.OUT_OF_RANGE, f"SyncKind {index} names no secured message"
            failed = self._secoc.verify_sync(route.sync, (stream, route.node), data)
        return None if failed is None else (VERDICT_REASON[failed[0]], failed[1])

    def decode_can(self, msg: can.Message) -> Decoded | Rejected:
        """`decode` for a python-can message."""
        return self.decode(msg.arbitration_id, bytes(msg.data), msg.is_extended_id,
                           msg.is_remote_frame, msg.is_error_frame, msg.timestamp, msg.is_fd)


class Quantisation(NamedTuple):
    """The step between two values an output can take, in the model's unit, and the signal it
    comes from (what a report names)."""

    step: float
    source: str


def output_quantisation(decoder: RouteSource, node: int
                        ) -> tuple[Quantisation | None, ...]:
    """Per model output of `node`, in output order, the step of its decoded values: an
    integer-coded signal carries whole raw counts, so its values are multiples of the
    signal's scale (a DBC's factor; a CANopen object's scaling, `monitor.bus.canopen`) times
    the unit factor to the model's unit. None for a float-coded signal (its resolution is
    relative to its value, no fixed step); () for a node without outputs on this bus."""
    signals = [(r.message, r.outputs) for r in decoder.routes
               if r.node == node and r.outputs]
    if not signals:
        return ()
    message, outputs = signals[0]  # every output is in the one output message
    out: list[Quantisation | None] = []
    for name, factor in outputs:
        sig: Signal = message.get_signal_by_name(name)
        step = abs(float(sig.scale) * factor)
        if sig.is_float or not (math.isfinite(step) and step > 0):
            out.append(None)
            continue
        unit = f" {sig.unit}" if sig.unit else ""
        scaled = f", times {factor:g} to the model's unit" if factor != 1.0 else ""
        out.append(Quantisation(step, f"{message.name}.{name}: integer-coded, scale "
                                      f"{float(sig.scale):g}{unit}{scaled}"))
    return tuple(out)


def _route(message: Message, frame_id: int, spec: RigMessage, node: int,
           sync: RigSync | None) -> Route:
    """The route of rig message `spec` of `node` on `frame_id` (its SecOC layout added by
    `RigCodec._secured`): its kind the rig message's name, "sync" for the `sync` message;
    `Decoded.value` the first input, else the first output, else the truth, in the model's
    unit; the sync message's the freshness it carries. No reserved bits checked (a rig's
    DBC may leave bits its senders use)."""
    if sync is not None:
        return Route(frame_id, bool(message.is_extended_frame), message, node, "sync",
                     int(message.length), bool(message.is_fd), False, 0, (), None, (), (),
                     None, (sync.freshness, 1.0))
    value = (spec.inputs[0][1:] if spec.inputs else spec.outputs[0] if spec.outputs
             else None if spec.truth is None else (spec.truth, 1.0))
    return Route(frame_id, bool(message.is_extended_frame), message, node, spec.name,
                 int(message.length), bool(message.is_fd), spec.e2e, 0,
                 _limits(message, spec), spec.counter, spec.inputs, spec.outputs, spec.truth,
                 value)


def _limits(message: Message, spec: RigMessage) -> tuple[Limit, ...]:
    """[min, max] of every signal the estimator reads (NaN and inf fail it, with or
    without a range in the DBC)."""
    used = [s for _, s, _ in spec.inputs] + [s for s, _ in spec.outputs]
    if spec.truth is not None:
        used.append(spec.truth)
    out = []
    for name in dict.fromkeys(used):
        sig: Signal = message.get_signal_by_name(name)
        lo = -math.inf if sig.minimum is None else float(sig.minimum)
        hi = math.inf if sig.maximum is None else float(sig.maximum)
        if lo == hi == 0.0:  # a DBC that writes [0|0] means "no range given"
            lo, hi = -math.inf, math.inf
        out.append(Limit.of(name, lo, hi))
    return tuple(out)


def _attach_e2e(message: Message, data_id: int) -> None:
    """The properties cantools' profile-2 helpers read: one data ID for every counter."""
    e2e = AutosarEnd2EndProperties()
    e2e.category = "PROFILE_02"
    e2e.data_ids = [data_id & 0xFF] * 16
    e2e.payload_length = message.length
    specifics = AutosarMessageSpecifics()
    specifics.e2e = e2e
    message.autosar = specifics


def _attach_secoc(message: Message, layout: SecOCLayout) -> None:
    """The properties cantools' SecOC helpers read (`cantools.autosar.secoc`); cantools has
    no setter for them (ARXML fills them), as `monitor.bus.scheme` does for our bus."""
    if message.autosar is None:
        message.autosar = AutosarMessageSpecifics()
    message.autosar._secoc = layout.properties()
