"""The one place where CAN frames become typed samples, and samples become CAN frames.

Everything else in the monitor (and the virtual ECU) works on `Decoded` samples and
`Rejected` verdicts; nothing outside this package looks at payload bytes. All bit layout
and scaling comes from the DBC through cantools, and the AUTOSAR E2E CRCs are computed
and checked by `cantools.autosar.end_to_end`, so the DBC stays the single description
of the bus that `cantools dump` / `cantools decode` also read. The bus layout, the E2E
data IDs and the checks a DBC must pass are in `monitor.bus.scheme`; the alive-counter
supervision of decoded samples in `monitor.bus.counters`.

Optional SecOC-style authentication (`monitor.bus.secoc`: truncated AES-CMAC over SecOC data
ID, payload and a 64-bit freshness counter) on current and voltage frames: with a key
(``load_database(secoc_key=...)``) the database signs what it encodes and rejects, inside
`MotorDatabase.decode`, every current or voltage frame whose MAC does not verify
(``bad_mac``: forged, or unsigned) or whose freshness is not newer than the last accepted
one of its stream or too far ahead (``stale_freshness``: replayed), so such a frame never
reaches the estimator. The MAC is written before the E2E CRC, which covers it (E2E over
SecOC). Without a key the FreshnessValue and Authenticator signals are sent as 0 and not
checked: a monitor without the key cannot verify, so it decodes signed frames as before.
Diagnosis frames stay unauthenticated (8 spare bits cannot hold a useful MAC).

Freshness synchronisation (`monitor.bus.secoc.engine`, "Resynchronisation"): with a key the
database verifies ``SecOCSync`` frames (``bad_mac``; ``stale_freshness`` for a sync older
than the stream's last accepted value, i.e. a replayed one) and an accepted one sets that
stream's freshness, so a monitor that starts late, restarts, or lost more than the window
recovers at the next sync. A stream not yet synchronised (no sync, no saved state) rejects
its data frames as ``unsynced``. `encode_sync` builds sync frames (sender side, key
required); ``db.secoc.save_state`` / ``load_state`` persist the counters across restarts.
Without a key sync frames decode as plain ``sync`` samples (`Decoded.value` is
SyncFreshness), nothing checked.

Decoding never raises: every frame yields `Decoded` or `Rejected` with a reason from
`RejectReason`. Checks run cheapest-first, in the one order `CHECK_ORDER` of our bus's and
every rig's codec and of the column decoder (`monitor.columnar.decode`): error/remote/
extended flags, id lookup, then, in `check_payload`, frame format (every
message of our bus is classic CAN: a CAN FD frame with its ID is ``fd_frame``, whatever its
length), length, CRC, reserved bits (unused bits must be 0 -- a non-zero one means the
sender uses another DBC revision, reported as ``malformed``), the SecOC MAC and freshness
(with a key), then the DBC min/max of every signal (NaN fails). An authentic frame consumes
its freshness value even if a range check then rejects it.
"""

from __future__ import annotations

import contextlib
import copy
import logging
import math
import os
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum
from functools import partial
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Final, NamedTuple, TypeVar, cast

import cantools.database
from cantools.autosar.end_to_end import apply_profile2_crc, check_profile2_crc
from cantools.database.can import Database, Message

from monitor.bus.errors import CodecError
from monitor.bus.route import Limit, Route
from monitor.bus.scheme import (
    HEALTH_STATES,
    KINDS,
    N_NODES,
    SECOC_KINDS,
    Kind,
    build_routes,
    check_node,
    check_secoc_capable,
    e2e_data_id,
    frame_id,
)
from monitor.bus.secoc import (
    AUTHENTICATOR_SIGNAL,
    DEFAULT_WINDOW,
    FRESHNESS_SIGNAL,
    SecOC,
    SecOCError,
    SecOCHolder,
    SecOCLayout,
    SyncLayout,
    Verdict,
)
from monitor.errors import one_line
from monitor.files import MIB, UserFileError, read_user_file, shown_path

