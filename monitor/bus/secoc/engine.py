"""SecOC-style authentication of the ECU frames: truncated AES-CMAC and freshness counters.

AUTOSAR SecOC appends to an *authentic* PDU a truncated freshness value and a truncated
authenticator (MAC) over ``data ID || authentic PDU || full freshness value``.
`cantools.autosar.secoc` implements that scaffolding for ARXML messages whose
``message.autosar.secoc`` (`AutosarSecOCProperties`) describes it; a DBC has no such
properties. So `SecOCLayout.from_message` builds them from the DBC (signals
``FreshnessValue`` and ``Authenticator``, attributes ``SecOCDataID`` and
``SecOCFreshnessValueLength``) and `monitor.bus.codec` attaches them to each protected message
at load time, as it does with the E2E data IDs.

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

Freshness: one 64-bit counter per message stream (kind, node) on each side. The sender
increments it before every frame (the first frame carries 1) and sends its low bits.
The receiver keeps the last accepted value L and reconstructs the candidates
``v = L + d, L + d + 2^n, ...`` (d = the sent bits minus L, mod 2^n, in 1..2^n) up to
``L + window`` (default 64: one candidate for MotorCurrent's 8 bits, at most four for
MotorVoltage's 4 bits); the first one whose MAC matches is accepted and becomes L. A
frame whose MAC matches no candidate is rejected: as ``stale_freshness`` when it
verifies at a value not after L (a replay of one of the last `window` frames) or just
beyond the window (an authentic frame from too far ahead), otherwise as ``bad_mac``
(forged, corrupted past the CRC, unsigned, or replayed from too long ago to tell). These
classification MACs are only computed for frames that are rejected anyway.

Resynchronisation (an AUTOSAR-like freshness value manager with sync messages): the
sender also signs one ``SecOCSync_N<n>`` frame (0x1F0 + n, `SyncLayout`) per stream when it
starts, before its first data frame, and then once per second::

    SecOCSync     SyncKind 0-3 (0 MotorCurrent, 1 MotorVoltage) | (reserved 4-7) |
                  SyncFreshness 8-39 | SyncAuthenticator 40-63

* SyncFreshness = the low 32 bits of the stream's freshness value F (the value of the
  last frame signed on it, 0 before the first); SyncAuthenticator = the first 24 bits of
  AES-CMAC(key, sync data ID (its frame id, 2 bytes big-endian) || bytes 0..4 of the
  frame || F as 8 bytes big-endian), in bytes 5..7. The data ID differs from every data
  frame's, so no data-frame MAC is a sync MAC; the kind is authenticated, so a current
  sync cannot pass as a voltage one.
* No E2E CRC or alive counter: 8 + 4 bits do not fit beside 4 + 32 + 24, and the MAC
  covers every bit (a random corruption passes it with probability 2^-24, a CRC-8 with
  2^-8). A forged sync passes with probability 2^-24 per attempt (about 8 million frames,
  over half an hour of a saturated 500 kbit/s bus, counted as ``bad_mac``). What a
  successful forgery can do: move the stream's freshness *forward* (never back), so that
  the genuine frames are rejected until the sender's counter passes the forged value --
  a denial of service of that stream, which a saved state keeps across restarts (delete
  the state file or change the key). It never lets a forged or replayed data frame in.
* The receiver supplies the high 32 bits: of the values with the sent low 32 bits, the
  one nearest its own value L (`nearest_freshness`). So the high half is taken as
  unchanged unless the low half wrapped, i.e. lies more than 2^31 below L's low half (then
  it is one more); an old sync from before a wrap (more than 2^31 above) resolves into
  the past. 2^32 frames last 497 days at 100 Hz, 2^31 248 days. The MAC covers all 64 bits,
  so a wrong guess is rejected (``bad_mac``), never accepted. Limit: a receiver 2^31 or
  more behind the sender -- a monitor without a state file on a stream that has sent
  2^31 frames under the key, or a state file that old -- cannot place the sync: change
  the key before that (the counters restart) or keep the state file current.

Receiver rules, per stream (`SecOC.verify_sync`, `SecOC.verify`):

1. A sync whose MAC verifies at a value V >= L sets L = V (so the next data frame, V + 1,
   is in the window); V < L is a replayed sync and rejected as ``stale_freshness`` (L
   never moves backwards). V = L is accepted and changes nothing.
2. A stream with no L -- nothing accepted since start and no saved state -- rejects data
   frames as ``unsynced`` until a sync arrives. **Trust on first use:** on the very first
   start without a state file the first sync with a valid MAC is believed, even one
   recorded earlier and replayed now; such a replay (and the data frames recorded after
   it) can be accepted until the sender's next genuine sync, at most about a second
   later, moves L past all of them.
3. `import_state` / `load_state` restore each stream's last accepted value as L, a
   *floor*: data frames in the window after it are accepted at once (a quick restart
   continues without waiting for a sync), a sync below it is a replay (an old sync
   recorded before the restart cannot roll the freshness back). Until the stream is
   synchronised again (a sync, or a frame in the window), frames that do not fit are
   ``unsynced`` rather than ``bad_mac``: the sender may simply have moved on. The
   exposure of a crash: frames accepted after the last `save_state` (at most `window`
   of them count: the ones in the window after the floor) can be replayed once after the
   restart, until the sender's next genuine frame or sync moves L past them. Save often
   (every few seconds) and at exit.
4. A stream that lost more than `window` consecutive frames (or any gap) recovers at the
   next sync, at most a second later.

The sender's counters must never go back under a key: a sender that restarts without its
state (`export_state` includes the sending counters; `import_state(tx_margin=...)` skips
ahead past what it may have signed after its last save) would reuse freshness values, and
its syncs would be rejected as replays until its counter passes the receiver's.

Persistence: `SecOC.save_state` writes the counters atomically (temporary file, fsync,
`os.replace`, mode 0600); `SecOC.load_state` reads them back (a missing file is a fresh
start; anything malformed, or a file others may write, is one `SecOCError` line).

Keys: `load_key` reads an AES-128/256 key from a file only its owner can access.
"""

