"""The one place where CAN frames become typed samples, and samples become CAN frames.

Everything else in the monitor (and the virtual ECU) works on `Decoded` samples and
`Rejected` verdicts; nothing outside this module looks at payload bytes. All bit layout
and scaling comes from the DBC through cantools, and the AUTOSAR E2E CRCs are computed
and checked by `cantools.autosar.end_to_end`, so the DBC stays the single description
of the bus that `cantools dump` / `cantools decode` also read.

Bus layout (standard 11-bit ids, DLC 8, Intel byte order; node 0..15 = id & 0xF; DBC
message names carry the node as ``_N<node>``, e.g. ``MotorCurrent_N3``):

* ``current``   MotorCurrent_N<n>, 0x110 + n, 10 ms, MotorECU -> Monitor:
  ArmatureCurrent (A, 0.01, +-300), E2E, SecOC (FreshnessValue bits 32-39, Authenticator
  bits 40-63).
* ``voltage``   MotorVoltage_N<n>, 0x120 + n, 50 ms, MotorECU -> Monitor:
  VoltageCommand (V, 0.01, +-400), E2E, SecOC (FreshnessValue bits 12-15, Authenticator
  bits 40-63).
* ``truth``     SimTruth_N<n>, 0x7E0 + n, 10 ms, virtual MotorECU only, no E2E:
  TrueGamma (0..1, 1e-4), TrueCurrent (A, 0.01, +-300), TrueSpeed (rad/s, 0.01, +-3000).
* ``diagnosis`` MonitorDiagnosis_N<n>, 0x180 + n, 100 ms, Monitor: HealthState (bits
  12-15, VAL_ `HEALTH_STATES`), GammaEstimate (0.001, -0.5..1.5: signed because estimator
  transients undershoot 0), FaultEstimate (gamma*u, V, 0.1, +-1000), RuleCount (0..255), E2E.
* ``sync``      SecOCSync_N<n>, 0x1F0 + n, 1 s per stream, MotorECU -> Monitor, only with
  SecOC on: SyncKind (bits 0-3, VAL_ 0 current, 1 voltage: `SECOC_KINDS`), SyncFreshness
  (bits 8-39, the low 32 bits of that stream's freshness value), SyncAuthenticator (bits
  40-63); no E2E (the MAC covers every bit). `Decoded.value` is SyncFreshness.

E2E protection (AUTOSAR profile 2) on current, voltage and diagnosis frames: byte 0 is the
CRC-8/AUTOSAR (polynomial 0x2F) over bytes 1..7 followed by one data-ID byte, and
the low nibble of byte 1 is the alive counter. Profile 2 selects the data ID from a
16-entry *DataIDList* indexed by that counter; cantools expects exactly that list on
``message.autosar.e2e.data_ids`` (and ``payload_length`` = protected bytes). Our choice,
deterministic and documented in the DBC (attribute ``E2EDataID`` and the message comment):

    DataIDList[c] = frame_id & 0xFF   for every counter value c

i.e. 0x10+n for current, 0x20+n for voltage, 0x80+n for diagnosis. These 48 values are
pairwise distinct, which is the property that matters: a frame received under the wrong id
(masquerade, mis-routing, a node-number mix-up) fails the CRC for every counter value.
`load_database` checks the DBC attribute against this rule and attaches the list.

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

Freshness synchronisation (`monitor.bus.secoc`, "Resynchronisation"): with a key the database
verifies ``SecOCSync`` frames (``bad_mac``; ``stale_freshness`` for a sync older than the
stream's last accepted value, i.e. a replayed one) and an accepted one sets that stream's
freshness, so a monitor that starts late, restarts, or lost more than the window recovers
at the next sync. A stream not yet synchronised (no sync, no saved state) rejects its data
frames as ``unsynced``. `encode_sync` builds sync frames (sender side, key required);
``db.secoc.save_state`` / ``load_state`` persist the counters across restarts. Without a
key sync frames decode as plain ``sync`` samples, nothing checked.

Decoding never raises: every frame yields `Decoded` or `Rejected` with a reason from
`RejectReason`. Checks run cheapest-first: error/remote/extended flags, id lookup, length,
CRC, reserved bits (unused bits must be 0 -- a non-zero one means the sender uses another
DBC revision, reported as ``malformed``), the SecOC MAC and freshness (with a key), then
the DBC min/max of every signal (NaN fails). An authentic frame consumes its freshness
value even if a range check then rejects it.
"""