if TYPE_CHECKING:
    import can

__all__ = [
    "CHECK_ORDER",
    "HEALTH_STATES",
    "KINDS",
    "N_NODES",
    "SECOC_KINDS",
    "VERDICT_REASON",
    "CodecError",
    "Decoded",
    "Kind",
    "MotorDatabase",
    "PayloadCheck",
    "RejectReason",
    "Rejected",
    "check_payload",
    "default_dbc_path",
    "e2e_data_id",
    "frame_id",
    "load_database",
    "load_dbcs",
    "screen_frame",
]

DEFAULT_DBC_NAME: Final = "motor.dbc"
_log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- results


class RejectReason(StrEnum):
    """Why a frame was not turned into a sample (fixed set: counted and logged per reason)."""

    UNKNOWN_ID = "unknown_id"
    WRONG_LENGTH = "wrong_length"
    BAD_CRC = "bad_crc"
    OUT_OF_RANGE = "out_of_range"
    MALFORMED = "malformed"
    REMOTE_FRAME = "remote_frame"
    ERROR_FRAME = "error_frame"
    EXTENDED_ID = "extended_id"
    BAD_MAC = "bad_mac"  # SecOC: the authenticator does not verify (forged or unsigned)
    STALE_FRESHNESS = "stale_freshness"  # SecOC: authentic, but replayed or too far ahead
    UNSYNCED = "unsynced"  # SecOC: the stream's freshness is unknown until a sync frame
    FD_FRAME = "fd_frame"  # CAN FD frame for a classic DBC message, or the reverse


CHECK_ORDER: Final[tuple[RejectReason, ...]] = (
    RejectReason.ERROR_FRAME,
    RejectReason.REMOTE_FRAME,
    RejectReason.EXTENDED_ID,
    RejectReason.UNKNOWN_ID,
    RejectReason.FD_FRAME,
    RejectReason.WRONG_LENGTH,
    RejectReason.BAD_CRC,
    RejectReason.MALFORMED,  # reserved bits set
    RejectReason.BAD_MAC,  # the SecOC check gives one of these three
    RejectReason.STALE_FRESHNESS,
    RejectReason.UNSYNCED,
    RejectReason.OUT_OF_RANGE,
)
"""The one order of a frame's checks: a frame failing several gets the first failed one's
reason, from every codec's ``decode`` (the ID there, the flags and the payload in
`screen_frame`) and from the column decoder (`monitor.columnar.decode.RouteTable`). A
payload that is no bytes, or that cantools cannot decode, is ``malformed`` where that is
found (before the frame format, after SecOC); columns meet neither. Every check of the
payload needs the frame format and length checked first, so they stay ahead of the content
checks."""

VERDICT_REASON: Final[Mapping[Verdict, RejectReason]] = {  # SecOC's verdicts as outcomes
    Verdict.BAD_MAC: RejectReason.BAD_MAC,
    Verdict.STALE_FRESHNESS: RejectReason.STALE_FRESHNESS,
    Verdict.UNSYNCED: RejectReason.UNSYNCED,
}


@dataclass(frozen=True, slots=True)
class Decoded:
    """A valid frame as a typed sample.

    `value` is the kind's main physical value: ArmatureCurrent (A), VoltageCommand (V),
    TrueGamma, GammaEstimate, SyncFreshness (low 32 bits; the stream in raw["SyncKind"]).
    `counter` is the alive counter (None for truth and sync frames), `raw` all signals of
    the frame, physical (scaled) values, choices as ints.

    What the estimator takes from the frame, in the model's units: `inputs`, (index, value)
    pairs of the model inputs u it carries; `outputs`, every model output y (a frame with
    outputs is one sample); `truth`, a simulator's true gamma. For a rig's own DBC
    (`monitor.bus.rigcodec`) `kind` is the message's name in the rig.
    """

    kind: str
    node: int
    timestamp: float
    value: float
    counter: int | None
    raw: Mapping[str, float]
    inputs: tuple[tuple[int, float], ...] = ()
    outputs: tuple[float, ...] = ()
    truth: float | None = None


