"""A CANopen bus (CiA 301, drives of the CiA 402 profile) as the bus description the codec reads.

A CANopen rig names a drive's EDS or DCF file and its node IDs (`monitor.rig.spec.CanopenSpec`).
The `canopen` library reads the file (`canopen.objectdictionary.import_od`, with each node's
ID for the ``$NODEID`` COB-IDs) and its PDO maps (`canopen.pdo`: `PdoMap.read(from_od=True)`
takes a DCF's values, else the EDS's defaults), and the rig file may set PDOs and scalings
over the file. From that the same in-memory bus description the DBC path gives is built
(`canopen_database`): a cantools `Database` with one message per enabled PDO of each node,
named ``<PDO>_N<node>`` (``TPDO1_N3``) at its COB-ID, one signal per mapped object at its bit
offset, with its length, signedness, scale and unit, so that `monitor.bus.rigcodec.RigCodec`,
the columnar decoder and the rig's twin read it unchanged, the node found by COB-ID through
the ``name_suffix`` layout.

Scaling of an object's raw value, first found: the rig file's ``[bus.objects]``; the EDS's
``Factor`` and ``Unit`` (which the `canopen` library reads); CiA 402's per-mille objects
(torques per mille of the rated torque 0x6076 in mN m, currents per mille of the rated
current 0x6075 in mA) where the file gives the rated value; else the raw value, no unit.

Every problem with the file is one `CodecError` line naming the file and what is wrong.
"""

from __future__ import annotations

import io
import logging
import math
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

from cantools.database.can import Database, Message, Signal
from cantools.database.conversion import BaseConversion

from monitor.bus.errors import CodecError
from monitor.errors import one_line
from monitor.files import MIB, UserFileError, read_user_text, shown_path

if TYPE_CHECKING:
    from canopen.objectdictionary import ObjectDictionary

    from monitor.rig.spec import CanopenSpec, PdoSpec

__all__ = ["CIA402_PER_MILLE", "EDS_FILE_LIMIT", "CanopenNode", "MappedObject", "Pdo",
           "canopen_database", "canopen_node", "find_object", "parse_object"]

log = logging.getLogger(__name__)

EDS_FILE_LIMIT: Final = 16 * MIB
"""The largest EDS or DCF read (vendors' files are a few hundred kB)."""

CIA402_PER_MILLE: Final[Mapping[int, tuple[int, str]]] = {
    0x6071: (0x6076, "N*m"),  # target torque
    0x6072: (0x6076, "N*m"),  # max torque
    0x6074: (0x6076, "N*m"),  # torque demand
    0x6077: (0x6076, "N*m"),  # torque actual value
    0x6073: (0x6075, "A"),  # max current
    0x6078: (0x6075, "A"),  # current actual value
}
"""CiA 402 objects given per mille of a rated value: the object holding the rated value (the
motor rated torque 0x6076 in mN m, the motor rated current 0x6075 in mA) and the SI unit the
raw value is scaled to (raw * rated / 1000 in mN m or mA, / 1000 again to SI)."""

_PDO_NAME = re.compile(r"^(?P<dir>[TR])PDO(?P<n>[1-9]\d{0,2})$")
_OBJECT = re.compile(r"^0x(?P<index>[0-9A-Fa-f]{4})(?:[:.](?:0x)?(?P<sub>[0-9A-Fa-f]{1,2}))?$")


@dataclass(frozen=True)
class MappedObject:
    """One object mapped into a PDO: where it sits (bit offset and length, little-endian as
    CANopen sends it), its data type, and its physical scaling."""

    index: int
    subindex: int
    name: str  # the signal's name in the bus description
    offset: int
    length: int
    signed: bool
    is_float: bool
    factor: float
    unit: str | None
    minimum: float | None
    maximum: float | None

    @property
    def key(self) -> str:
        return f"0x{self.index:04X}" + (f":{self.subindex}" if self.subindex else "")


