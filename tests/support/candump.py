"""CAN frames as ``cansend`` writes and ``candump -L`` prints them, and candump logs."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import can

__all__ = ["CAN_EFF_MASK", "CAN_ERR_FLAG", "Captured", "Frame", "parse_frame", "read_candump"]

CAN_ERR_FLAG = 0x20000000
CAN_EFF_MASK = 0x1FFFFFFF


@dataclass(frozen=True)
class Frame:
    """One classic CAN (or CAN FD) frame, as cansend writes and candump -L prints it."""

    arbitration_id: int
    data: bytes = b""
    extended: bool = False
    remote: bool = False
    error: bool = False
    fd: bool = False
    dlc: int = 0  # remote frames: the DLC they carry

    @property
    def key(self) -> tuple[int, bytes, bool, bool, bool, bool]:
        return (self.arbitration_id, self.data, self.extended, self.remote, self.error, self.fd)

    def cansend(self) -> str:
        """The frame in cansend's syntax (``123#11223344``, ``00000123#R8``, ...)."""
        if self.error:
            ident = f"{CAN_ERR_FLAG | self.arbitration_id:08X}"
        elif self.extended:
            ident = f"{self.arbitration_id:08X}"
        else:
            ident = f"{self.arbitration_id:03X}"
        if self.remote:
            return f"{ident}#R{self.dlc or ''}"
        return f"{ident}#{self.data.hex().upper()}"

    def message(self, t: float) -> can.Message:
        return can.Message(timestamp=t, arbitration_id=self.arbitration_id,
                           data=b"" if self.remote else self.data,
                           dlc=self.dlc if self.remote else len(self.data),
                           is_extended_id=self.extended, is_remote_frame=self.remote,
                           is_error_frame=self.error, is_fd=self.fd, check=False)


def parse_frame(text: str) -> Frame:
    """A frame in cansend / candump -L syntax (the inverse of `Frame.cansend`)."""
    ident, sep, rest = text.partition("#")
    if not sep or len(ident) not in (3, 8):
        raise ValueError(f"not a CAN frame: {text!r}")
    can_id = int(ident, 16)
    fd = rest.startswith("#")
    if fd:
        rest = rest[2:]  # the flags nibble
    error = len(ident) == 8 and bool(can_id & CAN_ERR_FLAG)
    extended = len(ident) == 8 and not error
    arb = can_id & CAN_EFF_MASK if len(ident) == 8 else can_id
    if error:
        arb = can_id & ~CAN_ERR_FLAG & CAN_EFF_MASK
    if rest[:1] in ("R", "r"):
        return Frame(arb, b"", extended, True, error, fd, int(rest[1:] or 0))
    return Frame(arb, bytes.fromhex(rest.replace(".", "")), extended, False, error, fd)


@dataclass(frozen=True)
class Captured:
    t: float
    frame: Frame


_CANDUMP_RE = re.compile(r"^\((\d+\.\d+)\)\s+(\S+)\s+(\S+)")


def read_candump(path: Path) -> list[Captured]:
    """A ``candump -L`` log (error frames as error frames, which python-can's reader does not
    do), in file order."""
    out: list[Captured] = []
    if not path.exists():
        return out
    for line in path.read_text(errors="replace").splitlines():
        m = _CANDUMP_RE.match(line)
        if m is None:
            continue
        try:
            out.append(Captured(float(m.group(1)), parse_frame(m.group(3))))
        except ValueError:
            continue
    return out