@dataclass(frozen=True, slots=True)
class Rejected:
    """A frame that must not reach the estimator, with the reason and what is known."""

    reason: RejectReason
    arbitration_id: int
    timestamp: float
    node: int | None = None
    kind: str | None = None  # Decoded.kind of the route, once the ID is known
    detail: str = ""


# ----------------------------------------------------------------------------- checks

Verify = Callable[[bytes], tuple[RejectReason, str] | None]
"""A codec's SecOC check of one route's payload: why it fails (None: authentic and fresh,
or nothing to verify)."""

Decode = Callable[[bytes, bool, bool, bool, bool], dict[str, float]]
"""A message's ``decode_simple`` (cantools' ``decode`` of a message that is no container):
payload, decode_choices, scaling, allow_truncated, allow_excess -> signals."""


class PayloadCheck(NamedTuple):
    """What `check_payload` needs of one `Route`, read once when the codec builds its
    routing (no cantools property or method is looked up per frame): the message, its
    decoder, the route's length, frame format, E2E, reserved bits and limits, the codec's
    SecOC check of the route (None: no key, or nothing to verify), and the node and kind a
    rejection names."""

    message: Message
    decode: Decode
    length: int
    is_fd: bool
    e2e: bool
    reserved_mask: int
    limits: tuple[Limit, ...]
    verify: Verify | None
    node: int
    kind: str

    @classmethod
    def of(cls, route: Route, verify: Verify | None) -> PayloadCheck:
        """The check of `route`, with the codec's SecOC check of it."""
        # decode_choices=False (in check_payload) gives every signal as a number
        decode = cast("Decode", route.message.decode_simple)
        return cls(route.message, decode, route.length, route.fd, route.e2e,
                   route.reserved_mask, route.limits, verify, route.node, route.kind)


def check_payload(check: PayloadCheck, arbitration_id: int, data: object, is_fd: bool,
                  timestamp: float) -> dict[str, float] | Rejected:
    """The checks of a frame routed to `check.message`, in `CHECK_ORDER` for every codec
    (our bus's and a rig's): the payload as bytes, frame format (CAN FD or classic, as the
    message), length, the E2E profile-2 CRC, reserved bits (bits no signal uses must be 0),
    SecOC (with a key), decoding by cantools, then the limits (NaN and inf fail). Returns
    the decoded signals (physical values, choices as ints), or why not; never raises (hot
    path: one call per frame, so `check` is a tuple built once per route, and the order is
    written out, not looked up: tests/columnar/test_route_verdicts holds it to the column
    decoder's, which follows `CHECK_ORDER` step by step)."""
    message, decode, length, fd, e2e, reserved_mask, limits, verify, node, kind = check
    if type(data) is bytes:
        payload = data
    else:
        try:
            payload = bytes(data)  # type: ignore[call-overload]
        except Exception as exc:  # any object handed in by a driver: report, not raise
            return Rejected(RejectReason.MALFORMED, arbitration_id, timestamp, node, kind,
                            f"payload is {type(exc).__name__}")
    if is_fd != fd:
        want, got = ("CAN FD", "classic CAN") if fd else ("classic CAN", "CAN FD")
        return Rejected(RejectReason.FD_FRAME, arbitration_id, timestamp, node, kind,
                        f"{got} frame of {len(payload)} bytes; {message.name} is a {want} "
                        "message")
    if len(payload) != length:
        return Rejected(RejectReason.WRONG_LENGTH, arbitration_id, timestamp, node, kind,
                        f"{len(payload)} bytes, expected {length}")
    if e2e and not check_profile2_crc(payload, message):
        return Rejected(RejectReason.BAD_CRC, arbitration_id, timestamp, node, kind,
                        f"crc 0x{payload[0]:02X}, counter {payload[1] & 0xF}")
    if reserved_mask and int.from_bytes(payload, "little") & reserved_mask:
        return Rejected(RejectReason.MALFORMED, arbitration_id, timestamp, node, kind,
                        "reserved bits set")
    if verify is not None:
        failed = verify(payload)
        if failed is not None:
            return Rejected(failed[0], arbitration_id, timestamp, node, kind, failed[1])
    try:
        # decode_choices=False, scaling=True, allow_truncated=False, allow_excess=False
        signals = decode(payload, False, True, False, False)
    except Exception as exc:  # decode must never raise; cantools may raise several types
        return Rejected(RejectReason.MALFORMED, arbitration_id, timestamp, node, kind,
                        f"{type(exc).__name__}: {exc}")
    for name, low, high, lo, hi in limits:
        v = signals[name]
        if not low <= v <= high:  # NaN and inf too, ranged or not: low and high are finite
            return Rejected(RejectReason.OUT_OF_RANGE, arbitration_id, timestamp, node, kind,
                            f"{name}={v} not in [{lo}, {hi}]")
    return signals