@dataclass(frozen=True)
class Pdo:
    """An enabled PDO of a node: `transmit` (a TPDO, sent by the drive) or an RPDO (sent by
    the host), its COB-ID, transmission type and event timer, length in bytes and objects."""

    name: str
    transmit: bool
    cob_id: int
    transmission: int | None
    event_timer_ms: int | None
    length: int
    objects: tuple[MappedObject, ...]


@dataclass(frozen=True)
class CanopenNode:
    """What a node's file says about it on the bus: its enabled PDOs and its producer
    heartbeat time (0x1017, ms; 0: none)."""

    node: int
    pdos: tuple[Pdo, ...]
    heartbeat_ms: int
    product: str | None

    def pdo(self, name: str) -> Pdo:
        for p in self.pdos:
            if p.name == name:
                return p
        raise KeyError(name)


def parse_object(text: str) -> tuple[int, int] | None:
    """(index, subindex) of an object written ``0x606C`` or ``0x60C1:1``, None otherwise."""
    hit = _OBJECT.match(text.strip())
    if hit is None:
        return None
    return int(hit["index"], 16), int(hit["sub"], 16) if hit["sub"] else 0


def _load_od(path: Path, node: int) -> ObjectDictionary:
    """The object dictionary of `path` for `node` (one `CodecError` line if it cannot be)."""
    from canopen.objectdictionary import import_od

    shown = shown_path(path)
    suffix = path.suffix.lower()
    if suffix not in (".eds", ".dcf"):
        raise CodecError(f"{shown}: not an EDS or DCF file (the name must end in .eds or "
                         ".dcf)")
    try:
        text = read_user_text(path, what="EDS/DCF file", limit=EDS_FILE_LIMIT)
    except UserFileError as exc:
        raise CodecError(str(exc)) from None
    stream = io.StringIO(text)
    stream.name = f"drive{suffix}"  # import_od picks the format by the name's suffix
    try:
        od = import_od(stream, node)
    except Exception as exc:  # configparser's, ValueError, KeyError, ObjectDictionaryError
        raise CodecError(f"{shown}: not a valid {suffix[1:].upper()} file: "
                         f"{type(exc).__name__}: {one_line(exc)}") from None
    if not len(od):
        raise CodecError(f"{shown}: no objects (not an EDS or DCF file?)")
    return od


def _raw(var: Any) -> Any:
    """A variable's value as the file gives it: a DCF's ParameterValue, else its default."""
    return var.value if var.value is not None else var.default


def _rated(od: ObjectDictionary, index: int) -> float | None:
    var = od.get_variable(index)
    if var is None:
        return None
    value = _raw(var)
    return float(value) if isinstance(value, int | float) and value > 0 else None


def _scaling(od: ObjectDictionary, var: Any, spec: CanopenSpec) -> tuple[float, str | None]:
    """(factor, unit) from raw to physical value (see the module's docstring for the order)."""
    own = spec.objects.get((var.index, var.subindex))
    file_factor = float(var.factor) if var.factor not in (None, 0) else 1.0
    file_unit = var.unit.strip() if isinstance(var.unit, str) and var.unit.strip() else None
    factor, unit = file_factor, file_unit
    if file_factor == 1.0 and file_unit is None and var.index in CIA402_PER_MILLE:
        rated_index, si = CIA402_PER_MILLE[var.index]
        rated = _rated(od, rated_index)
        if rated is not None:
            factor, unit = rated / 1e6, si
    if own is not None:
        factor = own.factor if own.factor is not None else factor
        unit = own.unit if own.unit is not None else unit
    return factor, unit


