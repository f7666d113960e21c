"""What a CANopen drive says about itself: EMCY, NMT heartbeat and the CiA 402 statusword.

`DriveWatch` reads the frames of a CANopen rig that are not the model's (`monitor.bus.canopen`
describes the PDOs) and keeps, per node, what the drive reports:

* EMCY (0x80 + node): the error code and error register (CiA 301), named by the
  `canopen` library's classes (`canopen.emcy.EmcyError`) and, for the codes drives send
  most, by their CiA 301 / CiA 402 names; code 0 is the error reset;
* the NMT heartbeat (0x700 + node): the node's state (`canopen.nmt.NMT_STATES`; 0 is the
  boot-up), and its loss when none came for 1.5 producer heartbeat times (0x1017);
* the CiA 402 state from the statusword (0x6041) in any TPDO that maps it
  (`canopen.profiles.p402.State402.SW_MASK`: Operation enabled, Fault, Quick stop active,
  ...).

Each change is one `DriveReport`; `DriveWatch.operational` is the rule a diagnosis needs:
a drive that reports Fault or an active EMCY, has left Operation enabled, is not NMT
operational or whose heartbeat stopped is not driving its motor, so what its outputs show
is not a loss of effectiveness.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Final, Literal

from monitor.bus.canopen import CanopenNode

__all__ = ["CIA_ERROR_NAMES", "IGNORED_NOT_OPERATIONAL", "IGNORED_PROTOCOL", "DriveReport",
           "DriveWatch", "cia402_state", "drive_watch", "emcy_name", "error_register_bits",
           "report_counter", "report_level", "report_text"]

CIA_ERROR_NAMES: Final[Mapping[int, str]] = {
    0x0000: "error reset",
    0x2310: "continuous over current",
    0x2320: "short circuit",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x4210: "excess temperature device",
    0x4310: "excess temperature drive",
    0x5000: "device hardware",
    0x6100: "internal software",
    0x7121: "motor blocked",
    0x8110: "CAN overrun",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard or heartbeat error",
    0x8140: "recovered from bus off",
    0x8611: "following error",
}
"""Error codes named one by one (CiA 301's communication codes, CiA 402's common drive
codes); any other is named by its class (`canopen.emcy.EmcyError.DESCRIPTIONS`)."""

_REGISTER_BITS: Final = ("generic", "current", "voltage", "temperature", "communication",
                         "device profile", "reserved", "manufacturer")
IGNORED_NOT_OPERATIONAL: Final = "ignored/drive_not_operational"
"""The counter of a node's frames not read while its drive is not `DriveWatch.operational`:
what its outputs show then is the drive's state, not a loss of effectiveness, so the
estimator waits (the node falls silent) until the drive is operational again."""
IGNORED_PROTOCOL: Final = "ignored/canopen"
"""The counter of the CANopen frames a rig's messages do not include: NMT, SYNC and TIME, and
its drives' EMCY, heartbeat, SDO and PDOs the rig does not read (`DriveWatch.protocol_ids`).
They are the protocol's own traffic on the bus, not frames the monitor does not know; the
drives' EMCY, heartbeat and statusword are read (`DriveWatch.feed`) all the same."""
_BROADCAST: Final = (0x000, 0x080, 0x100)  # NMT, SYNC, TIME (CiA 301's broadcast COB-IDs)
_PER_NODE: Final = (0x080, 0x180, 0x200, 0x280, 0x300, 0x380, 0x400, 0x480, 0x500, 0x580,
                    0x600, 0x700)  # EMCY, the four TPDO and RPDO pairs, SDO tx/rx, heartbeat
HEARTBEAT_MARGIN: Final = 1.5
"""A heartbeat is lost after this many producer heartbeat times without one."""
OPERATIONAL: Final = "OPERATIONAL"
OPERATION_ENABLED: Final = "OPERATION ENABLED"