_R = TypeVar("_R")


def screen_frame(hit: tuple[PayloadCheck, _R] | None, arbitration_id: int, data: object,
                 is_remote: bool, is_error: bool, timestamp: float,
                 is_fd: bool) -> tuple[dict[str, float], _R] | Rejected | None:
    """Every codec's ``decode`` in `CHECK_ORDER` but for the ID: an error frame (whose "id"
    carries error class bits, so it is never taken for an unknown ID), a remote frame, then,
    for the route `hit` the codec looked the ID up to (its `check_payload` check, and what
    the codec reads the signals by), the payload. None: no route, the codec says why (an
    extended or unknown ID); else the decoded signals and the route's reading, or why not."""
    if is_error:
        return Rejected(RejectReason.ERROR_FRAME, arbitration_id, timestamp)
    if is_remote:
        return Rejected(RejectReason.REMOTE_FRAME, arbitration_id, timestamp,
                        detail="remote frames carry no data")
    if hit is None:
        return None
    check, reading = hit
    signals = check_payload(check, arbitration_id, data, is_fd, timestamp)
    if isinstance(signals, Rejected):
        return signals
    return signals, reading


# ----------------------------------------------------------------------------- database


class _Reading(NamedTuple):
    """How `MotorDatabase.decode` makes a sample of a route's signals, read off its `Route`
    once: on our bus a frame's one value signal (factor 1) is its `Decoded.value` and at
    most one of model input `as_input`, the model's output, the true gamma."""

    kind: str
    node: int
    signal: str
    counter: str | None
    as_input: int | None
    as_output: bool
    as_truth: bool

    @classmethod
    def of(cls, route: Route) -> _Reading:
        assert route.value is not None and route.value[1] == 1.0  # build_routes
        signal = route.value[0]
        assert all((s, f) == (signal, 1.0) for _, s, f in route.inputs)
        assert route.outputs in ((), ((signal, 1.0),)) and route.truth in (None, signal)
        return cls(route.kind, route.node, signal, route.counter,
                   route.inputs[0][0] if route.inputs else None, bool(route.outputs),
                   route.truth is not None)


