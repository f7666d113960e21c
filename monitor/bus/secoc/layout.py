"""Where SecOC puts freshness and MAC in the motor DBC's frames, read from the DBC.

AUTOSAR SecOC appends to an *authentic* PDU a truncated freshness value and a truncated
authenticator (MAC) over ``data ID || authentic PDU || full freshness value``.
`cantools.autosar.secoc` implements that scaffolding for ARXML messages whose
``message.autosar.secoc`` (`AutosarSecOCProperties`) describes it; a DBC has no such
properties. So `SecOCLayout.from_message` builds them from the DBC (signals
``FreshnessValue`` and ``Authenticator``, attributes ``SecOCDataID`` and
``SecOCFreshnessValueLength``) and `monitor.bus.scheme` attaches them to each protected
message at load time, as it does with the E2E data IDs. `SyncLayout` does the same for the
freshness synchronisation frames (`monitor.bus.secoc.engine`, "Resynchronisation").

Layout (dbc/motor.dbc, 8-byte frames, bit numbers of the little-endian payload integer)::

    MotorCurrent  CRC 0-7 | Counter 8-11 | (reserved 12-15) | ArmatureCurrent 16-31 |
                  FreshnessValue 32-39 | Authenticator 40-63
    MotorVoltage  CRC 0-7 | Counter 8-11 | FreshnessValue 12-15 | VoltageCommand 16-39 |
                  Authenticator 40-63

* authenticator = the first 24 bits of AES-CMAC(key, data ID (2 bytes, big-endian) ||
  bytes ``0 .. payload_length-1`` with byte 0 (the E2E CRC) set to 0 || the full 64-bit
  freshness value (big-endian)); the three MAC bytes go to bytes 5..7 in order. This is
  byte for byte what `cantools.autosar.secoc.compute_authenticator` feeds the
  authenticator callback (``u16 data_id, r{8 * payload_length} payload, u64 freshness``).
* MotorCurrent is a textbook secured PDU (24-bit CMAC, 8-bit freshness, as the AUTOSAR
  SecOC profile 1): authentic bytes 0..3, then the freshness byte, then the MAC;
  `cantools.autosar.secoc.apply_authenticator` / ``verify_authenticator`` produce and
  accept exactly these frames (tested).
* MotorVoltage keeps its 24-bit VoltageCommand where it was (an unprotected sender's
  frames must not change), so only bytes 5..7 plus the high nibble of byte 1 are free:
  the MAC takes bytes 5..7 and the 4 freshness bits ride in byte 1, *inside* the
  authentic bytes 0..4. cantools' trailer (freshness bits then MAC bits after the
  payload) cannot express that -- it would need 28 bits after byte 5, and a 0-bit
  trailer freshness is not a valid bitstruct format -- so the frames are built here with
  the same authenticator input. (The hot path is built here for both kinds anyway:
  cantools' ``verify_authenticator`` compiles bitstruct format strings on every call and
  costs about 13 us per frame, `SecOC.verify` about 1.4 us, of which the CMAC -- copied
  from a keyed prototype instead of re-keyed, 0.3 against 1.4 us -- is the smaller part.)
* E2E over SecOC: the sender writes freshness and MAC first and the E2E profile 2 CRC
  last, over everything (bytes 1..7, so also over the MAC); the receiver checks the CRC
  first (cheap, catches corruption), then the MAC. The CRC byte is the one byte the MAC
  does not cover: it is computed after the MAC. The E2E alive counter (byte 1) is
  covered by the MAC, but it is a separate mechanism (loss and duplicate detection,
  4 bits); the freshness counter is what defeats replays.

Sync frames (``SecOCSync_N<n>``)::

    SecOCSync     SyncKind 0-3 (0 MotorCurrent, 1 MotorVoltage) | (reserved 4-7) |
                  SyncFreshness 8-39 | SyncAuthenticator 40-63
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from cantools.database.can.formats.arxml import AutosarSecOCProperties

from monitor.bus.errors import SecOCError

if TYPE_CHECKING:
    from cantools.database.can import Message, Signal

__all__ = [
    "AUTHENTICATOR_SIGNAL",
    "AUTH_ALGORITHM",
    "DATA_ID_ATTRIBUTE",
    "FRESHNESS_ALGORITHM",
    "FRESHNESS_LENGTH_ATTRIBUTE",
    "FRESHNESS_SIGNAL",
    "SYNC_AUTHENTICATOR_SIGNAL",
    "SYNC_FRESHNESS_SIGNAL",
    "SYNC_KIND_SIGNAL",
    "SecOCLayout",
    "SyncLayout",
]

AUTH_ALGORITHM: Final = "AES-CMAC"
FRESHNESS_ALGORITHM: Final = "monotonic counter per message, low bits sent, window 64"
FRESHNESS_SIGNAL: Final = "FreshnessValue"
AUTHENTICATOR_SIGNAL: Final = "Authenticator"
DATA_ID_ATTRIBUTE: Final = "SecOCDataID"
FRESHNESS_LENGTH_ATTRIBUTE: Final = "SecOCFreshnessValueLength"
SYNC_KIND_SIGNAL: Final = "SyncKind"
SYNC_FRESHNESS_SIGNAL: Final = "SyncFreshness"
SYNC_AUTHENTICATOR_SIGNAL: Final = "SyncAuthenticator"


@dataclass(frozen=True, slots=True)
class SecOCLayout:
    """Where SecOC puts its values in one DBC message, and what the MAC covers.

    `payload_length` bytes from the start of the frame are authenticated (with
    `crc_byte`, byte 0 -- the E2E CRC, written after the MAC -- as 0); `fv_start`/`fv_bits`
    locate the sent freshness bits in the little-endian payload integer; the MAC bytes are
    ``auth_start .. auth_start + auth_bytes - 1``. `trailer` is True when the freshness byte
    sits right between the authentic bytes and the MAC (cantools' secured-PDU layout).
    """

    name: str
    data_id: int
    payload_length: int
    freshness_bits: int
    fv_start: int
    fv_bits: int
    auth_start: int
    auth_bytes: int
    trailer: bool
    crc_byte: bool = True

    @property
    def fv_modulus(self) -> int:
        return 1 << self.fv_bits

    @classmethod
    def from_message(cls, msg: Message) -> SecOCLayout:
        """Read the layout of our bus's DBC from `msg`'s signals ``FreshnessValue`` and
        ``Authenticator`` and its attributes (`from_signals` has the rules): SecOCDataID
        must be the frame id, SecOCFreshnessValueLength the full freshness length. The E2E
        CRC is in byte 0. `SecOCError` if unusable."""
        sigs = {s.name: s for s in msg.signals}
        fv, auth = sigs.get(FRESHNESS_SIGNAL), sigs.get(AUTHENTICATOR_SIGNAL)
        if fv is None or auth is None:
            raise SecOCError(f"{msg.name}: needs signals {FRESHNESS_SIGNAL} and "
                             f"{AUTHENTICATOR_SIGNAL} for SecOC")
        return cls.from_signals(msg, fv, auth, data_id=msg.frame_id,
                                freshness_bits=_freshness_length(msg, msg.name, fv.length),
                                crc_byte=True)

    @classmethod
    def from_signals(cls, msg: Message, fv: Signal, auth: Signal, *, data_id: int,
                     freshness_bits: int, crc_byte: bool) -> SecOCLayout:
        """The layout of `msg` whose truncated freshness is signal `fv` and MAC `auth`, for
        a 16-bit `data_id` and a full freshness of `freshness_bits` (a multiple of 8, no
        shorter than `fv`); `crc_byte`: byte 0 is an E2E CRC, written after the MAC and
        so not authenticated. `SecOCError` if unusable.

        Rules: both signals little-endian and unsigned; the authenticator byte-aligned, a
        whole number of bytes, ending the frame; the freshness either 8 bits right before
        it (cantools' trailer) or entirely inside the bytes before it (after the CRC byte),
        which are then all authenticated. Either way every bit except the CRC byte and the
        MAC is covered by the MAC.
        """
        where = msg.name
        _check_signals(where, msg.length, (fv,), auth)
        if not 1 <= fv.length <= 16:
            raise SecOCError(f"{where}.{fv.name}: must be 1..16 bits")
        trailer = fv.start + fv.length == auth.start and fv.start % 8 == 0
        if trailer:
            if fv.length != 8:
                raise SecOCError(f"{where}.{fv.name}: right before the {auth.name} it must "
                                 f"be one byte")
            payload_length = fv.start // 8
        else:
            payload_length = auth.start // 8
            first = 8 if crc_byte else 0
            if fv.start < first or fv.start + fv.length > auth.start:
                raise SecOCError(f"{where}.{fv.name}: must lie in bytes {first // 8}.."
                                 f"{payload_length - 1} or right before the {auth.name}")
        if crc_byte and payload_length < 1:
            raise SecOCError(f"{where}: no authentic bytes after the CRC byte")
        _check_stream(where, data_id, freshness_bits, fv.length)
        return cls(
            name=msg.name,
            data_id=data_id,
            payload_length=payload_length,
            freshness_bits=freshness_bits,
            fv_start=fv.start,
            fv_bits=fv.length,
            auth_start=auth.start // 8,
            auth_bytes=auth.length // 8,
            trailer=trailer,
            crc_byte=crc_byte,
        )

    def properties(self) -> AutosarSecOCProperties:
        """cantools' description of this layout (for ``message.autosar.secoc``).

        `compute_authenticator` uses data_id, payload_length and freshness_bit_length and
        is valid for every layout; `apply_authenticator` / `verify_authenticator`
        additionally place freshness_tx bits and auth_tx bits after the payload, which is
        this layout only when `trailer`.
        """
        return AutosarSecOCProperties(
            auth_algorithm_name=AUTH_ALGORITHM,
            freshness_algorithm_name=FRESHNESS_ALGORITHM,
            payload_length=self.payload_length,
            data_id=self.data_id,
            auth_tx_bit_length=8 * self.auth_bytes,
            freshness_bit_length=self.freshness_bits,
            freshness_tx_bit_length=self.fv_bits,
        )


@dataclass(frozen=True, slots=True)
class SyncLayout:
    """Where a freshness synchronisation (``SecOCSync``) frame puts its values.

    Bytes ``0 .. payload_length - 1`` (everything before the MAC; there is no CRC byte)
    are authenticated. `kind_start`/`kind_bits` locate SyncKind (which stream: the
    receiver maps it), `fv_start`/`fv_bits` the sent low bits of the freshness value,
    all in the little-endian payload integer; the MAC bytes are ``auth_start ..
    auth_start + auth_bytes - 1``.
    """

    name: str
    data_id: int
    payload_length: int
    freshness_bits: int
    kind_start: int
    kind_bits: int
    fv_start: int
    fv_bits: int
    auth_start: int
    auth_bytes: int

    @classmethod
    def from_message(cls, msg: Message) -> SyncLayout:
        """Read the layout of our bus's DBC from `msg`'s signals SyncKind, SyncFreshness and
        SyncAuthenticator and its attributes (`from_signals` has the rules): SecOCDataID
        must be the frame id, SecOCFreshnessValueLength the full freshness length.
        `SecOCError` if unusable."""
        sigs = {s.name: s for s in msg.signals}
        names = (SYNC_KIND_SIGNAL, SYNC_FRESHNESS_SIGNAL, SYNC_AUTHENTICATOR_SIGNAL)
        if any(n not in sigs for n in names):
            raise SecOCError(f"{msg.name}: needs signals {', '.join(names)} for SecOC sync")
        kind, fv, auth = (sigs[n] for n in names)
        return cls.from_signals(msg, kind, fv, auth, data_id=msg.frame_id,
                                freshness_bits=_freshness_length(msg, msg.name, fv.length))

    @classmethod
    def from_signals(cls, msg: Message, kind: Signal, fv: Signal, auth: Signal, *,
                     data_id: int, freshness_bits: int) -> SyncLayout:
        """The layout of sync message `msg` whose stream index is signal `kind`, low
        freshness bits `fv` and MAC `auth`, for a 16-bit `data_id` and a full freshness of
        `freshness_bits`. `SecOCError` if unusable.

        Rules: the three are unsigned little-endian integers; the freshness 16..64 bits;
        the authenticator whole bytes (8..64 bits) ending the frame, the other two before
        it (so covered by the MAC).
        """
        where = msg.name
        _check_signals(where, msg.length, (kind, fv), auth)
        if not 16 <= fv.length <= 64:
            raise SecOCError(f"{where}.{fv.name}: must be 16..64 bits")
        for s in (kind, fv):
            if s.start + s.length > auth.start:
                raise SecOCError(f"{where}.{s.name}: must lie before the {auth.name}")
        _check_stream(where, data_id, freshness_bits, fv.length)
        return cls(
            name=msg.name,
            data_id=data_id,
            payload_length=auth.start // 8,
            freshness_bits=freshness_bits,
            kind_start=kind.start,
            kind_bits=kind.length,
            fv_start=fv.start,
            fv_bits=fv.length,
            auth_start=auth.start // 8,
            auth_bytes=auth.length // 8,
        )

    def kind_index(self, frame: bytes) -> int:
        """The raw SyncKind of `frame` (which stream it synchronises)."""
        return (int.from_bytes(frame, "little") >> self.kind_start) & ((1 << self.kind_bits) - 1)


def _check_signals(where: str, frame_bytes: int, fields: tuple[Signal, ...],
                   auth: Signal) -> None:
    """SecOC signals are unsigned little-endian integers; the authenticator fills the last
    whole bytes of the frame (8..64 bits)."""
    for s in (*fields, auth):
        if s.byte_order != "little_endian" or s.is_signed or s.is_float:
            raise SecOCError(f"{where}.{s.name}: must be an unsigned little-endian integer")
    if (auth.start % 8 or auth.length % 8 or not 8 <= auth.length <= 64
            or auth.start + auth.length != 8 * frame_bytes):
        raise SecOCError(f"{where}.{auth.name}: must be whole bytes (8..64 bits) at the end of "
                         f"the frame")


def _freshness_length(msg: Message, where: str, truncated_bits: int) -> int:
    """Check a message's SecOC DBC attributes; return the full freshness length in bits.

    The data ID must be the frame ID, and the freshness value a whole number of bytes no
    shorter than the truncated value carried on the wire.
    """
    attrs = msg.dbc.attributes if msg.dbc is not None else {}
    if DATA_ID_ATTRIBUTE not in attrs or attrs[DATA_ID_ATTRIBUTE].value != msg.frame_id:
        raise SecOCError(f"{where}: attribute {DATA_ID_ATTRIBUTE} must be "
                         f"{msg.frame_id} (the frame id)")
    n_fresh = attrs[FRESHNESS_LENGTH_ATTRIBUTE].value if (
        FRESHNESS_LENGTH_ATTRIBUTE in attrs) else None
    if not isinstance(n_fresh, int) or not _valid_freshness_bits(n_fresh, truncated_bits):
        raise SecOCError(f"{where}: attribute {FRESHNESS_LENGTH_ATTRIBUTE} must be a "
                         f"multiple of 8 in {truncated_bits}..64, got {n_fresh!r}")
    return n_fresh


def _valid_freshness_bits(n_fresh: int, truncated_bits: int) -> bool:
    """A full freshness value is whole bytes, no shorter than what the wire carries."""
    return n_fresh % 8 == 0 and truncated_bits <= n_fresh <= 64


def _check_stream(where: str, data_id: int, n_fresh: int, truncated_bits: int) -> None:
    """A layout's stream: a 16-bit data ID and a usable full freshness length."""
    if not _valid_freshness_bits(n_fresh, truncated_bits):
        raise SecOCError(f"{where}: the full freshness length must be a multiple of 8 in "
                         f"{truncated_bits}..64, got {n_fresh}")
    if not 0 <= data_id <= 0xFFFF:
        raise SecOCError(f"{where}: the SecOC data ID must be 16 bits, got {data_id}")