from __future__ import annotations

import contextlib
import enum
import hmac
import json
import os
import re
import stat
import tempfile
from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

from cantools.database.can.formats.arxml import AutosarSecOCProperties
from cryptography.hazmat.primitives.ciphers import algorithms
from cryptography.hazmat.primitives.cmac import CMAC

if TYPE_CHECKING:
    from cantools.database.can import Message

__all__ = [
    "AUTH_ALGORITHM",
    "DEFAULT_WINDOW",
    "FRESHNESS_ALGORITHM",
    "KEY_LENGTHS",
    "SecOC",
    "SecOCError",
    "SecOCLayout",
    "SyncLayout",
    "Verdict",
    "aes_cmac",
    "load_key",
    "nearest_freshness",
    "parse_key",
]

KEY_LENGTHS: Final[tuple[int, ...]] = (16, 32)
"""AES-128 and AES-256 key lengths in bytes."""
DEFAULT_WINDOW: Final = 64
"""Accept a freshness value at most this far ahead of the last accepted one."""
AUTH_ALGORITHM: Final = "AES-CMAC"
FRESHNESS_ALGORITHM: Final = "monotonic counter per message, low bits sent, window 64"
FRESHNESS_SIGNAL: Final = "FreshnessValue"
AUTHENTICATOR_SIGNAL: Final = "Authenticator"
DATA_ID_ATTRIBUTE: Final = "SecOCDataID"
FRESHNESS_LENGTH_ATTRIBUTE: Final = "SecOCFreshnessValueLength"
SYNC_KIND_SIGNAL: Final = "SyncKind"
SYNC_FRESHNESS_SIGNAL: Final = "SyncFreshness"
SYNC_AUTHENTICATOR_SIGNAL: Final = "SyncAuthenticator"
STATE_FORMAT: Final = "motor-monitor SecOC freshness state"
STATE_VERSION: Final = 1
_MAX_STATE_FILE: Final = 1 << 20
_STATE_KEY: Final = re.compile(r"^(?P<dir>rx|tx)/(?P<kind>[a-z][a-z0-9_]*)/(?P<node>\d{1,5})$")
_MAX_KEY_FILE: Final = 4096
_HEX_DIGITS: Final = frozenset(b"0123456789abcdefABCDEF")
_TEXT: Final = frozenset(range(0x20, 0x7F)) | frozenset(b"\t\n\r")