from __future__ import annotations

import copy
import math
import re
from collections import Counter as _Tally
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from enum import StrEnum
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Final, Literal, cast, get_args

import cantools.database
from cantools.autosar.end_to_end import apply_profile2_crc, check_profile2_crc
from cantools.database.can import Database, Message, Signal
from cantools.database.can.formats.arxml import (
    AutosarEnd2EndProperties,
    AutosarMessageSpecifics,
)

from monitor.bus.secoc import (
    AUTHENTICATOR_SIGNAL,
    DEFAULT_WINDOW,
    FRESHNESS_SIGNAL,
    SecOC,
    SecOCError,
    SecOCLayout,
    SyncLayout,
    Verdict,
)

if TYPE_CHECKING:
    import can

__all__ = [
    "HEALTH_STATES",
    "KINDS",
    "N_NODES",
    "SECOC_KINDS",
    "CodecError",
    "CounterCheck",
    "CounterOutcome",
    "CounterTracker",
    "Decoded",
    "Kind",
    "MotorDatabase",
    "RejectReason",
    "Rejected",
    "default_dbc_path",
    "e2e_data_id",
    "frame_id",
    "load_database",
]

Kind = Literal["current", "voltage", "truth", "diagnosis", "sync"]
KINDS: Final[tuple[Kind, ...]] = get_args(Kind)
N_NODES: Final = 16
HEALTH_STATES: Final[tuple[str, ...]] = ("fault_free", "fault", "outage", "no_data")
"""`HealthState` names; the index is the raw signal value (the DBC VAL_ table)."""

DEFAULT_DBC_NAME: Final = "motor.dbc"
_FRAME_LENGTH: Final = 8


@dataclass(frozen=True, slots=True)
class _KindSpec:
    prefix: str  # DBC message name prefix, message name is f"{prefix}_N{node}"
    base_id: int  # frame id of node 0
    value_signal: str  # the "main physical value" reported as Decoded.value
    e2e: bool  # CRC in byte 0, counter in the low nibble of byte 1
    secoc: bool = False  # may carry FreshnessValue + Authenticator (monitor.bus.secoc)
    sync: bool = False  # SecOC freshness synchronisation of the secoc kinds (optional)


_SPECS: Final[Mapping[Kind, _KindSpec]] = {
    "current": _KindSpec("MotorCurrent", 0x110, "ArmatureCurrent", True, True),
    "voltage": _KindSpec("MotorVoltage", 0x120, "VoltageCommand", True, True),
    "truth": _KindSpec("SimTruth", 0x7E0, "TrueGamma", False),
    "diagnosis": _KindSpec("MonitorDiagnosis", 0x180, "GammaEstimate", True),
    "sync": _KindSpec("SecOCSync", 0x1F0, "SyncFreshness", False, sync=True),
}
SECOC_KINDS: Final[tuple[Kind, ...]] = tuple(k for k, s in _SPECS.items() if s.secoc)
"""Kinds authenticated when the database has a SecOC key; SyncKind is the index here."""
_NAME_RE: Final = re.compile(r"^(?P<prefix>[A-Za-z]+)_N(?P<node>\d{1,2})$")


class CodecError(ValueError):
    """A DBC that cannot serve the codec, or a value that cannot be encoded (one line)."""


def frame_id(kind: Kind, node: int) -> int:
    """The 11-bit frame id of `kind` for `node` (base id + node)."""
    if kind not in _SPECS:
        raise CodecError(f"unknown message kind {kind!r}; expected one of {KINDS}")
    _check_node(node)
    return _SPECS[kind].base_id + node