ReportKind = Literal["emcy", "nmt", "heartbeat_lost", "cia402"]


def emcy_name(code: int) -> str:
    """The name of an EMCY error code: its own where known, else its CiA 301 class."""
    from canopen.emcy import EmcyError

    if code in CIA_ERROR_NAMES:
        return CIA_ERROR_NAMES[code]
    for value, mask, description in EmcyError.DESCRIPTIONS:
        if code & mask == value:
            return description.lower()
    return "unknown"


def error_register_bits(register: int) -> tuple[str, ...]:
    """The error register's (0x1001) set bits by name."""
    return tuple(name for bit, name in enumerate(_REGISTER_BITS) if register >> bit & 1)


def cia402_state(statusword: int) -> str:
    """The CiA 402 state a statusword says (`State402.SW_MASK`), e.g. "OPERATION ENABLED"."""
    from canopen.profiles.p402 import State402

    for state, (mask, value) in State402.SW_MASK.items():
        if statusword & mask == value:
            return state
    return "UNKNOWN"


@dataclass(frozen=True)
class DriveReport:
    """A change in what a drive reports: `kind`, its time and node, `text` (one line) and
    the raw value (the EMCY code, the NMT state, the statusword)."""

    t: float
    node: int
    kind: ReportKind
    text: str
    value: int


@dataclass
class _Drive:
    heartbeat_s: float  # 0: the drive sends none
    nmt: str | None = None
    last_beat: float | None = None
    beat_lost: bool = False
    state: str | None = None
    emcy: int = 0  # the active error code (0: none)
    counts: dict[str, int] = field(default_factory=dict)