def _apply(pdo_map: Any, own: PdoSpec, node: int, where: str) -> None:
    """The rig file's settings of one PDO over the file's, through the library's `PdoMap`."""
    if own.objects is not None:
        pdo_map.clear()
        for index, sub in own.objects:
            if pdo_map.add_variable(index, sub) is None:
                raise CodecError(f"{where}: {own.name} maps 0x{index:04X}:{sub}, which the "
                                 "file does not define")
        pdo_map.enabled = True if own.enabled is None else own.enabled
    if own.enabled is not None:
        pdo_map.enabled = own.enabled
    if own.transmission is not None:
        pdo_map.trans_type = own.transmission
    if own.event_timer_ms is not None:
        pdo_map.event_timer = own.event_timer_ms
    if own.cob_id is not None:
        pdo_map.cob_id = own.cob_id + node - 1
    elif pdo_map.cob_id in (None, 0) and pdo_map.predefined_cob_id is not None:
        pdo_map.cob_id = pdo_map.predefined_cob_id


def _mapped_count(pdo_map: Any) -> int:
    """The entries the file's mapping parameter lists (index and length not 0)."""
    count = _raw(pdo_map.map_array[0].od) or 0
    n = 0
    for sub in range(1, int(count) + 1):
        value = _raw(pdo_map.map_array[sub].od)
        if value and value >> 16 and value & 0xFF:
            n += 1
    return n


def canopen_node(spec: CanopenSpec, node: int) -> CanopenNode:
    """Node `node`'s enabled PDOs and heartbeat, from the file and the rig file's settings."""
    import canopen
    from canopen.objectdictionary import datatypes as dt

    where = shown_path(spec.file)
    od = _load_od(spec.file, node)
    network = canopen.Network()  # no bus: the maps subscribe to it, nothing is sent
    remote = canopen.RemoteNode(node, od)
    network.add_node(remote)
    own = {p.name: p for p in spec.pdos}
    pdos: list[Pdo] = []
    for kind, maps in (("TPDO", remote.tpdo), ("RPDO", remote.rpdo)):
        assert maps.map is not None  # the library fills it in the constructor
        for number, pdo_map in maps.map.items():
            name = f"{kind}{number}"
            try:
                pdo_map.read(from_od=True)
                listed = _mapped_count(pdo_map)
            except Exception as exc:  # a record missing or without values in the file
                raise CodecError(f"{where}: {name}: its communication or mapping "
                                 f"parameter cannot be read: {type(exc).__name__}: "
                                 f"{one_line(exc)}") from None
            if len(pdo_map.map) != listed:
                raise CodecError(f"{where}: {name} maps {listed} object(s), of which "
                                 f"{listed - len(pdo_map.map)} the file does not define")
            if name in own:
                _apply(pdo_map, own.pop(name), node, where)
            if not pdo_map.enabled or not pdo_map.map:
                continue
            if pdo_map.length > 64:
                raise CodecError(f"{where}: {name} maps {pdo_map.length} bits, more than "
                                 "the 64 of a CAN frame")
            if not 0 < pdo_map.cob_id < 0x800:
                raise CodecError(f"{where}: {name} of node {node} has COB-ID "
                                 f"0x{pdo_map.cob_id:X}, not an 11-bit ID")
            objects: list[MappedObject] = []
            seen: set[str] = set()
            for var in pdo_map.map:
                if var.od.data_type not in dt.NUMBER_TYPES and var.od.data_type != dt.BOOLEAN:
                    raise CodecError(f"{where}: {name} maps 0x{var.index:04X} "
                                     f"({var.od.qualname}), which is not a number")
                factor, unit = _scaling(od, var.od, spec)
                label = var.od.qualname
                if label in seen:
                    label = f"{label} 0x{var.index:04X}:{var.subindex}"
                seen.add(label)
                signed = var.od.data_type in dt.SIGNED_TYPES
                is_float = var.od.data_type in dt.FLOAT_TYPES
                lo = None if var.od.min is None else float(var.od.min) * factor
                hi = None if var.od.max is None else float(var.od.max) * factor
                if lo is not None and hi is not None and lo > hi:
                    lo, hi = hi, lo
                objects.append(MappedObject(var.index, var.subindex, label, int(var.offset),
                                            int(var.length), signed, is_float, factor, unit,
                                            lo, hi))
            pdos.append(Pdo(name, kind == "TPDO", int(pdo_map.cob_id), pdo_map.trans_type,
                            pdo_map.event_timer, math.ceil(pdo_map.length / 8),
                            tuple(objects)))
    if own:
        name = next(iter(own))
        raise CodecError(f"{where}: has no {name} (it has "
                         f"{', '.join(_names(remote)) or 'no PDOs'})")
    heartbeat = od.get_variable(0x1017)
    beat = _raw(heartbeat) if heartbeat is not None else 0
    return CanopenNode(node, tuple(pdos), int(beat or 0), od.device_information.product_name)