class MotorDatabase(SecOCHolder):
    """The motor bus DBC plus a pre-built frame-id routing table for the hot decode path.

    With `secoc_key` (16 or 32 bytes) current and voltage frames are signed on encoding
    and verified on decoding; the object then keeps the freshness counters of every
    (kind, node) stream it sends and receives (see `monitor.bus.secoc`; sending and receiving
    counters are separate), so keep one object for the whole life of a bus connection.
    """

    accepts_extended: Final = False
    """Our bus is 11-bit only: every 29-bit frame is ``extended_id`` (`RouteSource`)."""

    def __init__(self, db: Database, source: str, secoc_key: bytes | None = None, *,
                 secoc_window: int = DEFAULT_WINDOW) -> None:
        self._db = db
        self.source = source
        self._routes = build_routes(db, source)
        self._by_kind: dict[tuple[str, int], Route] = {(r.kind, r.node): r for r in self._routes}
        self._secoc = None
        if secoc_key is not None:
            self._secoc = self._new_secoc(secoc_key, secoc_window)
        self._checks = self._build_checks()

    def _build_checks(self) -> dict[int, tuple[PayloadCheck, _Reading]]:
        """Each frame ID's `check_payload` check, SecOC verified by this database's engine
        (rebuilt when the engine changes), and how its sample is read."""
        secoc = self._secoc is not None
        return {r.frame_id: (PayloadCheck.of(
                    r, partial(self._verify, r) if secoc and (r.secoc or r.sync) else None),
                    _Reading.of(r))
                for r in self._routes}

    @property
    def routes(self) -> tuple[Route, ...]:
        """Every frame ID of the bus and how it is read, in frame-ID order (`RouteSource`)."""
        return self._routes

    def _new_secoc(self, key: bytes, window: int) -> SecOC:
        check_secoc_capable(self._routes, self.source)
        try:
            return SecOC(key, window=window)
        except SecOCError as exc:
            raise CodecError(str(exc)) from None

    def with_secoc_key(self, key: bytes | None, *,
                       window: int = DEFAULT_WINDOW) -> MotorDatabase:
        """A database on the same DBC with its own SecOC key and fresh counters (None: off)."""
        clone = copy.copy(self)
        clone._secoc = None if key is None else self._new_secoc(key, window)
        clone._checks = clone._build_checks()
        return clone

    # -- SecOC ------------------------------------------------------------------------

    def secoc_layout(self, kind: Kind, node: int) -> SecOCLayout | None:
        """Where the message of `kind` for `node` carries freshness and MAC (None: nowhere)."""
        return self._route(kind, node).secoc

    def sync_layout(self, node: int) -> SyncLayout:
        """The layout of `node`'s SecOC sync frame (`CodecError` if the DBC has none)."""
        layout = self._route("sync", node).sync
        assert layout is not None  # every sync route has one (build_routes)
        return layout

    # -- lookup ---------------------------------------------------------------------

    def message(self, kind: Kind, node: int) -> Message:
        """The cantools message of `kind` for `node` (cycle time, comments, signals)."""
        return self._route(kind, node).message

    def frame_id(self, kind: Kind, node: int) -> int:
        """The frame id of `kind` for `node`, as in the DBC."""
        return self._route(kind, node).message.frame_id

    def _route(self, kind: str, node: int) -> Route:
        check_node(node)
        route = self._by_kind.get((kind, node))
        if route is None:
            raise CodecError(f"unknown message kind {kind!r}; expected one of {KINDS}")
        return route

    # -- encoding ---------------------------------------------------------------------

    def encode_current(self, node: int, current_a: float, counter: int) -> bytes:
        """MotorCurrent payload (armature current in A) with counter and E2E CRC."""
        return self._encode("current", node, {"ArmatureCurrent": current_a}, counter)

    def encode_voltage(self, node: int, volts: float, counter: int) -> bytes:
        """MotorVoltage payload (voltage command in V) with counter and E2E CRC."""
        return self._encode("voltage", node, {"VoltageCommand": volts}, counter)

    def encode_truth(self, node: int, gamma: float, current: float, speed: float) -> bytes:
        """SimTruth payload (virtual ECU only): true gamma, current (A), speed (rad/s)."""
        return self._encode(
            "truth",
            node,
            {"TrueGamma": gamma, "TrueCurrent": current, "TrueSpeed": speed},
            None,
        )

    def encode_diagnosis(
        self,
        node: int,
        state: str | int,
        gamma: float,
        fault: float,
        rules: int,
        counter: int,
        model_mismatch: bool = False,
    ) -> bytes:
        """MonitorDiagnosis payload with counter and E2E CRC.

        `state` is a name from `HEALTH_STATES` or its index; `fault` is gamma*u in volts;
        `model_mismatch` the flag beside the state (signal ModelMismatch, bit 56).
        Values outside the DBC range raise `CodecError`: clipping is the caller's decision.
        """
        if isinstance(state, str):
            if state not in HEALTH_STATES:
                raise CodecError(f"unknown health state {state!r}; expected one of "
                                 f"{HEALTH_STATES}")
            state_value = HEALTH_STATES.index(state)
        elif isinstance(state, int) and 0 <= state < len(HEALTH_STATES):
            state_value = state
        else:
            raise CodecError(f"health state must be a name or 0..{len(HEALTH_STATES) - 1}, "
                             f"got {state!r}")
        if not isinstance(rules, int):
            raise CodecError(f"rule count must be an int, got {rules!r}")
        signals: dict[str, float] = {
            "HealthState": state_value,
            "GammaEstimate": gamma,
            "FaultEstimate": fault,
            "RuleCount": rules,
            "ModelMismatch": 1 if model_mismatch else 0,
        }
        return self._encode("diagnosis", node, signals, counter)

    def encode_sync(self, node: int, kind: Kind) -> bytes:
        """SecOCSync payload announcing the freshness of `node`'s `kind` stream (key needed).

        Carries the low 32 bits of the freshness value of the last frame this database
        signed on the stream (0 before the first) and its MAC; consumes no freshness value.
        """
        if kind not in SECOC_KINDS:
            raise CodecError(f"sync frames are for {' and '.join(SECOC_KINDS)}, not {kind!r}")
        route = self._route("sync", node)
        if self._secoc is None:
            raise CodecError(f"{route.message.name}: sync frames need a SecOC key")
        layout = route.sync
        assert layout is not None
        payload = route.message.encode({"SyncKind": SECOC_KINDS.index(kind),
                                        "SyncFreshness": 0, "SyncAuthenticator": 0},
                                       scaling=False, padding=False, strict=True)
        return self._secoc.sign_sync(layout, (kind, node), payload)

    def _encode(
        self, kind: Kind, node: int, values: dict[str, float], counter: int | None
    ) -> bytes:
        route = self._route(kind, node)
        name = route.message.name
        for signal, value in values.items():
            if not isinstance(value, int | float) or not math.isfinite(value):
                raise CodecError(f"{name}: {signal} must be a finite number, got {value!r}")
        signals = dict(values)
        if route.e2e:
            if counter is None or not isinstance(counter, int) or not 0 <= counter <= 15:
                raise CodecError(f"{name}: counter must be an int in 0..15, got {counter!r}")
            signals["CRC"] = 0
            signals["Counter"] = counter
        if route.secoc is not None:
            signals[FRESHNESS_SIGNAL] = 0
            signals[AUTHENTICATOR_SIGNAL] = 0
        try:
            payload = route.message.encode(signals, scaling=True, padding=False, strict=True)
        except (cantools.database.EncodeError, ValueError, OverflowError) as exc:
            raise CodecError(f"{name}: {exc}") from None
        if route.secoc is not None and self._secoc is not None:
            # SecOC first (the MAC sees the CRC byte as 0), then the E2E CRC over all.
            try:
                payload = self._secoc.sign(route.secoc, (kind, node), payload)
            except SecOCError as exc:
                raise CodecError(str(exc)) from None
        if not route.e2e:
            return payload
        protected = apply_profile2_crc(payload, route.message)
        if protected is None:  # cannot happen for a route built by build_routes
            raise CodecError(f"{name}: cantools did not apply the E2E profile 2 CRC")
        return bytes(protected)

    # -- decoding ---------------------------------------------------------------------

    def decode(
        self,
        arbitration_id: int,
        data: bytes,
        is_extended: bool,
        is_remote: bool,
        is_error: bool,
        timestamp: float,
        is_fd: bool = False,
    ) -> Decoded | Rejected:
        """Classify one received frame; never raises (hot path: ~10k frames/s).

        Flags are checked before the id so that an error frame, whose "id" carries error
        class bits, is never misreported as an unknown id.
        """
        found = screen_frame(None if is_extended else self._checks.get(arbitration_id),
                             arbitration_id, data, is_remote, is_error, timestamp, is_fd)
        if found is None:
            if is_extended:
                return Rejected(RejectReason.EXTENDED_ID, arbitration_id, timestamp,
                                detail=f"29-bit id 0x{arbitration_id:08X}")
            return Rejected(RejectReason.UNKNOWN_ID, arbitration_id, timestamp,
                            detail=f"not in {self.source}")
        if isinstance(found, Rejected):
            return found
        signals, reading = found
        kind, node, signal, counter, as_input, as_output, as_truth = reading
        value = float(signals[signal])
        return Decoded(
            kind,
            node,
            timestamp,
            value,
            None if counter is None else int(signals[counter]),
            signals,
            ((as_input, value),) if as_input is not None else (),
            (value,) if as_output else (),
            value if as_truth else None,
        )

    def _verify(self, route: Route, data: bytes) -> tuple[RejectReason, str] | None:
        """Why a current, voltage or sync frame fails SecOC (None: authentic and fresh, or
        nothing to verify: a sync frame of no stream is out_of_range by its limits)."""
        assert self._secoc is not None
        if route.secoc is not None:
            failed = self._secoc.verify(route.secoc, (route.kind, route.node), data)
        else:
            assert route.sync is not None  # only secured and sync routes are verified
            index = route.sync.kind_index(data)
            if index >= len(SECOC_KINDS):
                return None
            failed = self._secoc.verify_sync(route.sync, (SECOC_KINDS[index], route.node),
                                             data)
        return None if failed is None else (VERDICT_REASON[failed[0]], failed[1])

    def decode_can(self, msg: can.Message) -> Decoded | Rejected:
        """`decode` for a python-can message (flags read from the message, not guessed)."""
        return self.decode(msg.arbitration_id, bytes(msg.data), msg.is_extended_id,
                           msg.is_remote_frame, msg.is_error_frame, msg.timestamp, msg.is_fd)