class DriveWatch:
    """What the drives of a CANopen rig report, from their frames (`feed`), per node."""

    def __init__(self, nodes: Iterable[CanopenNode]) -> None:
        self._drives: dict[int, _Drive] = {}
        self._status: dict[int, tuple[int, int]] = {}  # COB-ID -> (node, bit offset)
        ids = set(_BROADCAST)
        for n in nodes:
            self._drives[n.node] = _Drive(n.heartbeat_ms / 1000.0)
            ids.update(base + n.node for base in _PER_NODE)
            ids.update(pdo.cob_id for pdo in n.pdos)
            for pdo in n.pdos:
                for o in pdo.objects:
                    if pdo.transmit and (o.index, o.subindex) == (0x6041, 0) and o.length == 16:
                        self._status.setdefault(pdo.cob_id, (n.node, o.offset))

        self.protocol_ids: frozenset[int] = frozenset(ids)
        """The 11-bit COB-IDs of the CANopen protocol on this rig's bus (`IGNORED_PROTOCOL`):
        one rule, which both engines consult for a frame no rig message takes."""

    @property
    def nodes(self) -> tuple[int, ...]:
        return tuple(self._drives)

    def counts(self, node: int) -> Mapping[str, int]:
        """How many reports of each kind `node` gave."""
        return dict(self._drives[node].counts)

    def _report(self, t: float, node: int, kind: ReportKind, text: str, value: int
                ) -> DriveReport:
        d = self._drives[node].counts
        d[kind] = d.get(kind, 0) + 1
        return DriveReport(t, node, kind, text, value)

    def feed(self, arbitration_id: int, data: bytes, t: float) -> list[DriveReport]:
        """The reports one frame gives (none for a frame that says nothing new)."""
        from canopen.nmt import NMT_STATES

        out = self.tick(t)
        node = arbitration_id & 0x7F
        drive = self._drives.get(node)
        service = arbitration_id & 0x780
        if drive is not None and service == 0x080 and len(data) >= 3:
            code, register = int.from_bytes(data[:2], "little"), data[2]
            if code != drive.emcy or code:
                drive.emcy = code
                bits = ", ".join(error_register_bits(register)) or "none"
                out.append(self._report(t, node, "emcy", f"EMCY 0x{code:04X} "
                                        f"{emcy_name(code)} (error register 0x{register:02X}: "
                                        f"{bits})", code))
        elif drive is not None and service == 0x700 and len(data) >= 1:
            state = NMT_STATES.get(data[0] & 0x7F, f"state {data[0] & 0x7F}")
            state = "BOOT-UP" if data[0] == 0 else state
            drive.last_beat = t
            back, drive.beat_lost = drive.beat_lost, False
            if state != drive.nmt or back:  # a heartbeat back after its loss is a change
                drive.nmt = state
                out.append(self._report(t, node, "nmt", f"NMT {state}", data[0] & 0x7F))
        hit = self._status.get(arbitration_id)
        if hit is not None:
            status_node, offset = hit
            start = offset // 8
            if len(data) >= start + 2 and not offset % 8:
                word = int.from_bytes(data[start:start + 2], "little")
                state = cia402_state(word)
                status = self._drives[status_node]
                if state != status.state:
                    status.state = state
                    out.append(self._report(t, status_node, "cia402",
                                            f"CiA 402 {state} (statusword 0x{word:04X})", word))
        return out

    def unread(self, arbitration_id: int, is_extended: bool, data: bytes, t: float
               ) -> tuple[bool, list[DriveReport]]:
        """A frame that is no rig message (the codec's unknown_id): whether it is the
        CANopen protocol's own (`IGNORED_PROTOCOL`, not unknown_id) and what the drive says
        in it (`feed`). The one rule of the per-frame engine, identify and `check`."""
        return (not is_extended and arbitration_id in self.protocol_ids,
                self.feed(arbitration_id, data, t))

    def tick(self, t: float) -> list[DriveReport]:
        """Heartbeats lost by time `t` (each once, until the next heartbeat)."""
        out = []
        for node, d in self._drives.items():
            if (d.heartbeat_s > 0 and d.last_beat is not None and not d.beat_lost
                    and t - d.last_beat > HEARTBEAT_MARGIN * d.heartbeat_s):
                d.beat_lost = True
                out.append(self._report(t, node, "heartbeat_lost", "heartbeat lost (none for "
                                        f"{t - d.last_beat:.3f} s)", 0))
        return out

    def operational(self, node: int) -> bool:
        """Whether `node` drives its motor as far as it says: NMT operational (where it sends
        heartbeats), its heartbeat not lost, no active EMCY, and in Operation enabled (where
        a TPDO carries its statusword). What it has not reported yet is taken as fine."""
        d = self._drives[node]
        if d.beat_lost or d.emcy:
            return False
        if d.nmt is not None and d.nmt != OPERATIONAL:
            return False
        return d.state is None or d.state == OPERATION_ENABLED


def drive_watch(codec: object) -> DriveWatch | None:
    """A fresh `DriveWatch` of the drives `codec` decodes (its ``drives``: a CANopen rig's
    `monitor.bus.rigcodec.RigCodec`), None for a codec of no CANopen rig."""
    drives: Sequence[CanopenNode] = getattr(codec, "drives", ())
    return DriveWatch(drives) if drives else None


def report_counter(report: DriveReport) -> str:
    """The counter of a report's kind: ``drive/emcy``, ``drive/nmt``, ``drive/cia402``,
    ``drive/heartbeat_lost``."""
    return f"drive/{report.kind}"


def report_level(report: DriveReport) -> str:
    """The level a report is shown at: WARN for an error (an EMCY other than the reset, a
    lost heartbeat, a CiA 402 state other than Operation enabled), else INFO."""
    if report.kind == "emcy":
        return "WARN" if report.value else "INFO"
    if report.kind == "heartbeat_lost":
        return "WARN"
    if report.kind == "cia402":
        return "INFO" if report.text.startswith(f"CiA 402 {OPERATION_ENABLED} ") else "WARN"
    return "INFO"


def report_text(report: DriveReport) -> str:
    """One line: the node and what it reports."""
    return f"node {report.node}: {report.text}"
