"""The CANopen keys of a rig file (`[bus] protocol = "canopen"`), read by `monitor.rig.load`.

    [bus]
    protocol = "canopen"
    eds = "drive.eds"              # or dcf = "drive.dcf": the drive's file, relative to the rig
    nodes = [1, 2]                 # the drives' node IDs, 1..127
    [bus.pdo.TPDO4]                # optional, per PDO: over the file's mapping and communication
    enabled = true
    objects = ["0x6041", "0x606C"]
    transmission = 1               # 1..240: every n-th SYNC; 254, 255: on the event timer
    event_timer_ms = 10
    cob_id = 0x481                 # node 1's; node n's is this + n - 1
    [bus.objects."0x606C"]         # optional, per object: raw value * factor = value in unit
    factor = 0.001
    unit = "rpm"

A signal of `[signals]` names an object (``signal = "0x606C"`` or its name in the file) and
may leave out its message: the one enabled PDO that maps the object is taken
(`monitor.bus.canopen.find_object`). Everything is checked here, against the file as the
`canopen` library reads it, so each mistake is one line naming the rig file and the key.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from monitor.bus.canopen import canopen_database, canopen_node, find_object, parse_object
from monitor.bus.errors import CodecError
from monitor.files import shown_path, user_file_problem
from monitor.rig.errors import RigError
from monitor.rig.spec import CanopenSpec, ObjectScale, PdoSpec, SignalRef

if TYPE_CHECKING:
    from monitor.bus.rigcodec import RigCodec
    from monitor.rig.load import _Table

__all__ = ["canopen_bus", "canopen_database", "canopen_refs", "file_key", "watch_canopen"]

Fail = Callable[[str, str], RigError]
_TRANSMISSION = (*range(0, 241), 252, 253, 254, 255)


def file_key(spec: CanopenSpec) -> str:
    """The rig file's key naming the drive's file: ``bus.eds`` or ``bus.dcf``."""
    return "bus.dcf" if spec.file.suffix.lower() == ".dcf" else "bus.eds"


def _int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def canopen_bus(bus: _Table, base: Path, fail: Fail) -> CanopenSpec:
    """The `[bus]` table of a CANopen rig (its `protocol` already taken), checked against
    the drive's file for every node."""
    given = [k for k in ("eds", "dcf") if k in bus.data]
    if len(given) != 1:
        raise fail("bus.eds", "a CANopen rig names its drive's file: eds = \"FILE.eds\" or "
                   "dcf = \"FILE.dcf\"" if not given else "give eds or dcf, not both")
    key = given[0]
    file = base / bus.take(key, str)
    if (problem := user_file_problem(file)) is not None:
        raise fail(f"bus.{key}", f"{shown_path(file)}: {problem}")
    if file.suffix.lower() != f".{key}":
        raise fail(f"bus.{key}", f"{shown_path(file)}: the name of a {key.upper()} file ends "
                   f"in .{key}")
    nodes_value = bus.take("nodes", list)
    if not nodes_value or not all(_int(v) and 1 <= v <= 127 for v in nodes_value):
        raise fail("bus.nodes", "must be an array of CANopen node IDs 1..127")
    nodes = tuple(sorted(set(nodes_value)))
    pdos = _pdos(bus.table("pdo"), fail)
    objects = _objects(bus.table("objects"), fail)
    spec = CanopenSpec(file, nodes, pdos, objects)
    for node in nodes:
        try:
            canopen_node(spec, node)
        except CodecError as exc:
            raise fail(f"bus.{key}", str(exc)) from None
    return spec


def _pdos(t: _Table, fail: Fail) -> tuple[PdoSpec, ...]:
    out = []
    for name in list(t.data):
        p = t.table(name)
        if name[:4] not in ("TPDO", "RPDO") or not name[4:].isdigit() or not (
                1 <= int(name[4:]) <= 512):
            raise fail(p.where, "not a PDO name (TPDO1..TPDO512, RPDO1..RPDO512)")
        enabled = p.take("enabled", bool, None)
        objects_value = p.take("objects", list, None)
        objects = None
        if objects_value is not None:
            parsed = [parse_object(v) if isinstance(v, str) else None for v in objects_value]
            if not objects_value or any(o is None for o in parsed):
                raise fail(p.key("objects"), "must be an array of objects such as \"0x606C\" "
                           "or \"0x60C1:1\"")
            objects = tuple(o for o in parsed if o is not None)
        trans = p.take("transmission", int, None)
        if trans is not None and trans not in _TRANSMISSION:
            raise fail(p.key("transmission"), f"must be 0..240 or 252..255, got {trans}")
        timer = p.take("event_timer_ms", int, None)
        if timer is not None and not 0 <= timer <= 0xFFFF:
            raise fail(p.key("event_timer_ms"), f"must be 0..65535 ms, got {timer}")
        cob = p.take("cob_id", int, None)
        if cob is not None and not 1 <= cob <= 0x7FF:
            raise fail(p.key("cob_id"), f"must be an 11-bit ID 1..0x7FF, got {cob}")
        p.done()
        out.append(PdoSpec(name, enabled, objects, trans, timer, cob))
    return tuple(out)


def _objects(t: _Table, fail: Fail) -> dict[tuple[int, int], ObjectScale]:
    out = {}
    for name in list(t.data):
        o = t.table(name)
        where = parse_object(name)
        if where is None:
            raise fail(o.where, "not an object (write it \"0x606C\" or \"0x60C1:1\")")
        factor = o.number("factor", 1.0) if "factor" in o.data else None
        if factor is not None and factor == 0:
            raise fail(o.key("factor"), "must not be 0")
        out[where] = ObjectScale(factor, o.take("unit", str, None))
        o.done()
    return out


def canopen_refs(spec: CanopenSpec, inputs: tuple[SignalRef, ...],
                 outputs: tuple[SignalRef, ...], truth: SignalRef | None, fail: Fail
                 ) -> tuple[tuple[SignalRef, ...], tuple[SignalRef, ...], SignalRef | None]:
    """The rig's signals with their PDO (the message) and their object's signal name in the
    bus description (`monitor.bus.canopen`), found in the first node's PDOs (every node
    reads the same file)."""
    node = canopen_node(spec, spec.nodes[0])

    def one(ref: SignalRef, key: str) -> SignalRef:
        try:
            pdo, obj = find_object(node, ref.signal, ref.message or None)
        except ValueError as exc:
            raise fail(f"{key}.message" if ref.message else f"{key}.signal", str(exc)) from None
        return SignalRef(pdo.name, obj.name, ref.unit)

    ins = tuple(one(r, f"signals.inputs[{i}]") for i, r in enumerate(inputs))
    outs = tuple(one(r, f"signals.outputs[{i}]") for i, r in enumerate(outputs))
    return ins, outs, None if truth is None else one(truth, "signals.truth")


def watch_canopen(codec: RigCodec, spec: CanopenSpec) -> None:
    """Give the rig's codec its drives, so that each engine reads their EMCY, heartbeat and
    statusword (`monitor.bus.cia402.drive_watch`)."""
    codec.drives = tuple(canopen_node(spec, n) for n in spec.nodes)
