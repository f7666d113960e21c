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
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, NamedTuple

import cantools.database
import numpy as np
from cantools.autosar.end_to_end import apply_profile2_crc
from cantools.database.can import Database, Message, Signal
from cantools.database.can.formats.arxml import AutosarEnd2EndProperties, AutosarMessageSpecifics
from numpy.typing import NDArray

from monitor.bus.codec import (
    VERDICT_REASON,
    Decoded,
    MotorDatabase,
    PayloadCheck,
    Rejected,
    RejectReason,
    check_payload,
    load_dbcs,
)
from monitor.bus.errors import CodecError, SecOCError
from monitor.bus.secoc import DEFAULT_WINDOW, SecOC, SecOCHolder, SecOCLayout, SyncLayout
from monitor.errors import one_line

if TYPE_CHECKING:
    import can

    from monitor.bus.canopen import CanopenNode

__all__ = ["Quantisation", "Resolver", "RigCodec", "RigMessage", "RigRoute", "RigSecOC", "RigSync",
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


@dataclass(frozen=True, slots=True)
class RigRoute:
    """One arbitration ID of the rig: its DBC message, how the rig reads it, its node, the
    signals' limits, its SecOC or sync layout."""

    message: Message
    spec: RigMessage
    node: int
    limits: tuple[tuple[str, float, float], ...]
    secoc: SecOCLayout | None = None
    sync: SyncLayout | None = None


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
        self._routes: dict[tuple[int, bool], RigRoute] = {}
        self._by_name: dict[tuple[str, int], tuple[RigRoute, int]] = {}
        self._sync_streams = {m.secoc.sync_kind: m.secoc.stream
                              for m in messages if m.secoc is not None}
        if self._sync_streams and sync is None:
            raise CodecError(f"{source}: SecOC needs a sync message")
        data_ids: dict[int, str] = {}
        sync_spec = None if sync is None else RigMessage(sync.message)
        for spec in (*messages, *(() if sync_spec is None else (sync_spec,))):
            for node in nodes:
                found = resolve(spec.name, node)
                if found is None:
                    continue
                message, frame_id = found
                route = self._secured(
                    RigRoute(message, spec, node, _limits(message, spec)), frame_id,
                    spec is sync_spec)
                key = (frame_id, message.is_extended_frame)
                other = self._routes.get(key)
                if other is not None and other is not route:
                    raise CodecError(f"{source}: {spec.name} of node {node} and "
                                     f"{other.spec.name} of node {other.node} share ID "
                                     f"0x{frame_id:X}")
                self._routes[key] = route
                self._by_name[(spec.name, node)] = (route, frame_id)
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
        secured = self._secoc is not None
        self._checks: dict[tuple[int, bool], tuple[RigRoute, PayloadCheck]] = {
            key: (r, PayloadCheck.of(
                r.message, r.node, None, r.spec.e2e, 0, r.limits,
                partial(self._verify, r) if secured and (r.secoc or r.sync) else None))
            for key, r in self._routes.items()}

    def _secured(self, route: RigRoute, frame_id: int, is_sync: bool) -> RigRoute:
        """`route` with its SecOC layout (data ID: the frame ID's low 16 bits)."""
        msg, sec, data_id = route.message, route.spec.secoc, frame_id & 0xFFFF
        try:
            if is_sync:
                assert self.sync is not None
                s = self.sync
                kind, fv, auth = (msg.get_signal_by_name(n)
                                  for n in (s.kind, s.freshness, s.authenticator))
                return RigRoute(msg, route.spec, route.node, route.limits,
                              sync=SyncLayout.from_signals(msg, kind, fv, auth, data_id=data_id,
                                                           freshness_bits=s.freshness_length))
            if sec is None:
                return route
            fv, auth = (msg.get_signal_by_name(n) for n in (sec.freshness, sec.authenticator))
            layout = SecOCLayout.from_signals(msg, fv, auth, data_id=data_id,
                                              freshness_bits=sec.freshness_length,
                                              crc_byte=route.spec.e2e)
            return RigRoute(msg, route.spec, route.node, route.limits, secoc=layout)
        except KeyError as exc:
            raise CodecError(f"{msg.name}: no signal {exc.args[0]} for SecOC") from None
        except SecOCError as exc:
            raise CodecError(str(exc)) from None

    @property
    def routes(self) -> Mapping[tuple[int, bool], RigRoute]:
        """Every (arbitration ID, extended) of the rig and how it is read (read-only)."""
        return MappingProxyType(self._routes)

    @property
    def secured(self) -> bool:
        """Whether any rig message has SecOC (verified only with a key)."""
        return bool(self._sync_streams)

    @property
    def nodes(self) -> tuple[int, ...]:
        return tuple(sorted({n for _, n in self._by_name}))

    def frame_id(self, name: str, node: int) -> int:
        """The arbitration ID of rig message `name` of `node`."""
        return self._lookup(name, node)[1]

    def message(self, name: str, node: int) -> Message:
        return self._lookup(name, node)[0].message

    def sync_message(self, node: int) -> Message:
        """`node`'s SecOC sync message (`CodecError` if the rig has none)."""
        if self.sync is None:
            raise CodecError("this rig has no SecOC sync message")
        return self.message(self.sync.message, node)

    def _lookup(self, name: str, node: int) -> tuple[RigRoute, int]:
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
        route, frame_id = self._lookup(name, node)
        msg, spec = route.message, route.spec
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
        route = self._lookup(self.sync.message, node)[0]
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
        if is_error:
            return Rejected(RejectReason.ERROR_FRAME, arbitration_id, timestamp)
        if is_remote:
            return Rejected(RejectReason.REMOTE_FRAME, arbitration_id, timestamp,
                            detail="remote frames carry no data")
        hit = self._checks.get((arbitration_id, is_extended))
        if hit is None:
            if (arbitration_id, not is_extended) in self._routes:
                return Rejected(RejectReason.EXTENDED_ID, arbitration_id, timestamp,
                                detail="the DBC defines this ID with the other ID length")
            return Rejected(RejectReason.UNKNOWN_ID, arbitration_id, timestamp,
                            detail=f"not a rig message in {self.source}")
        route, check = hit
        signals = check_payload(check, arbitration_id, data, is_fd, timestamp)
        if isinstance(signals, Rejected):
            return signals
        spec, node = route.spec, route.node
        if route.sync is not None:
            assert self.sync is not None
            return Decoded("sync", node, timestamp, float(signals[self.sync.freshness]), None,
                           signals)
        inputs = tuple((i, float(signals[s]) * f) for i, s, f in spec.inputs)
        outputs = tuple(float(signals[s]) * f for s, f in spec.outputs)
        truth = None if spec.truth is None else float(signals[spec.truth])
        first = inputs[0][1] if inputs else outputs[0] if outputs else (truth or 0.0)
        return Decoded(spec.name, node, timestamp, first,
                       None if spec.counter is None else int(signals[spec.counter]),
                       signals, inputs, outputs, truth)

    def _verify(self, route: RigRoute, data: bytes) -> tuple[RejectReason, str] | None:
        """Why a secured or sync frame is rejected (None: authentic and fresh)."""
        assert self._secoc is not None
        if route.secoc is not None:
            assert route.spec.secoc is not None
            failed = self._secoc.verify(route.secoc, (route.spec.secoc.stream, route.node),
                                        data)
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


def output_quantisation(decoder: MotorDatabase | RigCodec, node: int
                        ) -> tuple[Quantisation | None, ...]:
    """Per model output of `node`, in output order, the step of its decoded values: an
    integer-coded signal carries whole raw counts, so its values are multiples of the
    signal's scale (a DBC's factor; a CANopen object's scaling, `monitor.bus.canopen`) times
    the unit factor to the model's unit. None for a float-coded signal (its resolution is
    relative to its value, no fixed step); () for a node without outputs on this bus."""
    signals: list[tuple[Message, tuple[tuple[str, float], ...]]]
    if isinstance(decoder, MotorDatabase):  # our own bus: the armature current, unscaled
        signals = [(r.message, ((r.value_signal, 1.0),)) for r in decoder.routes.values()
                   if r.kind == "current" and r.node == node]
    else:
        signals = [(r.message, r.spec.outputs) for r in decoder.routes.values()
                   if r.node == node and r.spec.outputs]
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


def _limits(message: Message, spec: RigMessage) -> tuple[tuple[str, float, float], ...]:
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
        out.append((name, lo, hi))
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