def default_dbc_path() -> Path:
    """The DBC shipped in the package: ``monitor/bus/motor.dbc``, a link to the repository's
    dbc/motor.dbc (a copy of it in a wheel)."""
    return Path(str(resources.files("monitor.bus") / DEFAULT_DBC_NAME))


def load_database(
    path: str | Path | None = None,
    *,
    secoc_key: bytes | None = None,
    secoc_window: int = DEFAULT_WINDOW,
) -> MotorDatabase:
    """Load and validate the motor DBC; any problem is one `CodecError` line.

    `secoc_key` (16 or 32 bytes, e.g. from `monitor.bus.secoc.load_key`) turns on SecOC
    authentication of current and voltage frames: signed when encoded, verified when
    decoded, with freshness values accepted up to `secoc_window` ahead of the last one.
    """
    p = default_dbc_path() if path is None else Path(path)
    return MotorDatabase(load_dbcs([p]), str(p), secoc_key, secoc_window=secoc_window)


DBC_FILE_LIMIT: Final = 64 * MIB
"""The largest DBC file read: vehicle DBCs of thousands of messages take a few MiB."""


def load_dbcs(paths: Sequence[Path]) -> Database:
    """One cantools database (strict: overlapping signals are errors) from one or more DBC
    files; any problem is one `CodecError` line naming the file, two messages on one frame
    ID (or of one name) and a file listed twice too (cantools only warns)."""
    db = Database(strict=True)
    loading = _DbcLoad(paths)
    for p in paths:
        try:
            data = read_user_file(p, what="DBC file", limit=DBC_FILE_LIMIT)
        except UserFileError as exc:
            raise CodecError(str(exc)) from None
        # decoded as cantools' add_dbc_file reads a file: cp1252 (what DBC editors write),
        # undecodable bytes replaced, universal newlines
        text = data.decode("cp1252", errors="replace").replace("\r\n", "\n").replace("\r", "\n")
        try:
            with loading.adding(p, db):
                db.add_dbc_string(text)
        except Exception as exc:  # cantools/textparser raise many types for a bad DBC
            raise CodecError(f"DBC file {shown_path(p)}: not a valid DBC: {one_line(exc)}"
                             ) from None
    loading.check(db)
    return db


