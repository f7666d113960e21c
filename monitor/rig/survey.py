"""A rig file held against a capture: what the monitor reads from the rig (each message's
arbitration ID, length, node and the model's signals in it) and what it makes of every
frame of a capture, by arbitration ID, with the same frame decoder the monitor runs
(`monitor.rig.build_decoder`) and the same CANopen protocol set (`DriveWatch.protocol_ids`).

It answers the first questions of a new rig before any model is learned: is every message
that carries a model input or output on the bus, at which rate, with the length the rig
expects; which IDs on the bus the rig does not know (a node or ID layout mistake shows here
as a busy unknown ID); what the protocol's own frames are. `problems` lists what keeps the
monitor from forming samples, each in one line that says what to check.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field

import can

from monitor.bus.cia402 import IGNORED_PROTOCOL, drive_watch
from monitor.bus.codec import MotorDatabase, Rejected, RejectReason
from monitor.bus.errors import CodecError
from monitor.bus.rigcodec import RigCodec

__all__ = ["IdSurvey", "RigFrame", "Survey", "cob_id_name", "rig_frames", "survey"]

_COB_FUNCTIONS = {0x080: "EMCY", 0x180: "TPDO1", 0x200: "RPDO1", 0x280: "TPDO2",
                  0x300: "RPDO2", 0x380: "TPDO3", 0x400: "RPDO3", 0x480: "TPDO4",
                  0x500: "RPDO4", 0x580: "SDO tx", 0x600: "SDO rx", 0x700: "heartbeat"}


def cob_id_name(cob_id: int) -> str:
    """The CANopen predefined connection set's name of an 11-bit COB-ID (CiA 301), e.g.
    ``"TPDO3 of node 3"`` for 0x383, ``"SYNC"`` for 0x080."""
    if cob_id == 0x000:
        return "NMT"
    if cob_id == 0x080:
        return "SYNC"
    if cob_id == 0x100:
        return "TIME"
    function, node = cob_id & 0x780, cob_id & 0x7F
    name = _COB_FUNCTIONS.get(function)
    return f"{name} of node {node}" if name is not None and node else f"COB-ID 0x{cob_id:03X}"


@dataclass(frozen=True)
class RigFrame:
    """One message of one node as the monitor reads it."""

    name: str
    node: int
    frame_id: int
    extended: bool
    length: int
    inputs: tuple[str, ...]  # the signals read as model inputs
    outputs: tuple[str, ...]
    protection: str  # "", "E2E", "counter", "SecOC", ...

    @property
    def carries_model(self) -> bool:
        return bool(self.inputs or self.outputs)


def rig_frames(codec: MotorDatabase | RigCodec) -> list[RigFrame]:
    """Every message of every node the decoder routes, by node then ID."""
    out: list[RigFrame] = []
    if isinstance(codec, RigCodec):
        for name, spec in codec.specs.items():
            for node in codec.nodes:
                try:
                    frame_id = codec.frame_id(name, node)
                except CodecError:  # this node has no such message
                    continue
                msg = codec.message(name, node)
                prot = ("SecOC" if spec.secoc is not None else "E2E" if spec.e2e
                        else "counter" if spec.counter else "")
                out.append(RigFrame(name, node, frame_id, bool(msg.is_extended_frame),
                                    int(msg.length), tuple(s for _, s, _ in spec.inputs),
                                    tuple(s for s, _ in spec.outputs), prot))
    else:
        for r in codec.routes:
            out.append(RigFrame(r.message.name, r.node, r.frame_id, r.extended, r.length,
                                tuple(s for _, s, _ in r.inputs), tuple(s for s, _ in r.outputs),
                                "E2E" if r.e2e else ""))
    return sorted(out, key=lambda f: (f.node, f.frame_id))


@dataclass
class IdSurvey:
    """The frames of one arbitration ID in a capture and what the monitor made of them."""

    frame_id: int
    extended: bool
    frames: int = 0
    first_t: float = 0.0
    last_t: float = 0.0
    lengths: Counter[int] = field(default_factory=Counter)
    outcomes: Counter[str] = field(default_factory=Counter)  # "read", "rejected/...", ...
    read_as: str = ""  # the rig message and node it was read as, or the protocol's name

    @property
    def rate_hz(self) -> float:
        span = self.last_t - self.first_t
        return (self.frames - 1) / span if self.frames > 1 and span > 0 else 0.0


@dataclass
class Survey:
    frames: int = 0
    error_frames: int = 0
    ids: dict[tuple[int, bool], IdSurvey] = field(default_factory=dict)
    canopen: bool = False  # the rig's bus is CANopen: IDs are named by the connection set
    nodes_read: set[int] = field(default_factory=set)  # nodes with a frame read

    def of(self, frame_id: int, extended: bool) -> IdSurvey | None:
        return self.ids.get((frame_id, extended))

    def problems(self, expected: Iterable[RigFrame]) -> list[str]:
        """What keeps the monitor from forming samples, one line each: a message carrying
        model signals that never read (absent, or every frame rejected: why), and, when
        nothing reads at all, the busiest IDs the rig does not know."""
        out: list[str] = []
        for f in expected:
            if not f.carries_model:
                continue
            s = self.of(f.frame_id, f.extended)
            what = (f"node {f.node}'s {f.name} (ID 0x{f.frame_id:X}, "
                    f"{', '.join(f.inputs + f.outputs)})")
            if s is None:
                out.append(f"{what}: no frame with this ID in the capture: check the node "
                           "number and the ID layout (or the PDO's COB-ID and mapping)")
            elif not s.outcomes.get("read"):
                why = ", ".join(f"{n} {k}" for k, n in s.outcomes.most_common())
                lengths = ", ".join(f"{n} of {k} bytes" for k, n in s.lengths.most_common())
                hint = (f"; the rig expects {f.length} bytes" if "rejected/wrong_length"
                        in s.outcomes else "")
                out.append(f"{what}: {s.frames} frames, none read ({why}; {lengths}{hint})")
        if not any(s.outcomes.get("read") for s in self.ids.values()):
            unknown = sorted((s for s in self.ids.values()
                              if s.outcomes.get(f"rejected/{RejectReason.UNKNOWN_ID}")),
                             key=lambda s: -s.frames)[:5]
            if unknown:
                out.append("no frame of the capture is one of the rig's; its busiest IDs: " +
                           ", ".join(f"0x{s.frame_id:X} ({self._named(s)}{s.frames} frames, "
                                     f"{s.rate_hz:.0f} Hz)" for s in unknown))
        return out


    def _named(self, s: IdSurvey) -> str:
        return f"{cob_id_name(s.frame_id)}, " if self.canopen and not s.extended else ""


def survey(codec: MotorDatabase | RigCodec, frames: Iterable[can.Message]) -> Survey:
    """Every frame of `frames` through `codec` (the monitor's frame checks), by ID."""
    watch = drive_watch(codec)
    out = Survey(canopen=watch is not None)
    for msg in frames:
        out.frames += 1
        if msg.is_error_frame:
            out.error_frames += 1
            continue
        key = (msg.arbitration_id, bool(msg.is_extended_id))
        s = out.ids.get(key)
        if s is None:
            s = out.ids[key] = IdSurvey(*key, first_t=float(msg.timestamp))
        s.frames += 1
        s.last_t = float(msg.timestamp)
        s.lengths[len(msg.data)] += 1
        res = codec.decode_can(msg)
        if isinstance(res, Rejected):
            if res.reason == RejectReason.UNKNOWN_ID and watch is not None and watch.unread(
                    msg.arbitration_id, msg.is_extended_id, bytes(msg.data),
                    float(msg.timestamp))[0]:
                s.outcomes[IGNORED_PROTOCOL] += 1
                s.read_as = cob_id_name(msg.arbitration_id)
            else:
                s.outcomes[f"rejected/{res.reason}"] += 1
        else:
            s.outcomes["read"] += 1
            s.read_as = f"{res.kind} of node {res.node}"
            out.nodes_read.add(res.node)
    return out
