"""Random DBC encodings, node layouts and rig files; frames packed for whole runs at once.

The DBC is built with cantools (`Database`, `Message`, `Signal`, `as_dbc_string`); the
frames of a run are packed with numpy (a run at 2 kHz holds 10^5 frames per message) and
the packing is checked against cantools' own `decode` on the first frames of every message,
so the capture is exactly what the DBC says.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import cantools
import numpy as np
from cantools.database.can import Database, Message, Node, Signal
from cantools.database.conversion import BaseConversion
from numpy.typing import NDArray

Array = NDArray[np.float64]

# bus value = SI value * factor
UNITS: dict[str, dict[str, float]] = {
    "voltage": {"V": 1.0},
    "current": {"A": 1.0, "mA": 1000.0},
    "torque": {"N*m": 1.0},
    "speed": {"rad/s": 1.0, "rpm": 60.0 / (2 * math.pi), "turn/s": 1.0 / (2 * math.pi)},
    "position": {"rad": 1.0, "deg": 180.0 / math.pi, "turn": 1.0 / (2 * math.pi)},
}


@dataclass
class SignalEnc:
    """One signal: its DBC encoding and the units on each side."""

    name: str
    role: str  # "input", "output" or "filler"
    length: int
    is_float: bool
    is_signed: bool
    scale: float
    offset: float
    minimum: float  # physical, bus unit
    maximum: float
    bus_factor: float  # bus value = SI * bus_factor
    dbc_unit: str | None  # the unit written in the DBC (None: none)
    model_unit: str | None  # the unit the rig file gives (None: no `unit` key)
    byte_order: str = "little_endian"
    start: int = 0

    def raw_range(self) -> tuple[int, int]:
        if self.is_signed:
            return -(1 << (self.length - 1)), (1 << (self.length - 1)) - 1
        return 0, (1 << self.length) - 1

    def to_raw(self, si: Array) -> NDArray[np.int64]:
        """SI values to raw bits (clipped to the signal's range, as a sensor saturates)."""
        v = np.asarray(si, dtype=np.float64) * self.bus_factor
        v = np.clip(v, self.minimum, self.maximum)
        if self.is_float:
            return np.asarray(v.astype(np.float32).view(np.uint32), dtype=np.int64)
        lo, hi = self.raw_range()
        r = np.clip(np.round((v - self.offset) / self.scale), lo, hi).astype(np.int64)
        return r

    def from_raw(self, raw: NDArray[np.int64]) -> Array:
        """Raw bits back to SI (what the bus says)."""
        if self.is_float:
            v = raw.astype(np.uint32).view(np.float32).astype(np.float64)
        else:
            v = raw.astype(np.float64) * self.scale + self.offset
        return np.asarray(v / self.bus_factor, dtype=np.float64)

    def bits(self) -> set[int]:
        """Occupied bits, numbered byte * 8 + bit (DBC's sawtooth numbering)."""
        out = set()
        if self.byte_order == "little_endian":
            return set(range(self.start, self.start + self.length))
        b = self.start
        for _ in range(self.length):
            out.add(b)
            b = b - 1 if b % 8 else b + 15
        return out

    def cantools(self) -> Signal:
        conv = BaseConversion.factory(scale=self.scale, offset=self.offset,
                                      is_float=self.is_float)
        order: Literal["little_endian", "big_endian"] = (
            "big_endian" if self.byte_order == "big_endian" else "little_endian")
        return Signal(name=self.name, start=self.start, length=self.length,
                      byte_order=order, is_signed=self.is_signed,
                      conversion=conv, minimum=self.minimum, maximum=self.maximum,
                      unit=self.dbc_unit, receivers=["Monitor"])


def _fits(sig: SignalEnc, used: set[int], nbytes: int) -> bool:
    if sig.byte_order == "little_endian":
        if sig.start + sig.length > nbytes * 8:
            return False
    else:
        # MSB at `start`; the LSB must stay inside the frame
        lsb_byte = sig.start // 8 + (sig.length - 1 - sig.start % 8 + 7) // 8
        if lsb_byte >= nbytes:
            return False
    return not (sig.bits() & used)


def place(rng: np.random.Generator, sigs: list[SignalEnc], nbytes: int = 8) -> bool:
    """Random non-overlapping positions for the signals (floats byte-aligned)."""
    used: set[int] = set()
    for sig in sigs:
        cands = []
        for start in range(nbytes * 8):
            if sig.is_float and start % 8 != (7 if sig.byte_order == "big_endian" else 0):
                continue
            sig.start = start
            if _fits(sig, used, nbytes):
                cands.append(start)
        if not cands:
            return False
        # prefer byte-aligned positions, as most DBCs do, but not always
        aligned = [c for c in cands if c % 8 == (7 if sig.byte_order == "big_endian" else 0)]
        pool = aligned if aligned and rng.random() < 0.7 else cands
        sig.start = int(rng.choice(pool))
        used |= sig.bits()
    return True


def nice_at_most(x: float) -> float:
    """The largest of 1, 2, 5 x 10^k not above x."""
    e = math.floor(math.log10(x))
    for m in (5.0, 2.0, 1.0):
        if m * 10.0**e <= x:
            return m * 10.0**e
    return 10.0 ** (e - 1) * 5.0


def integer_encoding(rng: np.random.Generator, sig: SignalEnc, span: float, quantum: float,
                     symmetric: bool) -> bool:
    """Pick scale, offset and length so that `span` (bus unit, +-) fits at `quantum`.

    False if more than 32 bits would be needed (use a float).
    """
    scale = nice_at_most(quantum)
    need = 2.0 * span / scale
    length = max(8, math.ceil(math.log2(need + 1)))
    length += int(rng.integers(0, 3))
    if length > 32:
        return False
    sig.length = length
    sig.is_float = False
    sig.scale = scale
    if symmetric or rng.random() < 0.5:
        sig.is_signed = True
        sig.offset = 0.0
    else:  # unsigned with an offset, as many DBCs do
        sig.is_signed = False
        sig.offset = -nice_round(scale * (1 << (length - 1)))
    lo, hi = sig.raw_range()
    sig.minimum = lo * scale + sig.offset
    sig.maximum = hi * scale + sig.offset
    return True


def nice_round(x: float) -> float:
    return float(f"{x:.6g}")


def float_encoding(sig: SignalEnc, span: float) -> None:
    sig.length = 32
    sig.is_float = True
    sig.is_signed = True
    sig.scale = 1.0
    sig.offset = 0.0
    sig.minimum = -nice_round(span)
    sig.maximum = nice_round(span)


@dataclass
class MessageSpec:
    """A rig message (`key`), its signals and, per node, its DBC name and frame ID."""

    key: str
    signals: list[SignalEnc]
    extended: bool
    period: int  # fine steps
    phase: int  # fine steps
    dbc_names: dict[int, str] = field(default_factory=dict)
    frame_ids: dict[int, int] = field(default_factory=dict)
    is_output: bool = False
    length: int = 8

    def signal(self, role: str) -> SignalEnc | None:
        for s in self.signals:
            if s.role == role:
                return s
        return None


def pack(msg: MessageSpec, raws: dict[str, NDArray[np.int64]], n: int) -> NDArray[np.uint8]:
    """The payloads of n frames (n x length bytes) from each signal's raw values."""
    le = np.zeros(n, dtype=np.uint64)
    be = np.zeros(n, dtype=np.uint64)
    for sig in msg.signals:
        r = raws[sig.name].astype(np.int64) & ((1 << sig.length) - 1)
        r = r.astype(np.uint64)
        if sig.byte_order == "little_endian":
            le |= r << np.uint64(sig.start)
        else:
            msb = (7 - sig.start // 8) * 8 + sig.start % 8  # in the big-endian 64-bit word
            be |= r << np.uint64(msb - sig.length + 1)
    out = le.astype("<u8").view(np.uint8).reshape(n, 8) | be.astype(">u8").view(
        np.uint8).reshape(n, 8)
    return np.ascontiguousarray(out[:, :msg.length])


def build_database(msgs: list[MessageSpec], nodes: list[int], layout: str,
                   extra: list[Message]) -> Database:
    """The DBC: every node's messages (name_suffix, explicit) or node 0's (id_bits)."""
    cmsgs: list[Message] = []
    listed = [0] if layout == "id_bits" else nodes
    for m in msgs:
        for node in listed:
            cmsgs.append(Message(
                frame_id=m.frame_ids[node], name=m.dbc_names[node], length=m.length,
                signals=[s.cantools() for s in m.signals], senders=["Drive"],
                is_extended_frame=m.extended, cycle_time=None, strict=True))
    cmsgs.extend(extra)
    return Database(messages=cmsgs, nodes=[Node("Drive"), Node("Monitor")], strict=True)


def check_packing(db_text: str, msgs: list[MessageSpec], node: int, layout: str,
                  samples: dict[str, NDArray[np.uint8]],
                  raws: dict[str, dict[str, NDArray[np.int64]]]) -> None:
    """Decode the first frames with cantools and compare with the raw values packed."""
    db = cantools.database.load_string(db_text, database_format="dbc", strict=True)
    assert isinstance(db, Database)
    for m in msgs:
        name = m.dbc_names[0 if layout == "id_bits" else node]
        cm = db.get_message_by_name(name)
        payloads = samples[m.key]
        for k in range(min(20, payloads.shape[0])):
            dec = cm.decode(bytes(payloads[k]), decode_choices=False, scaling=False)
            assert isinstance(dec, dict)
            for sig in m.signals:
                got = dec[sig.name]
                assert isinstance(got, int | float)
                want = int(raws[m.key][sig.name][k])
                if sig.is_float:
                    want_f = float(np.array([want], dtype=np.uint32).view(np.float32)[0])
                    ok = math.isclose(float(got), want_f, rel_tol=1e-6, abs_tol=1e-30) or (
                        math.isnan(want_f) and math.isnan(float(got)))
                else:
                    ok = int(got) == want
                if not ok:
                    raise AssertionError(
                        f"zoo packing differs from cantools: {name}.{sig.name} frame {k}: "
                        f"{got} != {want}")


def toml_str(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


def signal_entry(msg_key: str, sig: SignalEnc) -> str:
    parts = [f"message = {toml_str(msg_key)}", f"signal = {toml_str(sig.name)}"]
    if sig.model_unit is not None:
        parts.append(f"unit = {toml_str(sig.model_unit)}")
    return "{ " + ", ".join(parts) + " }"