def _check_signals(where: str, frame_bytes: int, fields: tuple[Any, ...], auth: Any) -> None:
    """SecOC signals are unsigned little-endian integers; the authenticator fills the last
    whole bytes of the frame (8..64 bits)."""
    for s in (*fields, auth):
        if s.byte_order != "little_endian" or s.is_signed or s.is_float:
            raise SecOCError(f"{where}.{s.name}: must be an unsigned little-endian integer")
    if (auth.start % 8 or auth.length % 8 or not 8 <= auth.length <= 64
            or auth.start + auth.length != 8 * frame_bytes):
        raise SecOCError(f"{where}.{auth.name}: must be whole bytes (8..64 bits) at the end of "
                         f"the frame")

def _freshness_length(msg: Any, where: str, truncated_bits: int) -> int:
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
    if not isinstance(n_fresh, int) or n_fresh % 8 or not truncated_bits <= n_fresh <= 64:
        raise SecOCError(f"{where}: attribute {FRESHNESS_LENGTH_ATTRIBUTE} must be a "
                         f"multiple of 8 in {truncated_bits}..64, got {n_fresh!r}")
    return n_fresh

class SecOCError(ValueError):
    """A key, key file or SecOC layout that cannot be used; the message is one line."""


# ----------------------------------------------------------------------------- keys


def parse_key(data: bytes, where: str = "key") -> bytes:
    """An AES key from 32 or 64 hex digits (surrounding whitespace ignored) or 16/32 raw bytes.

    Content that is all printable text is read as hex only (so a mistyped hex key is an
    error, not 32 raw bytes); random raw keys are text with probability about 1e-14.
    """
    text = data.strip()
    if len(text) in (32, 64) and all(b in _HEX_DIGITS for b in text):
        return bytes.fromhex(text.decode("ascii"))
    if len(data) in KEY_LENGTHS and not all(b in _TEXT for b in data):
        return bytes(data)
    raise SecOCError(
        f"{where}: not an AES key: expected 32 or 64 hex digits (AES-128/256) or 16 or 32 "
        f"raw bytes, got {len(data)} bytes"
    )