def e2e_data_id(arbitration_id: int) -> int:
    """The profile-2 data ID of an E2E-protected frame: ``frame_id & 0xFF`` (all counters)."""
    return arbitration_id & 0xFF


def _check_node(node: int) -> None:
    if not isinstance(node, int) or not 0 <= node < N_NODES:
        raise CodecError(f"node must be an int in 0..{N_NODES - 1}, got {node!r}")


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


_VERDICT_REASON: Final[Mapping[Verdict, RejectReason]] = {
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
    """

    kind: Kind
    node: int
    timestamp: float
    value: float
    counter: int | None
    raw: Mapping[str, float]


@dataclass(frozen=True, slots=True)
class Rejected:
    """A frame that must not reach the estimator, with the reason and what is known."""

    reason: RejectReason
    arbitration_id: int
    timestamp: float
    node: int | None = None
    kind: Kind | None = None
    detail: str = ""


@dataclass(frozen=True, slots=True)
class _Route:
    message: Message
    kind: Kind
    node: int
    data_id: int | None  # None: not E2E protected
    reserved_mask: int  # bits of int.from_bytes(payload, "little") no signal uses
    limits: tuple[tuple[str, float, float], ...]  # (signal, min, max) physical
    value_signal: str
    secoc: SecOCLayout | None = None  # None: the DBC gives this message no SecOC signals
    sync: SyncLayout | None = None  # sync frames only


# ----------------------------------------------------------------------------- database


class MotorDatabase:
    """The motor bus DBC plus a pre-built frame-id routing table for the hot decode path.

    With `secoc_key` (16 or 32 bytes) current and voltage frames are signed on encoding
    and verified on decoding; the object then keeps the freshness counters of every
    (kind, node) stream it sends and receives (see `monitor.bus.secoc`; sending and receiving
    counters are separate), so keep one object for the whole life of a bus connection.
    """

    def __init__(self, db: Database, source: str, secoc_key: bytes | None = None, *,
                 secoc_window: int = DEFAULT_WINDOW) -> None:
        self._db = db
        self.source = source
        self._routes: dict[int, _Route] = _build_routes(db, source)
        self._by_kind: dict[tuple[Kind, int], _Route] = {
            (r.kind, r.node): r for r in self._routes.values()
        }
        self._secoc: SecOC | None = None
        if secoc_key is not None:
            self._secoc = self._new_secoc(secoc_key, secoc_window)

    def _new_secoc(self, key: bytes, window: int) -> SecOC:
        missing = sorted({r.message.name.split("_N")[0] for r in self._routes.values()
                          if r.kind in SECOC_KINDS and r.secoc is None})
        if missing:
            raise CodecError(f"{Path(self.source).name}: {', '.join(missing)} carry no "
                             f"{FRESHNESS_SIGNAL}/{AUTHENTICATOR_SIGNAL}: this DBC cannot "
                             "authenticate (SecOC)")
        if not any(r.kind == "sync" for r in self._routes.values()):
            raise CodecError(f"{Path(self.source).name}: no {_SPECS['sync'].prefix}_N<node> "
                             "messages: this DBC cannot resynchronise SecOC freshness")
        try:
            return SecOC(key, window=window)
        except SecOCError as exc:
            raise CodecError(str(exc)) from None

    def with_secoc_key(self, key: bytes | None, *,
                       window: int = DEFAULT_WINDOW) -> MotorDatabase:
        """A database on the same DBC with its own SecOC key and fresh counters (None: off)."""
        clone = copy.copy(self)
        clone._secoc = None if key is None else self._new_secoc(key, window)
        return clone

    # -- SecOC ------------------------------------------------------------------------

    @property
    def secoc(self) -> SecOC | None:
        """The SecOC signer/verifier (key and freshness counters), None without a key."""
        return self._secoc

    @property
    def secoc_enabled(self) -> bool:
        return self._secoc is not None

    def secoc_layout(self, kind: Kind, node: int) -> SecOCLayout | None:
        """Where the message of `kind` for `node` carries freshness and MAC (None: nowhere)."""
        return self._route(kind, node).secoc

    def sync_layout(self, node: int) -> SyncLayout:
        """The layout of `node`'s SecOC sync frame (`CodecError` if the DBC has none)."""
        layout = self._route("sync", node).sync
        assert layout is not None  # every sync route has one (_build_routes)
        return layout

    # -- lookup ---------------------------------------------------------------------

    def message(self, kind: Kind, node: int) -> Message:
        """The cantools message of `kind` for `node` (cycle time, comments, signals)."""
        return self._route(kind, node).message

    def frame_id(self, kind: Kind, node: int) -> int:
        """The frame id of `kind` for `node`, as in the DBC."""
        return self._route(kind, node).message.frame_id

    def _route(self, kind: Kind, node: int) -> _Route:
        _check_node(node)
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
    ) -> bytes:
        """MonitorDiagnosis payload with counter and E2E CRC.

        `state` is a name from `HEALTH_STATES` or its index; `fault` is gamma*u in volts.
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
        if route.data_id is not None:
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
        if route.data_id is None:
            return payload
        protected = apply_profile2_crc(payload, route.message)
        if protected is None:  # cannot happen for a route built by _build_routes
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
    ) -> Decoded | Rejected:
        """Classify one received frame; never raises (hot path: ~10k frames/s).

        Flags are checked before the id so that an error frame, whose "id" carries error
        class bits, is never misreported as an unknown id.
        """
        if is_error:
            return Rejected(RejectReason.ERROR_FRAME, arbitration_id, timestamp)
        if is_remote:
            return Rejected(RejectReason.REMOTE_FRAME, arbitration_id, timestamp,
                            detail="remote frames carry no data")
        if is_extended:
            return Rejected(RejectReason.EXTENDED_ID, arbitration_id, timestamp,
                            detail=f"29-bit id 0x{arbitration_id:08X}")
        route = self._routes.get(arbitration_id)
        if route is None:
            return Rejected(RejectReason.UNKNOWN_ID, arbitration_id, timestamp,
                            detail=f"not in {self.source}")
        if type(data) is not bytes:
            try:
                data = bytes(data)
            except Exception as exc:  # any object handed in by a driver: report, not raise
                return Rejected(RejectReason.MALFORMED, arbitration_id, timestamp, route.node,
                                route.kind, f"payload is {type(exc).__name__}")
        if len(data) != _FRAME_LENGTH:
            return Rejected(RejectReason.WRONG_LENGTH, arbitration_id, timestamp, route.node,
                            route.kind, f"{len(data)} bytes, expected {_FRAME_LENGTH}")
        message = route.message
        if route.data_id is not None and not check_profile2_crc(data, message):
            return Rejected(RejectReason.BAD_CRC, arbitration_id, timestamp, route.node,
                            route.kind, f"crc 0x{data[0]:02X}, counter {data[1] & 0xF}")
        if int.from_bytes(data, "little") & route.reserved_mask:
            return Rejected(RejectReason.MALFORMED, arbitration_id, timestamp, route.node,
                            route.kind, "reserved bits set")
        if route.secoc is not None and self._secoc is not None:
            failed = self._secoc.verify(route.secoc, (route.kind, route.node), data)
            if failed is not None:
                return Rejected(_VERDICT_REASON[failed[0]], arbitration_id, timestamp,
                                route.node, route.kind, failed[1])
        elif route.sync is not None and self._secoc is not None:
            index = route.sync.kind_index(data)
            if index < len(SECOC_KINDS):  # otherwise out_of_range below, nothing verified
                failed = self._secoc.verify_sync(route.sync, (SECOC_KINDS[index], route.node),
                                                 data)
                if failed is not None:
                    return Rejected(_VERDICT_REASON[failed[0]], arbitration_id, timestamp,
                                    route.node, route.kind, failed[1])
        try:
            signals = cast(
                "dict[str, float]",
                message.decode(data, decode_choices=False, scaling=True,
                               allow_truncated=False, allow_excess=False),
            )
        except Exception as exc:  # decode must never raise; cantools may raise several types
            return Rejected(RejectReason.MALFORMED, arbitration_id, timestamp, route.node,
                            route.kind, f"{type(exc).__name__}: {exc}")
        for name, lo, hi in route.limits:
            v = signals[name]
            if not lo <= v <= hi:  # also catches NaN
                return Rejected(RejectReason.OUT_OF_RANGE, arbitration_id, timestamp,
                                route.node, route.kind, f"{name}={v} not in [{lo}, {hi}]")
        return Decoded(
            route.kind,
            route.node,
            timestamp,
            float(signals[route.value_signal]),
            None if route.data_id is None else int(signals["Counter"]),
            signals,
        )

    def decode_can(self, msg: can.Message) -> Decoded | Rejected:
        """`decode` for a python-can message (flags read from the message, not guessed)."""
        return self.decode(msg.arbitration_id, bytes(msg.data), msg.is_extended_id,
                           msg.is_remote_frame, msg.is_error_frame, msg.timestamp)


def default_dbc_path() -> Path:
    """The DBC shipped in the package (byte-identical to the repository's dbc/motor.dbc)."""
    return Path(str(resources.files("monitor") / "data" / DEFAULT_DBC_NAME))


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
    try:
        db = cantools.database.load_file(p, database_format="dbc", strict=True)
    except FileNotFoundError:
        raise CodecError(f"{p}: file not found") from None
    except OSError as exc:
        raise CodecError(f"{p}: cannot read: {exc.strerror or exc}") from None
    except Exception as exc:  # cantools/textparser raise many types for a bad DBC
        raise CodecError(f"{p}: not a valid DBC: {_one_line(exc)}") from None
    if not isinstance(db, Database):
        raise CodecError(f"{p}: not a CAN database")
    return MotorDatabase(db, str(p), secoc_key, secoc_window=secoc_window)


def _one_line(exc: BaseException, limit: int = 200) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _build_routes(db: Database, source: str) -> dict[int, _Route]:
    """Validate the DBC against the bus scheme and build the id -> route table."""
    name_of = Path(source).name

    def fail(what: str) -> CodecError:
        return CodecError(f"{name_of}: {what}")

    kind_of_prefix = {spec.prefix: kind for kind, spec in _SPECS.items()}
    routes: dict[int, _Route] = {}
    for msg in db.messages:
        m = _NAME_RE.match(msg.name)
        kind = kind_of_prefix.get(m["prefix"]) if m else None
        if m is None or kind is None:
            raise fail(f"unexpected message {msg.name} (0x{msg.frame_id:X}); expected "
                       f"<{'|'.join(kind_of_prefix)}>_N<node>")
        spec = _SPECS[kind]
        node = int(m["node"])
        if node >= N_NODES or msg.frame_id != spec.base_id + node or msg.is_extended_frame:
            raise fail(f"{msg.name} has id 0x{msg.frame_id:X}, expected standard id "
                       f"0x{spec.base_id:X} + node")
        if msg.length != _FRAME_LENGTH:
            raise fail(f"{msg.name} has length {msg.length}, expected {_FRAME_LENGTH}")
        attrs = msg.dbc.attributes if msg.dbc is not None else {}
        if "NodeNumber" not in attrs or attrs["NodeNumber"].value != node:
            raise fail(f"{msg.name}: attribute NodeNumber must be {node}")
        sigs = {s.name: s for s in msg.signals}
        if spec.value_signal not in sigs:
            raise fail(f"{msg.name}: no signal {spec.value_signal}")
        for s in msg.signals:
            if s.is_float:
                raise fail(f"{msg.name}.{s.name}: float signals are not supported")
        data_id: int | None = None
        if spec.e2e:
            crc, cnt = sigs.get("CRC"), sigs.get("Counter")
            if (crc is None or (crc.start, crc.length, crc.byte_order) != (0, 8, "little_endian")
                    or cnt is None
                    or (cnt.start, cnt.length, cnt.byte_order) != (8, 4, "little_endian")):
                raise fail(f"{msg.name}: E2E profile 2 needs CRC in byte 0 and Counter in "
                           "the low nibble of byte 1")
            data_id = e2e_data_id(msg.frame_id)
            if "E2EDataID" not in attrs or attrs["E2EDataID"].value != data_id:
                raise fail(f"{msg.name}: attribute E2EDataID must be {data_id} (id & 0xFF)")
            e2e = AutosarEnd2EndProperties()
            e2e.category = "PROFILE_02"
            e2e.data_ids = [data_id] * 16  # DataIDList indexed by the counter
            e2e.payload_length = _FRAME_LENGTH
            specifics = AutosarMessageSpecifics()
            specifics.e2e = e2e
            msg.autosar = specifics
        secoc = _secoc_layout(msg, spec, fail)
        sync: SyncLayout | None = None
        if spec.sync:
            try:
                sync = SyncLayout.from_message(msg)
            except SecOCError as exc:
                raise fail(str(exc)) from None
            choices = sigs["SyncKind"].choices
            names = {int(k): str(v) for k, v in (choices or {}).items()}
            if names != dict(enumerate(SECOC_KINDS)):
                raise fail(f"{msg.name}: SyncKind VAL_ must be {dict(enumerate(SECOC_KINDS))}")
        if kind == "diagnosis":
            choices = sigs["HealthState"].choices if "HealthState" in sigs else None
            names = {int(k): str(v) for k, v in (choices or {}).items()}
            if names != dict(enumerate(HEALTH_STATES)):
                raise fail(f"{msg.name}: HealthState VAL_ must be "
                           f"{dict(enumerate(HEALTH_STATES))}")
        limits = tuple(
            (s.name, float(s.minimum), float(s.maximum))
            for s in msg.signals
            if s.minimum is not None and s.maximum is not None and not _covers_raw(s)
        )
        routes[msg.frame_id] = _Route(msg, kind, node, data_id, _reserved_mask(msg), limits,
                                      spec.value_signal, secoc, sync)
    present = {r.kind for r in routes.values()}
    for kind, spec in _SPECS.items():
        if spec.sync and kind not in present:
            continue  # an older DBC without sync frames: loads, but cannot take a key
        for node in range(N_NODES):
            if spec.base_id + node not in routes:
                raise fail(f"missing message {spec.prefix}_N{node} "
                           f"(0x{spec.base_id + node:X}, {kind})")
    return routes


def _secoc_layout(
    msg: Message, spec: _KindSpec, fail: Callable[[str], CodecError]
) -> SecOCLayout | None:
    """The SecOC layout of `msg` (attached as ``msg.autosar.secoc``), None if it has none.

    A DBC without the two SecOC signals (an older revision) still loads; it only cannot
    be used with a key. Half a layout, or SecOC signals on other kinds, is an error.
    """
    names = {s.name for s in msg.signals} & {FRESHNESS_SIGNAL, AUTHENTICATOR_SIGNAL}
    if not names:
        return None
    if not spec.secoc:
        raise fail(f"{msg.name}: {' and '.join(sorted(names))} only belong to "
                   f"{' and '.join(s.prefix for s in _SPECS.values() if s.secoc)}")
    try:
        layout = SecOCLayout.from_message(msg)
    except SecOCError as exc:
        raise fail(str(exc)) from None
    if msg.autosar is None:  # cannot happen: SecOC kinds are E2E kinds
        msg.autosar = AutosarMessageSpecifics()
    # cantools has no setter for it (ARXML fills it); set what its SecOC helpers read.
    msg.autosar._secoc = layout.properties()
    return layout


def _covers_raw(signal: Signal) -> bool:
    """True if [min, max] admits every raw value (CRC, Counter): no need to check it."""
    raw_lo = -(1 << (signal.length - 1)) if signal.is_signed else 0
    raw_hi = (1 << (signal.length - (1 if signal.is_signed else 0))) - 1
    ends = [float(cast("float", signal.conversion.raw_to_scaled(raw, False)))
            for raw in (raw_lo, raw_hi)]
    lo, hi = min(ends), max(ends)
    assert signal.minimum is not None and signal.maximum is not None
    return signal.minimum <= lo and hi <= signal.maximum


def _reserved_mask(msg: Message) -> int:
    """Bits (of the little-endian payload integer) that no signal covers.

    Found by letting cantools encode every signal with all raw bits set, so the mask holds
    for either byte order without re-implementing the DBC bit numbering.
    """
    all_ones = {
        s.name: -1 if s.is_signed else (1 << s.length) - 1 for s in msg.signals
    }
    used = int.from_bytes(msg.encode(all_ones, scaling=False, strict=False), "little")
    return ((1 << (8 * msg.length)) - 1) & ~used


# ----------------------------------------------------------------------------- counters


class CounterOutcome(StrEnum):
    """Alive-counter verdict for one frame."""

    OK = "ok"  # first frame of its stream, or counter advanced by exactly 1
    REPEATED = "repeated"  # same counter as the previous frame: duplicate or replay
    JUMP = "jump"  # counter advanced by 2..15: frames lost (mod 16)


@dataclass(frozen=True, slots=True)
class CounterCheck:
    outcome: CounterOutcome
    lost: int = 0  # frames missing before this one (JUMP only), 1..14


class CounterTracker:
    """Per (kind, node) alive-counter supervision of the 4-bit E2E counters.

    A 4-bit counter can only tell losses modulo 16: 16 lost frames look like ``ok``, and
    an old frame replayed later looks like a jump. Timeouts catch the former, the CRC and
    timestamps the rest; this class only classifies and counts.
    """

    def __init__(self) -> None:
        self._last: dict[tuple[Kind, int], int] = {}
        self._counts: dict[tuple[Kind, int], _Tally[CounterOutcome]] = {}
        self._lost: _Tally[tuple[Kind, int]] = _Tally()

    def update(self, kind: Kind, node: int, counter: int) -> CounterCheck:
        """Classify `counter` against the previous one of the same stream and count it."""
        if not isinstance(counter, int) or not 0 <= counter <= 15:
            raise ValueError(f"alive counter must be an int in 0..15, got {counter!r}")
        key = (kind, node)
        last = self._last.get(key)
        self._last[key] = counter
        if last is None:
            check = CounterCheck(CounterOutcome.OK)
        else:
            step = (counter - last) % 16
            if step == 1:
                check = CounterCheck(CounterOutcome.OK)
            elif step == 0:
                check = CounterCheck(CounterOutcome.REPEATED)
            else:
                check = CounterCheck(CounterOutcome.JUMP, step - 1)
                self._lost[key] += step - 1
        self._counts.setdefault(key, _Tally())[check.outcome] += 1
        return check

    def observe(self, sample: Decoded) -> CounterCheck | None:
        """`update` for a decoded frame; None for frames without a counter (truth)."""
        if sample.counter is None:
            return None
        return self.update(sample.kind, sample.node, sample.counter)

    def reset(self, kind: Kind | None = None, node: int | None = None) -> None:
        """Forget the last counter (e.g. after a timeout) so the next frame is ``ok``."""
        for key in list(self._last):
            if self._matches(key, kind, node):
                del self._last[key]

    def counts(self, kind: Kind | None = None, node: int | None = None) -> dict[str, int]:
        """Frames per outcome (all three keys present), summed over the matching streams."""
        total = dict.fromkeys((o.value for o in CounterOutcome), 0)
        for key in self._keys(kind, node):
            for outcome, n in self._counts[key].items():
                total[outcome.value] += n
        return total

    def lost_frames(self, kind: Kind | None = None, node: int | None = None) -> int:
        """Total frames inferred lost by jumps, over the matching streams."""
        return sum(self._lost[key] for key in self._keys(kind, node))

    def _keys(self, kind: Kind | None, node: int | None) -> Iterator[tuple[Kind, int]]:
        return (k for k in self._counts if self._matches(k, kind, node))

    @staticmethod
    def _matches(key: tuple[Kind, int], kind: Kind | None, node: int | None) -> bool:
        return (kind is None or key[0] == kind) and (node is None or key[1] == node)