def _names(remote: Any) -> Iterable[str]:
    yield from (f"TPDO{n}" for n in remote.tpdo.map)
    yield from (f"RPDO{n}" for n in remote.rpdo.map)


def canopen_database(spec: CanopenSpec) -> Database:
    """The bus description of a CANopen rig: one message ``<PDO>_N<node>`` per enabled PDO
    of every node at its COB-ID, one signal per mapped object."""
    messages: list[Message] = []
    for node in spec.nodes:
        for pdo in canopen_node(spec, node).pdos:
            signals = [Signal(o.name, o.offset, o.length, "little_endian", o.signed,
                              conversion=BaseConversion.factory(scale=o.factor,
                                                                is_float=o.is_float),
                              minimum=o.minimum, maximum=o.maximum, unit=o.unit,
                              comment=o.key)
                       for o in pdo.objects]
            try:
                messages.append(Message(pdo.cob_id, f"{pdo.name}_N{node}", pdo.length,
                                        signals, comment=f"{pdo.name} of node {node}"))
            except Exception as exc:  # cantools: overlapping signals
                raise CodecError(f"{shown_path(spec.file)}: {pdo.name} of node {node}: "
                                 f"{one_line(exc)}") from None
    if not messages:
        raise CodecError(f"{shown_path(spec.file)}: no enabled PDO maps any object (enable "
                         "one or map objects with [bus.pdo.<PDO>])")
    db = Database(messages)
    db.refresh()
    return db


def find_object(node: CanopenNode, signal: str, message: str | None) -> tuple[Pdo, MappedObject]:
    """The PDO and mapped object a rig file's signal names: an object (``0x606C``,
    ``0x60C1:1``) or its name in the file, in the PDO `message` or, without it, in the one
    enabled PDO that maps it. `ValueError` (one line) if none or several do."""
    want = parse_object(signal)

    def hit(o: MappedObject) -> bool:
        if want is not None:
            return (o.index, o.subindex) == want
        return o.name.casefold() == signal.strip().casefold()

    pdos: Sequence[Pdo] = node.pdos
    if message:
        if _PDO_NAME.match(message) is None:
            raise ValueError(f"{message!r} is not a PDO name (TPDO1, RPDO2, ...)")
        pdos = [p for p in node.pdos if p.name == message]
        if not pdos:
            raise ValueError(f"{message} is not an enabled PDO of node {node.node} (enabled: "
                             f"{', '.join(p.name for p in node.pdos)})")
    found = [(p, o) for p in pdos for o in p.objects if hit(o)]
    if len(found) == 1:
        return found[0]
    if found:
        raise ValueError(f"{signal} is mapped by {', '.join(p.name for p, _ in found)}: give "
                         "message = \"<PDO>\"")
    mapped = ", ".join(sorted({f"{o.key} {o.name}" for p in pdos for o in p.objects}))
    if message:
        raise ValueError(f"{message} does not map {signal} (it maps {mapped or 'nothing'})")
    raise ValueError(f"no enabled PDO maps {signal} (mapped: {mapped or 'nothing'}); map it "
                     "with [bus.pdo.<PDO>]")
