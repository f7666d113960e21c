"""The bus scheme: which messages the motor DBC must hold, checked once at load time.

`build_routes` validates a cantools database against the scheme below, attaches to each
protected message the AUTOSAR properties cantools' E2E and SecOC helpers read, and
returns the routes (`monitor.bus.route.Route`, one per frame ID) that `monitor.bus.codec`
decodes with.

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
  transients undershoot 0), FaultEstimate (gamma*u, V, 0.1, +-1000), RuleCount (0..255),
  ModelMismatch (bit 56: the model-mismatch flag beside the state, 0/1), E2E.
* ``sync``      SecOCSync_N<n>, 0x1F0 + n, 1 s per stream, MotorECU -> Monitor, only with
  SecOC on: SyncKind (bits 0-3, VAL_ 0 current, 1 voltage: `SECOC_KINDS`), SyncFreshness
  (bits 8-39, the low 32 bits of that stream's freshness value), SyncAuthenticator (bits
  40-63); no E2E (the MAC covers every bit).

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
`build_routes` checks the DBC attribute against this rule and attaches the list.

SecOC (`monitor.bus.secoc`): the FreshnessValue/Authenticator signals of current and
voltage frames and the sync frames are read into `SecOCLayout` / `SyncLayout`, and the
layout is attached as ``message.autosar.secoc`` for cantools' SecOC helpers. A DBC
without them (an older revision) loads; `check_secoc_capable` says why it cannot take a key.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Final, Literal, cast, get_args

from cantools.database.can import Database, Message, Signal
from cantools.database.can.formats.arxml import (
    AutosarEnd2EndProperties,
    AutosarMessageSpecifics,
)

from monitor.bus.errors import CodecError, SecOCError
from monitor.bus.route import Limit, Route
from monitor.bus.secoc import AUTHENTICATOR_SIGNAL, FRESHNESS_SIGNAL, SecOCLayout, SyncLayout
from monitor.diagnosis.classifier import HealthState

__all__ = [
    "FRAME_LENGTH",
    "HEALTH_STATES",
    "KINDS",
    "N_NODES",
    "SECOC_KINDS",
    "Kind",
    "build_routes",
    "check_node",
    "check_secoc_capable",
    "e2e_data_id",
    "frame_id",
]

Kind = Literal["current", "voltage", "truth", "diagnosis", "sync"]
KINDS: Final[tuple[Kind, ...]] = get_args(Kind)
N_NODES: Final = 16
HEALTH_STATES: Final[tuple[str, ...]] = tuple(s.label for s in HealthState)
"""`HealthState` labels; the index is the raw signal value (the DBC VAL_ table)."""
FRAME_LENGTH: Final = 8


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


def frame_id(kind: Kind, node: int) -> int:
    """The 11-bit frame id of `kind` for `node` (base id + node)."""
    if kind not in _SPECS:
        raise CodecError(f"unknown message kind {kind!r}; expected one of {KINDS}")
    check_node(node)
    return _SPECS[kind].base_id + node


def e2e_data_id(arbitration_id: int) -> int:
    """The profile-2 data ID of an E2E-protected frame: ``frame_id & 0xFF`` (all counters)."""
    return arbitration_id & 0xFF


def check_node(node: int) -> None:
    """`CodecError` unless `node` is a node number (an int in 0..N_NODES-1)."""
    if not isinstance(node, int) or not 0 <= node < N_NODES:
        raise CodecError(f"node must be an int in 0..{N_NODES - 1}, got {node!r}")


_Fail = Callable[[str], CodecError]


def build_routes(db: Database, source: str) -> tuple[Route, ...]:
    """Validate the DBC against the bus scheme and build its routes, in frame-ID order: the
    value signal of a voltage frame is model input 0, that of a current frame the model's
    output, that of a truth frame the true gamma (every factor 1: the DBC is in the model's
    units)."""
    name_of = Path(source).name

    def fail(what: str) -> CodecError:
        return CodecError(f"{name_of}: {what}")

    kind_of_prefix = {spec.prefix: kind for kind, spec in _SPECS.items()}
    routes: dict[int, Route] = {}
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
        if msg.length != FRAME_LENGTH:
            raise fail(f"{msg.name} has length {msg.length}, expected {FRAME_LENGTH}")
        attrs = msg.dbc.attributes if msg.dbc is not None else {}
        if "NodeNumber" not in attrs or attrs["NodeNumber"].value != node:
            raise fail(f"{msg.name}: attribute NodeNumber must be {node}")
        sigs = {s.name: s for s in msg.signals}
        if spec.value_signal not in sigs:
            raise fail(f"{msg.name}: no signal {spec.value_signal}")
        for s in msg.signals:
            if s.is_float:
                raise fail(f"{msg.name}.{s.name}: float signals are not supported")
        data_id = _attach_e2e(msg, sigs, fail) if spec.e2e else None
        secoc = _secoc_layout(msg, spec, fail)
        sync: SyncLayout | None = None
        if spec.sync:
            try:
                sync = SyncLayout.from_message(msg)
            except SecOCError as exc:
                raise fail(str(exc)) from None
            _check_choices(msg, sigs, "SyncKind", SECOC_KINDS, fail)
        if kind == "diagnosis":
            _check_choices(msg, sigs, "HealthState", HEALTH_STATES, fail)
        limits = tuple(
            Limit.of(s.name, float(s.minimum), float(s.maximum))
            for s in msg.signals
            if s.minimum is not None and s.maximum is not None and not _covers_raw(s)
        )
        value = spec.value_signal
        routes[msg.frame_id] = Route(
            msg.frame_id, False, msg, node, kind, FRAME_LENGTH, bool(msg.is_fd),
            data_id is not None, _reserved_mask(msg), limits,
            "Counter" if data_id is not None else None,
            ((0, value, 1.0),) if kind == "voltage" else (),
            ((value, 1.0),) if kind == "current" else (),
            value if kind == "truth" else None, (value, 1.0), secoc, sync)
    present = {r.kind for r in routes.values()}
    for kind, spec in _SPECS.items():
        if spec.sync and kind not in present:
            continue  # an older DBC without sync frames: loads, but cannot take a key
        for node in range(N_NODES):
            if spec.base_id + node not in routes:
                raise fail(f"missing message {spec.prefix}_N{node} "
                           f"(0x{spec.base_id + node:X}, {kind})")
    return tuple(routes[fid] for fid in sorted(routes))


def check_secoc_capable(routes: Iterable[Route], source: str) -> None:
    """`CodecError` unless the DBC behind `routes` can authenticate: SecOC signals on every
    current and voltage message, and sync messages to resynchronise freshness."""
    name_of = Path(source).name
    routes = tuple(routes)
    missing = sorted({r.message.name.split("_N")[0] for r in routes
                      if r.kind in SECOC_KINDS and r.secoc is None})
    if missing:
        raise CodecError(f"{name_of}: {', '.join(missing)} carry no "
                         f"{FRESHNESS_SIGNAL}/{AUTHENTICATOR_SIGNAL}: this DBC cannot "
                         "authenticate (SecOC)")
    if not any(r.kind == "sync" for r in routes):
        raise CodecError(f"{name_of}: no {_SPECS['sync'].prefix}_N<node> "
                         "messages: this DBC cannot resynchronise SecOC freshness")


def _attach_e2e(msg: Message, sigs: Mapping[str, Signal], fail: _Fail) -> int:
    """Check `msg`'s profile-2 layout and E2EDataID; attach the properties cantools' E2E
    helpers read (``msg.autosar.e2e``). Returns the data ID."""
    crc, cnt = sigs.get("CRC"), sigs.get("Counter")
    if (crc is None or (crc.start, crc.length, crc.byte_order) != (0, 8, "little_endian")
            or cnt is None
            or (cnt.start, cnt.length, cnt.byte_order) != (8, 4, "little_endian")):
        raise fail(f"{msg.name}: E2E profile 2 needs CRC in byte 0 and Counter in "
                   "the low nibble of byte 1")
    data_id = e2e_data_id(msg.frame_id)
    attrs = msg.dbc.attributes if msg.dbc is not None else {}
    if "E2EDataID" not in attrs or attrs["E2EDataID"].value != data_id:
        raise fail(f"{msg.name}: attribute E2EDataID must be {data_id} (id & 0xFF)")
    e2e = AutosarEnd2EndProperties()
    e2e.category = "PROFILE_02"
    e2e.data_ids = [data_id] * 16  # DataIDList indexed by the counter
    e2e.payload_length = FRAME_LENGTH
    specifics = AutosarMessageSpecifics()
    specifics.e2e = e2e
    msg.autosar = specifics
    return data_id


def _check_choices(msg: Message, sigs: Mapping[str, Signal], signal: str,
                   names: tuple[str, ...], fail: _Fail) -> None:
    """`signal`'s VAL_ table must name the raw values 0, 1, ... as `names` does."""
    choices = sigs[signal].choices if signal in sigs else None
    found = {int(k): str(v) for k, v in (choices or {}).items()}
    if found != dict(enumerate(names)):
        raise fail(f"{msg.name}: {signal} VAL_ must be {dict(enumerate(names))}")


def _secoc_layout(msg: Message, spec: _KindSpec, fail: _Fail) -> SecOCLayout | None:
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