class _DbcLoad:
    """What `load_dbcs` learns while cantools adds its files: which file each message
    came from, and cantools' log and warnings, kept instead of printed (the user's
    terminal gets one line per mistake). `check` then refuses what cantools only warns
    about: two messages on one frame ID (or of one name), and a file listed twice."""

    def __init__(self, paths: Sequence[Path]) -> None:
        self.files: list[tuple[Path, int]] = []  # (file, messages in the database after it)
        self.heard: list[tuple[Path, str]] = []
        seen: dict[Path, Path] = {}  # the file (links resolved) -> as it was first named
        for p in paths:
            key = Path(os.path.realpath(p))  # Path.resolve raises on a link loop
            if key in seen:
                first = seen[key]
                twice = "" if str(first) == str(p) else f" (as {shown_path(first)} too)"
                raise CodecError(f"{shown_path(p)}: listed twice{twice}")
            seen[key] = p

    @contextlib.contextmanager
    def adding(self, path: Path, db: Database) -> Iterator[None]:
        """Keep what cantools logs and warns while it adds `path` to `db`."""
        keep = _Keep()
        logger = logging.getLogger("cantools")
        propagate, logger.propagate = logger.propagate, False
        logger.addHandler(keep)
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                yield
        finally:
            logger.removeHandler(keep)
            logger.propagate = propagate
        self.heard += [(path, text) for text in keep.texts]
        self.heard += [(path, str(w.message)) for w in caught]
        self.files.append((path, len(db.messages)))

    def _file_of(self, index: int) -> Path:
        return next(p for p, end in self.files if index < end)

    def _clash(self, db: Database, first: int, second: int, what: str, *,
               ids: bool = False) -> CodecError:
        """Messages `first` and `second` (indices in `db.messages`) have `what` alike;
        `ids`: name their frame IDs (which `what` does not)."""
        one, two = db.messages[first], db.messages[second]
        if len(self.files) == 1:
            a, b = (f"{m.name} (0x{m.frame_id:X})" if ids else m.name for m in (one, two))
            return CodecError(f"{shown_path(self.files[0][0])}: messages {a} and {b} have "
                              f"{what}")
        a, b = (f"{m.name} ({f'0x{m.frame_id:X} ' if ids else ''}in "
                f"{shown_path(self._file_of(i))})" for m, i in ((one, first), (two, second)))
        return CodecError(f"messages {a} and {b} have {what}")

    def check(self, db: Database) -> None:
        """`CodecError` for two messages with one frame ID or one name (cantools keeps the
        last and warns); what else cantools said is logged at INFO (a DBC that loads
        needs no second line)."""
        by_id: dict[tuple[int, bool], int] = {}
        by_name: dict[str, int] = {}
        for i, m in enumerate(db.messages):
            j = by_id.setdefault((m.frame_id, m.is_extended_frame), i)
            if j != i:
                bits = "29" if m.is_extended_frame else "11"
                raise self._clash(db, j, i, f"the same {bits}-bit frame ID 0x{m.frame_id:X}")
            k = by_name.setdefault(m.name, i)
            if k != i:
                raise self._clash(db, k, i, "the same name", ids=True)
        for path, text in self.heard:
            _log.info("%s: cantools: %s", shown_path(path), one_line(text))


class _Keep(logging.Handler):
    """A logging handler that keeps the messages (cantools' records while a DBC loads)."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.texts: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.texts.append(record.getMessage())
