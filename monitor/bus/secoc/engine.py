"""The SecOC engine: AES-CMAC authenticators, signing and verifying, freshness counters.

`SecOC` holds one key (as a keyed CMAC prototype) and the freshness counters of every
stream it sends or receives; it signs and verifies data frames (`SecOCLayout`) and sync
frames (`SyncLayout`), both from `monitor.bus.secoc.layout`, and saves and restores its
counters through `monitor.bus.secoc.state`.

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
starts, before its first data frame, and then once per second (SyncKind, SyncFreshness
and SyncAuthenticator: drawn in `monitor.bus.secoc.layout`).

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
"""

from __future__ import annotations

import enum
import hmac
import os
from collections.abc import Callable, Hashable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Final

from cryptography.hazmat.primitives.ciphers import algorithms
from cryptography.hazmat.primitives.cmac import CMAC

from monitor.bus.errors import SecOCError
from monitor.bus.secoc.keys import check_key
from monitor.bus.secoc.layout import SecOCLayout, SyncLayout
from monitor.bus.secoc.state import (
    export_counters,
    parse_counters,
    read_state_file,
    write_state_file,
)

if TYPE_CHECKING:
    from cantools.database.can import Message

__all__ = ["DEFAULT_WINDOW", "SecOC", "SecOCHolder", "Verdict", "aes_cmac", "nearest_freshness"]

DEFAULT_WINDOW: Final = 64
"""Accept a freshness value at most this far ahead of the last accepted one."""


def aes_cmac(key: bytes, data: bytes) -> bytes:
    """The full 16-byte AES-CMAC (RFC 4493 / NIST SP 800-38B) of `data` under `key`."""
    mac = CMAC(algorithms.AES(check_key(key)))
    mac.update(data)
    return mac.finalize()


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
        self._proto = CMAC(algorithms.AES(check_key(key)))
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
        """The CMAC input: data ID || authentic bytes (an E2E CRC byte as 0) || full
        freshness."""
        if not layout.crc_byte:
            return (layout.data_id.to_bytes(2, "big") + frame[:layout.payload_length]
                    + freshness.to_bytes(layout.freshness_bits // 8, "big"))
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
        return _stamp(layout, frame, freshness,
                      lambda out: self.authenticator(layout, out, freshness))

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
        return _stamp(layout, frame, freshness,
                      lambda out: self.sync_authenticator(layout, out, freshness))

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
        return export_counters(dict(self._rx), dict(self._tx))

    def import_state(self, state: Mapping[str, int], *, tx_margin: int = 0) -> None:
        """Restore counters from `export_state` output; all or nothing (`SecOCError`).

        A receiving value becomes the stream's *floor*: frames in the window after it are
        accepted, syncs below it are replays; counters only ever move forward (a value
        below the current one is ignored). A sending value is restored `tx_margin` higher:
        a sender that saved periodically may have signed up to that many frames after its
        last save, and must never reuse a freshness value (its first sync tells the
        receivers where it went on).
        """
        for direction, stream, value in parse_counters(state, tx_margin=tx_margin):
            table = self._rx if direction == "rx" else self._tx
            if value > table.get(stream, -1):
                table[stream] = value

    def save_state(self, path: str | os.PathLike[str]) -> None:
        """Write `export_state` to `path` atomically (temp file, fsync, rename), mode 0600.

        Every problem is one `SecOCError` line; the previous file stays intact.
        """
        write_state_file(path, self.export_state())

    def load_state(self, path: str | os.PathLike[str], *, tx_margin: int = 0) -> int | None:
        """`import_state` from a file written by `save_state`.

        Returns the number of counters restored, or None if `path` does not exist (a
        fresh start: the first valid sync of each stream is trusted). A file that is not a
        regular file, is writable by group or others, or is malformed is one `SecOCError`
        line and nothing is restored.
        """
        freshness = read_state_file(path)
        if freshness is None:
            return None
        try:
            self.import_state(freshness, tx_margin=tx_margin)
        except SecOCError as exc:
            raise SecOCError(f"{Path(path)}: {exc}") from None
        return len(freshness)


class SecOCHolder:
    """What a codec says of its SecOC engine: the one it signs and verifies with when it was
    given a key (`secoc`, None without one)."""

    _secoc: SecOC | None

    @property
    def secoc(self) -> SecOC | None:
        """The SecOC engine (key and freshness counters), None without a key."""
        return self._secoc

    @property
    def secoc_enabled(self) -> bool:
        return self._secoc is not None

    @property
    def frame_by_frame(self) -> bool:
        """Whether frames must be decoded one at a time, in order: with a key a frame's
        verdict depends on its stream's freshness state (`monitor.bus.route.RouteSource`)."""
        return self._secoc is not None


def _stamp(layout: SecOCLayout | SyncLayout, frame: bytes, freshness: int,
           mac: Callable[[bytes], bytes]) -> bytes:
    """`frame` with the low `layout.fv_bits` of `freshness` written at `layout.fv_start`,
    then ``mac(that frame)`` written to the MAC bytes."""
    mask = ((1 << layout.fv_bits) - 1) << layout.fv_start
    n = int.from_bytes(frame, "little") & ~mask
    n |= (freshness << layout.fv_start) & mask
    out = bytearray(n.to_bytes(len(frame), "little"))
    a = layout.auth_start
    out[a:a + layout.auth_bytes] = mac(bytes(out))
    return bytes(out)
