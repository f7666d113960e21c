"""Signals of a whole column of payloads at once, from cantools' own signal definitions.

`SignalExtractor(signal, length)` reads a `cantools.database.can.Signal` -- start bit,
length, byte order, sign, float or integer, and its conversion -- and `extract(le, be)`
returns the physical values of that signal for every payload of a chunk, as
`cantools` ``Message.decode(..., decode_choices=False, scaling=True)`` gives them one frame
at a time. Nothing here knows our bus: every rig's DBC goes through the same code, and the
property test (tests/columnar/test_columnar.py) checks it against cantools on random payloads.

Bit numbering, as cantools defines it: a little-endian (Intel) signal's `start` is its least
significant bit, bit ``start % 8`` of byte ``start // 8``, so it is ``(LE >> start) & mask`` of
the payload read as a little-endian integer. A big-endian (Motorola) signal's `start` is its
most significant bit in the DBC's sawtooth numbering; counted from the most significant bit
of the payload read as a big-endian integer it sits at ``8 * (start // 8) + 7 - start % 8``.
Floats are the IEEE bits of the raw field. The scaling is cantools' own
``conversion.raw_to_scaled``, applied to the whole column (numpy arithmetic: the same
operations in the same order as on one value).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from cantools.database.can import Signal
from numpy.typing import NDArray

__all__ = ["SignalExtractor", "payload_integers"]


def payload_integers(data: NDArray[np.uint8]) -> tuple[NDArray[np.uint64], NDArray[np.uint64]]:
    """(little-endian, big-endian) 64-bit integers of (n, 8) payloads."""
    d = np.ascontiguousarray(data, dtype=np.uint8)
    le = d.view("<u8").reshape(-1).astype(np.uint64)
    be = d.view(">u8").reshape(-1).astype(np.uint64)
    return le, be


class SignalExtractor:
    """One signal of a message of `msg_length` bytes (at most 8), for columns of payloads."""

    def __init__(self, signal: Signal, msg_length: int) -> None:
        if not 0 < msg_length <= 8:
            raise ValueError(f"{signal.name}: messages of {msg_length} bytes are not columnar")
        self.signal = signal
        self.name = signal.name
        n = int(signal.length)
        self.length = n
        self.mask = np.uint64((1 << n) - 1) if n < 64 else np.uint64(0xFFFFFFFFFFFFFFFF)
        if signal.byte_order == "little_endian":
            self.big = False
            self.shift = int(signal.start)
        else:
            msb = 8 * (signal.start // 8) + 7 - signal.start % 8
            self.big = True
            # the payload's big-endian integer is left-aligned in 64 bits (zero padded)
            self.shift = 64 - msb - n
        if self.shift < 0 or self.shift + n > 64:
            raise ValueError(f"{signal.name}: bits outside the payload")
        self.is_float = bool(signal.is_float)
        self.is_signed = bool(signal.is_signed)
        if self.is_float and n not in (16, 32, 64):
            raise ValueError(f"{signal.name}: float of {n} bits")
        conv = signal.conversion
        self.conversion = conv
        scale = getattr(conv, "scale", 1)
        offset = getattr(conv, "offset", 0)
        # integer conversions run in int64 where that cannot overflow (else Python ints)
        self._int_ok = (isinstance(scale, int) and isinstance(offset, int)
                        and n + abs(scale).bit_length() + 1 < 62
                        and abs(offset).bit_length() < 61)

    def raw(self, le: NDArray[np.uint64], be: NDArray[np.uint64]) -> NDArray[np.generic]:
        """The raw field of every payload: int64 (or float for float signals)."""
        src = be if self.big else le
        bits = (src >> np.uint64(self.shift)) & self.mask
        n = self.length
        if self.is_float:
            width = {16: np.uint16, 32: np.uint32, 64: np.uint64}[n]
            ftype = {16: np.float16, 32: np.float32, 64: np.float64}[n]
            with np.errstate(invalid="ignore"):  # signalling NaNs turn quiet, as in struct
                return bits.astype(width).view(ftype).astype(np.float64)
        if n == 64:
            if self.is_signed:
                return bits.view(np.int64)
            return bits.astype(object) if (bits >> np.uint64(63)).any() else bits.astype(np.int64)
        r = bits.astype(np.int64)
        if self.is_signed:
            sign = np.int64(1 << (n - 1))
            r = np.where(r & sign, r - np.int64(1 << n), r)
        return r

    def extract(self, le: NDArray[np.uint64], be: NDArray[np.uint64]) -> NDArray[np.float64]:
        """Physical values (float64) of the signal in every payload."""
        raw = self.raw(le, be)
        if not self.is_float and not self._int_ok:
            raw = raw.astype(object)
        # cantools' own scaling on the whole column (numpy arithmetic, same operations)
        scaled: Any = self.conversion.raw_to_scaled(raw, False)  # type: ignore[arg-type]
        if np.ndim(scaled) == 0:
            return np.full(raw.shape, float(scaled))
        return np.asarray(scaled, dtype=np.float64)