def load_key(path: str | os.PathLike[str], *, allow_insecure: bool = False) -> bytes:
    """Read an AES-128/256 key for SecOC from `path` (format: `parse_key`).

    The file must be a regular file that neither its group nor others can access
    (``mode & 0o077 == 0``, e.g. ``chmod 600``) unless `allow_insecure`. Every problem is
    one `SecOCError` line; the key itself never appears in a message.
    """
    p = Path(path)
    try:
        fd = os.open(p, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise SecOCError(f"{p}: key file not found") from None
    except OSError as exc:
        raise SecOCError(f"{p}: cannot read key file: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)  # the file we opened, not whatever the path names by now
        if not stat.S_ISREG(st.st_mode):
            raise SecOCError(f"{p}: key file is not a regular file")
        mode = stat.S_IMODE(st.st_mode)
        if mode & 0o077 and not allow_insecure:
            raise SecOCError(
                f"{p}: key file is accessible by group or others (mode {mode:04o}); "
                f"make it readable only by the service (chmod 600)"
            )
        chunks: list[bytes] = []
        size = 0
        while size <= _MAX_KEY_FILE and (chunk := os.read(fd, _MAX_KEY_FILE + 1 - size)):
            chunks.append(chunk)
            size += len(chunk)
    except OSError as exc:
        raise SecOCError(f"{p}: cannot read key file: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    return parse_key(b"".join(chunks), str(p))


# ----------------------------------------------------------------------------- CMAC


def _check_key(key: bytes) -> bytes:
    if not isinstance(key, bytes | bytearray) or len(key) not in KEY_LENGTHS:
        got = f"{len(key)} bytes" if isinstance(key, bytes | bytearray) else type(key).__name__
        raise SecOCError(f"SecOC key must be 16 or 32 bytes (AES-128/256), got {got}")
    return bytes(key)


def aes_cmac(key: bytes, data: bytes) -> bytes:
    """The full 16-byte AES-CMAC (RFC 4493 / NIST SP 800-38B) of `data` under `key`."""
    mac = CMAC(algorithms.AES(_check_key(key)))
    mac.update(data)
    return mac.finalize()


# ----------------------------------------------------------------------------- layout


@dataclass(frozen=True, slots=True)
class SecOCLayout:
    """Where SecOC puts its values in one DBC message, and what the MAC covers.

    `payload_length` bytes from the start of the frame are authenticated (byte 0, the
    E2E CRC, as 0); `fv_start`/`fv_bits` locate the sent freshness bits in the
    little-endian payload integer; the MAC bytes are ``auth_start .. auth_start +
    auth_bytes - 1``. `trailer` is True when the freshness byte sits right between the
    authentic bytes and the MAC (cantools' secured-PDU layout).
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

    @property
    def fv_modulus(self) -> int:
        return 1 << self.fv_bits

    @classmethod
    def from_message(cls, msg: Message) -> SecOCLayout:
        """Read the layout from `msg`'s signals and attributes; `SecOCError` if unusable.

        Rules: both signals little-endian and unsigned; the Authenticator byte-aligned, a
        whole number of bytes, ending the frame; the FreshnessValue either 8 bits right
        before it (cantools' trailer) or entirely inside the bytes before it, which are
        then all authenticated. Either way every bit except the CRC byte and the MAC is
        covered by the MAC. SecOCDataID must be the frame id (16 bits), the full
        freshness length a multiple of 8 in fv_bits..64.
        """
        where = msg.name
        sigs = {s.name: s for s in msg.signals}
        fv, auth = sigs.get(FRESHNESS_SIGNAL), sigs.get(AUTHENTICATOR_SIGNAL)
        if fv is None or auth is None:
            raise SecOCError(f"{where}: needs signals {FRESHNESS_SIGNAL} and "
                             f"{AUTHENTICATOR_SIGNAL} for SecOC")
        _check_signals(where, msg.length, (fv,), auth)
        if not 1 <= fv.length <= 16:
            raise SecOCError(f"{where}.{FRESHNESS_SIGNAL}: must be 1..16 bits")
        trailer = fv.start + fv.length == auth.start and fv.start % 8 == 0
        if trailer:
            if fv.length != 8:
                raise SecOCError(f"{where}.{FRESHNESS_SIGNAL}: right before the "
                                 f"{AUTHENTICATOR_SIGNAL} it must be one byte")
            payload_length = fv.start // 8
        else:
            payload_length = auth.start // 8
            if fv.start < 8 or fv.start + fv.length > auth.start:
                raise SecOCError(f"{where}.{FRESHNESS_SIGNAL}: must lie in bytes 1.."
                                 f"{payload_length - 1} or right before the "
                                 f"{AUTHENTICATOR_SIGNAL}")
        n_fresh = _freshness_length(msg, where, fv.length)
        return cls(
            name=msg.name,
            data_id=msg.frame_id,
            payload_length=payload_length,
            freshness_bits=n_fresh,
            fv_start=fv.start,
            fv_bits=fv.length,
            auth_start=auth.start // 8,
            auth_bytes=auth.length // 8,
            trailer=trailer,
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
        """Read the layout from `msg`'s signals and attributes; `SecOCError` if unusable.

        Rules: SyncKind, SyncFreshness (16..64 bits) and SyncAuthenticator unsigned
        little-endian integers; the authenticator whole bytes (8..64 bits) ending the
        frame, the other two before it (so covered by the MAC). SecOCDataID must be the
        frame id, SecOCFreshnessValueLength a multiple of 8 in fv_bits..64.
        """
        where = msg.name
        sigs = {s.name: s for s in msg.signals}
        names = (SYNC_KIND_SIGNAL, SYNC_FRESHNESS_SIGNAL, SYNC_AUTHENTICATOR_SIGNAL)
        if any(n not in sigs for n in names):
            raise SecOCError(f"{where}: needs signals {', '.join(names)} for SecOC sync")
        kind, fv, auth = (sigs[n] for n in names)
        _check_signals(where, msg.length, (kind, fv), auth)
        if not 16 <= fv.length <= 64:
            raise SecOCError(f"{where}.{SYNC_FRESHNESS_SIGNAL}: must be 16..64 bits")
        for s in (kind, fv):
            if s.start + s.length > auth.start:
                raise SecOCError(f"{where}.{s.name}: must lie before the "
                                 f"{SYNC_AUTHENTICATOR_SIGNAL}")
        n_fresh = _freshness_length(msg, where, fv.length)
        return cls(
            name=msg.name,
            data_id=msg.frame_id,
            payload_length=auth.start // 8,
            freshness_bits=n_fresh,
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


def nearest_freshness(reference: int, sent: int, bits: int, top_bits: int = 64) -> int:
    """The freshness value with low `bits` = `sent` nearest to `reference`.

    Candidates are taken from ``[reference - 2^(bits-1), reference + 2^(bits-1))``: the
    high part of `reference` unless the low part wrapped (`sent` more than half the range
    below reference's low part: one more) or is from before a wrap (more than half the
    range above: one less). Clamped to ``0 .. 2^top_bits - 1``.
    """
    m = 1 << bits
    d = (sent - reference) % m
    v = reference + d if d < m >> 1 else reference + d - m
    if v < 0:
        v += m
    elif v >> top_bits:
        v -= m
    return v


# ----------------------------------------------------------------------------- engine


class Verdict(enum.Enum):
    """Why `SecOC.verify` refused a frame."""

    BAD_MAC = "bad_mac"
    STALE_FRESHNESS = "stale_freshness"
    UNSYNCED = "unsynced"


class SecOC:
    """Signs and verifies frames under one key; keeps the freshness counters per stream.

    A stream is any hashable name of a message stream, e.g. ``("current", 3)``; sending
    and receiving counters are separate, so one object may do both (a demo sends and
    monitors in one process). Only streams named ``(kind, node)`` (a lower-case word and
    an int) can be exported and saved. Not thread-safe per stream: one sender and one
    receiver per stream (`export_state` / `save_state` may run in another thread).
    """

    def __init__(self, key: bytes, *, window: int = DEFAULT_WINDOW) -> None:
        if isinstance(window, bool) or not isinstance(window, int) or window < 1:
            raise SecOCError(f"freshness window must be a positive int, got {window!r}")
        # A keyed prototype: copy() skips the AES key schedule for every frame.
        self._proto = CMAC(algorithms.AES(_check_key(key)))
        self.key_bits = 8 * len(key)
        self.window = window
        self._tx: dict[Hashable, int] = {}
        self._rx: dict[Hashable, int] = {}
        # Streams synchronised since this object was made (a sync or an accepted frame,
        # or set_rx_freshness); the others in _rx hold only a floor from import_state.
        self._synced: set[Hashable] = set()
        self._prefix: dict[int, bytes] = {}

    # -- primitives -----------------------------------------------------------------

    def cmac(self, data: bytes) -> bytes:
        """The full 16-byte AES-CMAC of `data` under this key."""
        mac = self._proto.copy()
        mac.update(data)
        return mac.finalize()

    def authenticator_fn(self) -> Callable[[Message, bytes, int], bytes]:
        """This key as the authenticator callback of `cantools.autosar.secoc`.

        cantools passes the assembled ``data ID || payload || freshness`` and truncates
        the returned full CMAC to ``auth_tx_bit_length`` bits itself.
        """

        def authenticate(_msg: Message, auth_data: bytes, _freshness: int) -> bytes:
            return self.cmac(bytes(auth_data))

        return authenticate

    def auth_data(self, layout: SecOCLayout, frame: bytes, freshness: int) -> bytes:
        """The CMAC input: data ID || authentic bytes (CRC byte as 0) || full freshness."""
        prefix = self._prefix.get(layout.data_id)
        if prefix is None:
            prefix = self._prefix[layout.data_id] = layout.data_id.to_bytes(2, "big") + b"\0"
        return (prefix + frame[1:layout.payload_length]
                + freshness.to_bytes(layout.freshness_bits // 8, "big"))

    def authenticator(self, layout: SecOCLayout, frame: bytes, freshness: int) -> bytes:
        """The truncated MAC (`layout.auth_bytes` bytes) of `frame` at `freshness`."""
        return self.cmac(self.auth_data(layout, frame, freshness))[:layout.auth_bytes]

    def sync_authenticator(self, layout: SyncLayout, frame: bytes, freshness: int) -> bytes:
        """The truncated MAC of a sync frame: over data ID || bytes 0.. || full freshness."""
        data = (layout.data_id.to_bytes(2, "big") + frame[:layout.payload_length]
                + freshness.to_bytes(layout.freshness_bits // 8, "big"))
        return self.cmac(data)[:layout.auth_bytes]

    # -- counters ---------------------------------------------------------------------

    def tx_freshness(self, stream: Hashable) -> int:
        """The freshness value of the last frame signed for `stream` (0: none yet)."""
        return self._tx.get(stream, 0)

    def rx_freshness(self, stream: Hashable) -> int:
        """The freshness value of the last frame accepted on `stream` (0: none yet)."""
        return self._rx.get(stream, 0)

    def is_synchronised(self, stream: Hashable) -> bool:
        """Whether `stream` was synchronised since start (sync, accepted frame, or set)."""
        return stream in self._synced

    def set_tx_freshness(self, stream: Hashable, value: int) -> None:
        """Continue sending on `stream` after `value` (e.g. restored from storage)."""
        self._tx[stream] = self._check_freshness(value)

    def set_rx_freshness(self, stream: Hashable, value: int) -> None:
        """Accept on `stream` only freshness values after `value` (resynchronisation)."""
        self._rx[stream] = self._check_freshness(value)
        self._synced.add(stream)

    @staticmethod
    def _check_freshness(value: int) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < 1 << 64:
            raise SecOCError(f"freshness value must be an int in 0..2^64-1, got {value!r}")
        return value

    # -- frames -----------------------------------------------------------------------

    def sign(self, layout: SecOCLayout, stream: Hashable, frame: bytes) -> bytes:
        """`frame` with the next freshness value of `stream` and its MAC written in.

        The CRC byte is left as it is (its value does not enter the MAC); the caller
        applies the E2E CRC afterwards.
        """
        freshness = self._tx.get(stream, 0) + 1
        if freshness >> layout.freshness_bits:
            raise SecOCError(f"{layout.name}: freshness counter exhausted; change the key")
        self._tx[stream] = freshness
        mask = (layout.fv_modulus - 1) << layout.fv_start
        n = int.from_bytes(frame, "little") & ~mask
        n |= (freshness << layout.fv_start) & mask
        out = bytearray(n.to_bytes(len(frame), "little"))
        a = layout.auth_start
        out[a:a + layout.auth_bytes] = self.authenticator(layout, bytes(out), freshness)
        return bytes(out)

    def verify(self, layout: SecOCLayout, stream: Hashable,
               frame: bytes) -> tuple[Verdict, str] | None:
        """Check `frame` of `stream`; None if authentic and fresh (then it is the new last).

        Otherwise (verdict, one-line detail) and the stream's state is unchanged.
        """
        last = self._rx.get(stream)
        if last is None:
            return (Verdict.UNSYNCED, "freshness not synchronised yet: no SecOC sync frame "
                                      "received for this stream")
        m = layout.fv_modulus
        sent = (int.from_bytes(frame, "little") >> layout.fv_start) & (m - 1)
        d = (sent - last) % m or m
        tag = frame[layout.auth_start:layout.auth_start + layout.auth_bytes]
        top = (1 << layout.freshness_bits) - 1
        window = self.window
        v = last + d
        limit = min(last + window, top)
        while v <= limit:
            if hmac.compare_digest(self.authenticator(layout, frame, v), tag):
                self._rx[stream] = v
                self._synced.add(stream)
                return None
            v += m
        # Rejected. Tell a replay of a recent frame, or an authentic frame from just
        # beyond the window, from a forgery (a few more MACs, on this path only).
        past = last + d - m
        while past >= 0 and past > last - window:
            if hmac.compare_digest(self.authenticator(layout, frame, past), tag):
                return (Verdict.STALE_FRESHNESS,
                        f"freshness {past} is not after the last accepted {last} (replay)")
            past -= m
        synced = stream in self._synced
        if v <= top and hmac.compare_digest(self.authenticator(layout, frame, v), tag):
            if not synced:
                return (Verdict.UNSYNCED,
                        f"freshness {v} is {v - last} ahead of the saved {last}, beyond the "
                        f"window of {window}: waiting for a SecOC sync frame")
            return (Verdict.STALE_FRESHNESS,
                    f"freshness {v} is {v - last} ahead of the last accepted {last}, "
                    f"beyond the window of {window}")
        if not synced:
            return (Verdict.UNSYNCED,
                    f"does not verify within the window after the saved freshness {last} "
                    f"(the sender moved on, or forged): waiting for a SecOC sync frame")
        return (Verdict.BAD_MAC,
                f"authenticator {tag.hex()} does not verify for freshness bits {sent} "
                f"(last accepted {last})")

    # -- synchronisation ----------------------------------------------------------------

    def sign_sync(self, layout: SyncLayout, stream: Hashable, frame: bytes) -> bytes:
        """`frame` (a sync frame with its kind written) with `stream`'s freshness and MAC.

        The freshness is that of the last frame signed on `stream` (0 before the first);
        a sync consumes no freshness value.
        """
        freshness = self._tx.get(stream, 0)
        mask = ((1 << layout.fv_bits) - 1) << layout.fv_start
        n = int.from_bytes(frame, "little") & ~mask
        n |= (freshness << layout.fv_start) & mask
        out = bytearray(n.to_bytes(len(frame), "little"))
        a = layout.auth_start
        out[a:a + layout.auth_bytes] = self.sync_authenticator(layout, bytes(out), freshness)
        return bytes(out)

    def verify_sync(self, layout: SyncLayout, stream: Hashable,
                    frame: bytes) -> tuple[Verdict, str] | None:
        """Check the sync `frame` for `stream`; None if accepted (then its value is the last).

        The full value is the one nearest the stream's last accepted value (0 if none)
        with the sent low bits. Accepted if its MAC verifies and it is not older than the
        last accepted value; otherwise (verdict, one-line detail), state unchanged.
        """
        last = self._rx.get(stream)
        sent = (int.from_bytes(frame, "little") >> layout.fv_start) & ((1 << layout.fv_bits) - 1)
        value = nearest_freshness(0 if last is None else last, sent, layout.fv_bits,
                                  layout.freshness_bits)
        tag = frame[layout.auth_start:layout.auth_start + layout.auth_bytes]
        if not hmac.compare_digest(self.sync_authenticator(layout, frame, value), tag):
            return (Verdict.BAD_MAC,
                    f"sync authenticator {tag.hex()} does not verify for freshness {value}")
        if last is not None and value < last:
            return (Verdict.STALE_FRESHNESS,
                    f"sync freshness {value} is older than the last accepted {last} "
                    f"(replayed sync)")
        self._rx[stream] = value
        self._synced.add(stream)
        return None

    # -- persistence ------------------------------------------------------------------

    def export_state(self) -> dict[str, int]:
        """The counters as ``{"rx/<kind>/<node>": last accepted, "tx/<kind>/<node>": last
        signed}`` for every stream named ``(kind, node)``; others are left out."""
        out: dict[str, int] = {}
        for direction, table in (("rx", dict(self._rx)), ("tx", dict(self._tx))):
            for stream, value in table.items():
                name = _stream_name(stream)
                if name is not None:
                    out[f"{direction}/{name}"] = value
        return dict(sorted(out.items()))

    def import_state(self, state: Mapping[str, int], *, tx_margin: int = 0) -> None:
        """Restore counters from `export_state` output; all or nothing (`SecOCError`).

        A receiving value becomes the stream's *floor*: frames in the window after it are
        accepted, syncs below it are replays; counters only ever move forward (a value
        below the current one is ignored). A sending value is restored `tx_margin` higher:
        a sender that saved periodically may have signed up to that many frames after its
        last save, and must never reuse a freshness value (its first sync tells the
        receivers where it went on).
        """
        if isinstance(tx_margin, bool) or not isinstance(tx_margin, int) or tx_margin < 0:
            raise SecOCError(f"tx_margin must be a non-negative int, got {tx_margin!r}")
        if not isinstance(state, Mapping):
            raise SecOCError(f"SecOC state must be a mapping, got {type(state).__name__}")
        parsed: list[tuple[str, tuple[str, int], int]] = []
        for key, value in state.items():
            m = _STATE_KEY.match(key) if isinstance(key, str) else None
            if m is None:
                raise SecOCError(f"SecOC state: bad stream name {key!r}; expected "
                                 f"rx|tx/<kind>/<node>")
            if isinstance(value, bool) or not isinstance(value, int) or not (
                    0 <= value < 1 << 64):
                raise SecOCError(f"SecOC state: {key} must be an int in 0..2^64-1, "
                                 f"got {value!r}")
            if m["dir"] == "tx":
                value = min(value + tx_margin, (1 << 64) - 1)
            parsed.append((m["dir"], (m["kind"], int(m["node"])), value))
        for direction, stream, value in parsed:
            table = self._rx if direction == "rx" else self._tx
            if value > table.get(stream, -1):
                table[stream] = value

    def save_state(self, path: str | os.PathLike[str]) -> None:
        """Write `export_state` to `path` atomically (temp file, fsync, rename), mode 0600.

        Every problem is one `SecOCError` line; the previous file stays intact.
        """
        p = Path(path)
        text = json.dumps({"format": STATE_FORMAT, "version": STATE_VERSION,
                           "freshness": self.export_state()}, indent=1) + "\n"
        tmp: str | None = None
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp",
                                       dir=p.parent)
            with os.fdopen(fd, "w", encoding="ascii") as f:
                os.fchmod(f.fileno(), 0o600)
                f.write(text)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, p)
            tmp = None
            with contextlib.suppress(OSError):  # make the rename durable (best effort)
                dfd = os.open(p.parent, os.O_RDONLY)
                try:
                    os.fsync(dfd)
                finally:
                    os.close(dfd)
        except OSError as exc:
            raise SecOCError(f"{p}: cannot save SecOC state: {exc.strerror or exc}") from None
        finally:
            if tmp is not None:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)

    def load_state(self, path: str | os.PathLike[str], *, tx_margin: int = 0) -> int | None:
        """`import_state` from a file written by `save_state`.

        Returns the number of counters restored, or None if `path` does not exist (a
        fresh start: the first valid sync of each stream is trusted). A file that is not a
        regular file, is writable by group or others, or is malformed is one `SecOCError`
        line and nothing is restored.
        """
        p = Path(path)
        try:
            fd = os.open(p, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
        except FileNotFoundError:
            return None
        except OSError as exc:
            raise SecOCError(f"{p}: cannot read SecOC state: {exc.strerror or exc}") from None
        try:
            st = os.fstat(fd)
            if not stat.S_ISREG(st.st_mode):
                raise SecOCError(f"{p}: SecOC state is not a regular file")
            mode = stat.S_IMODE(st.st_mode)
            if mode & 0o022:
                raise SecOCError(f"{p}: SecOC state is writable by group or others (mode "
                                 f"{mode:04o}); it guards against replays: chmod 600")
            raw = os.read(fd, _MAX_STATE_FILE + 1)
        except OSError as exc:
            raise SecOCError(f"{p}: cannot read SecOC state: {exc.strerror or exc}") from None
        finally:
            os.close(fd)
        if len(raw) > _MAX_STATE_FILE:
            raise SecOCError(f"{p}: not a SecOC state file: larger than {_MAX_STATE_FILE} "
                             f"bytes")
        try:
            doc = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, ValueError) as exc:
            raise SecOCError(f"{p}: not a SecOC state file: {_one_line(exc)}") from None
        if not isinstance(doc, dict) or doc.get("format") != STATE_FORMAT:
            raise SecOCError(f"{p}: not a SecOC state file (no \"format\": "
                             f"\"{STATE_FORMAT}\")")
        if doc.get("version") != STATE_VERSION:
            raise SecOCError(f"{p}: SecOC state version {doc.get('version')!r} is not "
                             f"supported (expected {STATE_VERSION})")
        freshness = doc.get("freshness")
        if not isinstance(freshness, dict):
            raise SecOCError(f"{p}: not a SecOC state file: \"freshness\" must be an object")
        try:
            self.import_state(freshness, tx_margin=tx_margin)
        except SecOCError as exc:
            raise SecOCError(f"{p}: {exc}") from None
        return len(freshness)


def _stream_name(stream: Hashable) -> str | None:
    """``"<kind>/<node>"`` for a stream named ``(kind, node)``, else None."""
    if (isinstance(stream, tuple) and len(stream) == 2 and isinstance(stream[0], str)
            and isinstance(stream[1], int) and not isinstance(stream[1], bool)
            and stream[1] >= 0):
        name = f"{stream[0]}/{stream[1]}"
        if _STATE_KEY.match("rx/" + name):
            return name
    return None


def _one_line(exc: BaseException, limit: int = 160) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= limit else text[: limit - 3] + "..."
