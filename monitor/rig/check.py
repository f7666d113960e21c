"""A rig checked against its DBC files and its model: messages and signals exist, units
parse, convert and suit the model, protection signals sit where AUTOSAR E2E profile 2 and
SecOC put them, the model's shapes agree with the signals and its faults are observable.
Every rig is checked alike, our own bus's too. Builds what the monitor runs with: the frame
decoder (`MotorDatabase` only for a rig that says exactly what it implements, a `RigCodec`
reading every key for any other) and the discrete model."""

from __future__ import annotations

import copy
import functools
import logging
import re
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Final

import numpy as np
from cantools.database.can import Database, Message, Signal

from monitor.bus.codec import MotorDatabase
from monitor.bus.errors import CodecError, SecOCError
from monitor.bus.rigcodec import (
    Resolver,
    RigCodec,
    RigMessage,
    RigSecOC,
    RigSync,
    load_rig_dbcs,
)
from monitor.bus.secoc import SecOCLayout, SyncLayout
from monitor.errors import MonitorError, one_line
from monitor.estimation.friction import Friction
from monitor.estimation.model import (
    BIAS_WINDOW_S,
    ContinuousDescriptor,
    DCMotorParameters,
    ModelError,
    dc_motor,
    model_from_matrices,
)
from monitor.rig.errors import RigError
from monitor.rig.spec import ProtectionSpec, Rig, SignalRef, builtin_rig, model_of

__all__ = ["build_decoder", "build_model", "builtin_difference", "check_rig", "is_builtin_bus",
           "signal_units", "unit_factor"]

log = logging.getLogger(__name__)

Fail = Callable[[str, str], MonitorError]
_SUFFIX = re.compile(r"^(?P<name>.+)_N(?P<node>\d{1,3})$")
MAX_NODES = 256


@functools.cache
def _units():  # type: ignore[no-untyped-def]
    import pint  # 0.6 s with its registry: not for the built-in rig (plain V and A)

    return pint.UnitRegistry()


_PLAIN: Final = frozenset({"V", "A"})
"""Units taken as known without pint: the built-in rig's, so that it starts without it."""
_NO_UNIT: Final = frozenset({"", "-"})
"""What a DBC writes for a signal without a unit ("-" is the editors' convention)."""


def _written(unit: str | None) -> str | None:
    """A unit as the DBC or the rig writes it; None where it gives none."""
    if unit is None or unit.strip() in _NO_UNIT:
        return None
    return unit.strip()


def _unknown(unit: str) -> str | None:
    """Why pint cannot read `unit` (None: it can)."""
    if unit in _PLAIN:
        return None
    try:
        _units().parse_units(unit)
    except Exception as exc:  # pint: UndefinedUnitError, or a syntax its parser rejects
        return f"pint: {one_line(exc) or type(exc).__name__}"
    return None


def motion_of(unit: str | None) -> str | None:
    """What a unit says of a drive's motion, for the friction's speed
    (`monitor.estimation.friction`): "output" for a speed (rad/s, rpm, m/s: an inverse time
    or a length per time), "rate" for a position (an angle -- dimensionless in pint -- or a
    length), None for anything else (a current, a torque) or no unit."""
    written = _written(unit)
    if written is None or written in _PLAIN or _unknown(written) is not None:
        return None
    dim = dict(_units().parse_units(written).dimensionality)
    if dim in ({"[time]": -1.0}, {"[length]": 1.0, "[time]": -1.0}):
        return "output"
    if dim in ({}, {"[length]": 1.0}):
        return "rate"
    return None


def unit_factor(dbc_unit: str | None, model_unit: str | None) -> float:
    """The factor from a DBC signal's unit to the unit the model wants (pint); 1 where
    either is missing or they are the same. `ValueError` (one line) if the two do not
    convert or the conversion has an offset (degC to K is not a scale)."""
    dbc, model = _written(dbc_unit), _written(model_unit)
    if dbc is None or model is None or dbc == model:
        return 1.0
    ureg = _units()
    try:
        q = ureg.Quantity(1.0, dbc).to(model)
        zero = ureg.Quantity(0.0, dbc).to(model)
    except Exception as exc:  # pint: undefined unit, dimensionality error
        raise ValueError(f"cannot convert {dbc!r} to {model!r}: {one_line(exc)}") from None
    if abs(float(zero.magnitude)) > 1e-12:
        raise ValueError(f"{dbc!r} to {model!r} has an offset (not a scale)")
    return float(q.magnitude)


@dataclass(frozen=True)
class _Want:
    """The unit a model takes a signal in, where the model fixes it."""

    unit: str  # pint's spelling
    what: str  # the rule, as an error says it


_DC_INPUT: Final = _Want("V", "a dc_motor model's input is a voltage in V (its parameters "
                              "are SI)")
_DC_OUTPUT: Final = _Want("A", "a dc_motor model's output is a current in A (its "
                               "parameters are SI)")
_TRUTH: Final = _Want("dimensionless", "the truth is gamma, a plain fraction 0..1 shown "
                                       "beside gamma^ as it comes")

_told: set[tuple[str, str]] = set()
"""(rig, what) already logged: each rig is checked at load and again for each decoder."""


def _tell_once(rig: Rig, what: str) -> None:
    shown = str(rig.source) if rig.source is not None else "<built-in rig>"
    if (shown, what) not in _told:
        _told.add((shown, what))
        log.info("rig file %s: %s", shown, what)


def _signal_factor(rig: Rig, m: Message, sig: Signal, ref: SignalRef, key: str,
                   want: _Want | None, fail: Fail) -> float:
    """The factor from `sig`'s DBC unit to the model's, every unit checked: the rig's and
    the DBC's parse, convert into each other, and suit the model (`want`). Where the DBC
    gives no unit the rig's is taken (logged once); where the rig gives none, the DBC's."""
    mine, dbc = _written(ref.unit), _written(sig.unit)
    where = f"{m.name}.{sig.name}"
    if mine is not None and (problem := _unknown(mine)) is not None:
        raise fail(f"{key}.unit", f"{mine!r} is not a unit ({problem})")
    if dbc is not None and (problem := _unknown(dbc)) is not None:
        raise fail(f"{key}.unit" if mine else f"{key}.signal",
                   f"{where} has the unit {dbc!r} in the DBC, which is not a unit ({problem}); "
                   f"the rig's is {repr(mine) if mine else 'not given'}")
    factor = 1.0
    if mine is not None and dbc is not None:
        try:
            factor = unit_factor(dbc, mine)
        except ValueError as exc:
            raise fail(f"{key}.unit", f"{exc} ({where}: {dbc!r} in the DBC, {mine!r} in the "
                       "rig)") from None
    elif mine is not None:
        _tell_once(rig, f"{key}: {where} has no unit in the DBC; taken as the rig's {mine!r}")
    model = mine or dbc
    if want is None:
        return factor
    if model is None:
        if want is not _TRUTH:
            _tell_once(rig, f"{key}: {where} has no unit in the DBC or the rig; "
                            f"taken as {want.unit}")
        return factor
    taken = "" if mine else " (the DBC's)"
    try:
        scale = 1.0 if model == want.unit else unit_factor(model, want.unit)
    except ValueError:
        raise fail(f"{key}.unit", f"{want.what}, not {model!r}{taken}") from None
    if abs(scale - 1.0) > 1e-12:
        fix = "" if want is _TRUTH else f': give unit = "{want.unit}"' + (
            f" (the DBC's {dbc!r} are converted)" if dbc and dbc != want.unit else "")
        raise fail(f"{key}.unit", f"{want.what}, not {model!r}{taken}{fix}")
    return factor


def builtin_difference(rig: Rig) -> str | None:
    """The first key where `rig` describes its bus otherwise than the built-in rig, which
    is exactly what `MotorDatabase` implements (None: nowhere). Compared: the DBC count,
    the layout, the signals, the truth, the protection and SecOC; units are compared by
    `build_decoder`, by their conversion, since that needs the DBC. (The nodes, the model,
    the rate and the diagnosis are the pipeline's, served alike by either decoder.)"""
    ours = builtin_rig()
    if len(rig.dbc) != len(ours.dbc):
        return "bus.dbc"
    if rig.layout != ours.layout:
        return "bus.layout"
    for group in ("inputs", "outputs"):
        mine, theirs = getattr(rig, group), getattr(ours, group)
        if len(mine) != len(theirs):
            return f"signals.{group}"
        for i, (a, b) in enumerate(zip(mine, theirs, strict=True)):
            for field in ("message", "signal"):
                if getattr(a, field) != getattr(b, field):
                    return f"signals.{group}[{i}].{field}"
    if rig.truth is None or ours.truth is None:
        if rig.truth is not ours.truth:
            return "signals.truth"
    else:
        for field in ("message", "signal"):
            if getattr(rig.truth, field) != getattr(ours.truth, field):
                return f"signals.truth.{field}"

    def stated(p: Rig) -> dict[str, ProtectionSpec]:  # kind = "none" is the default
        return {k: v for k, v in p.protection.items() if v != ProtectionSpec()}

    mine_p, ours_p = stated(rig), stated(ours)
    for name in sorted(set(mine_p) | set(ours_p)):
        if mine_p.get(name) != ours_p.get(name):
            return f"protection.{name}"
    if rig.secoc != ours.secoc:
        return "secoc"
    return None


def is_builtin_bus(rig: Rig) -> bool:
    """Whether `rig` describes our own bus as the built-in rig does (`builtin_difference`;
    `build_decoder` then also needs the units to convert with factor 1 to serve it with
    `MotorDatabase`: SecOC, MonitorDiagnosis frames)."""
    return builtin_difference(rig) is None


def _resolver(rig: Rig, db: Database, fail: Fail) -> tuple[Callable[[str, int],
                                                                    tuple[Message, int] | None],
                                                           list[int]]:
    """How rig messages map to DBC messages per node, and the nodes the DBC has."""
    by_name = {m.name: m for m in db.messages}
    lay = rig.layout
    if lay.kind == "name_suffix":
        nodes_of: dict[str, set[int]] = {}
        for m in db.messages:
            hit = _SUFFIX.match(m.name)
            if hit:
                nodes_of.setdefault(hit["name"], set()).add(int(hit["node"]))
        for name in rig.bus_messages:
            if name not in nodes_of:
                raise fail(_key_of(rig, name), f"no message {name}_N<node> in the DBC")
        nodes = sorted(set.union(*(nodes_of[n] for n in rig.messages)))

        def resolve(name: str, node: int) -> tuple[Message, int] | None:
            m = by_name.get(f"{name}_N{node}")
            return None if m is None else (m, m.frame_id)

        return resolve, nodes
    if lay.kind == "id_bits":
        mask = (1 << lay.bits) - 1
        for name in rig.bus_messages:
            found = by_name.get(name)
            if found is None:
                raise fail(_key_of(rig, name), f"no message {name} in the DBC")
            m = found
            if (m.frame_id >> lay.shift) & mask:
                raise fail("bus.node_bits", f"{name} has ID 0x{m.frame_id:X}, whose node bits "
                           "are not 0: list node 0's messages in the DBC")
            limit = (1 << 29) if m.is_extended_frame else (1 << 11)
            if (mask << lay.shift) >= limit:
                raise fail("bus.node_bits", f"node bits beyond {name}'s "
                           f"{'29' if m.is_extended_frame else '11'}-bit ID")
        copies: dict[tuple[str, int], Message] = {}

        def resolve_bits(name: str, node: int) -> tuple[Message, int] | None:
            m = by_name[name]
            if node > mask:
                return None
            msg = copies.setdefault((name, node), copy.copy(m))
            return msg, m.frame_id | (node << lay.shift)

        return resolve_bits, list(range(mask + 1))
    # explicit
    for node, table in lay.explicit.items():
        for name in rig.bus_messages:
            if name not in table:
                raise fail(f"bus.node_messages.{node}", f"no entry for rig message {name}")
            if table[name] not in by_name:
                raise fail(f"bus.node_messages.{node}.{name}",
                           f"no message {table[name]} in the DBC")

    def resolve_explicit(name: str, node: int) -> tuple[Message, int] | None:
        table = lay.explicit.get(node)
        if table is None:
            return None
        m = by_name[table[name]]
        return m, m.frame_id

    return resolve_explicit, sorted(lay.explicit)


def _key_of(rig: Rig, message: str) -> str:
    if rig.secoc is not None and message == rig.secoc.message and message not in rig.messages:
        return "secoc.sync"
    for group, refs in (("inputs", rig.inputs), ("outputs", rig.outputs)):
        for i, r in enumerate(refs):
            if r.message == message:
                return f"signals.{group}[{i}].message"
    return "signals.truth.message"


def _rig_messages(rig: Rig, sample: Callable[[str], Message],
                  streams: dict[str, tuple[int, str]], fail: Fail) -> list[RigMessage]:
    """Each rig message's reading instructions, checked against a DBC message of it
    (`streams`: `_streams` of the rig)."""
    out = []
    for name in rig.messages:
        m = sample(name)
        sigs = {s.name: s for s in m.signals}

        def factor(ref: SignalRef, key: str, want: _Want | None, m: Message = m,
                   sigs: dict[str, Signal] = sigs) -> float:
            if ref.signal not in sigs:
                raise fail(f"{key}.signal", f"{m.name} has no signal {ref.signal} (it has "
                           f"{', '.join(sorted(sigs))})")
            return _signal_factor(rig, m, sigs[ref.signal], ref, key, want, fail)

        dc = rig.model is not None and rig.model.kind == "dc_motor"
        inputs = tuple((i, r.signal, factor(r, f"signals.inputs[{i}]", _DC_INPUT if dc else None))
                       for i, r in enumerate(rig.inputs) if r.message == name)
        outputs = tuple((r.signal, factor(r, f"signals.outputs[{i}]",
                                          _DC_OUTPUT if dc else None))
                        for i, r in enumerate(rig.outputs) if r.message == name)
        truth = None
        if rig.truth is not None and rig.truth.message == name:
            factor(rig.truth, "signals.truth", _TRUTH)  # 1: the codecs pass the truth as is
            truth = rig.truth.signal
        prot = rig.protection.get(name)
        e2e = prot is not None and prot.kind == "e2e_profile2"
        if e2e:
            assert prot is not None and prot.counter is not None and prot.crc is not None
            for field, signal in (("crc", prot.crc), ("counter", prot.counter)):
                if signal not in sigs:
                    raise fail(f"protection.{name}.{field}", f"{m.name} has no signal {signal} "
                               f"(it has {', '.join(sorted(sigs))})")
            crc, cnt = sigs[prot.crc], sigs[prot.counter]
            if (crc.start, crc.length, crc.byte_order) != (0, 8, "little_endian"):
                raise fail(f"protection.{name}.crc", f"{m.name}: E2E profile 2 needs the CRC "
                           "(8 bits) in byte 0")
            if (cnt.start, cnt.length, cnt.byte_order) != (8, 4, "little_endian"):
                raise fail(f"protection.{name}.counter", f"{m.name}: E2E profile 2 needs the "
                           "alive counter in the low nibble of byte 1")
        out.append(RigMessage(name, inputs, outputs, truth, e2e,
                              prot.counter if e2e and prot else None,
                              prot.crc if e2e and prot else None,
                              prot.data_id if prot else None,
                              _secoc(rig, name, m, e2e, streams, fail)))
    for name in rig.protection:
        if name not in rig.messages:
            raise fail(f"protection.{name}", "not a message of the rig's signals")
    return out


def _streams(rig: Rig, fail: Fail) -> dict[str, tuple[int, str]]:
    """Each secured rig message's SyncKind and stream name (its name in lower case: the
    freshness counters' ``rx/<stream>/<node>``), checked to be distinct."""
    secured = [n for n in rig.messages
               if (p := rig.protection.get(n)) is not None and p.secoc is not None]
    out: dict[str, tuple[int, str]] = {}
    for i, name in enumerate(secured):
        sec = rig.protection[name].secoc
        assert sec is not None
        kind = i if sec.sync_kind is None else sec.sync_kind
        stream = re.sub(r"[^a-z0-9_]", "_", name.lower())
        stream = stream if stream[:1].isalpha() else "m" + stream
        for other, (k, st) in out.items():
            if k == kind:
                raise fail(f"protection.{name}.secoc.sync_kind", f"SyncKind {kind} is "
                           f"{other}'s too: give each secured message its own")
            if st == stream:
                raise fail(f"protection.{name}", f"{name} and {other} have the same name in "
                           "lower case (their freshness counters would share a name)")
        out[name] = (kind, stream)
    return out


def _secoc(rig: Rig, name: str, m: Message, e2e: bool, streams: dict[str, tuple[int, str]],
           fail: Fail) -> RigSecOC | None:
    """Rig message `name`'s SecOC, its signals and their places checked in `m`."""
    prot = rig.protection.get(name)
    if prot is None or prot.secoc is None:
        return None
    assert rig.secoc is not None  # the loader requires [secoc] for a secured message
    sec, key = prot.secoc, f"protection.{name}.secoc"
    sigs = {s.name: s for s in m.signals}
    for field, signal in (("freshness", sec.freshness), ("authenticator", sec.authenticator)):
        if signal not in sigs:
            raise fail(f"{key}.{field}", f"{m.name} has no signal {signal}")
    try:  # the data ID is each node's frame ID (the codec's); its place is checked here
        SecOCLayout.from_signals(m, sigs[sec.freshness], sigs[sec.authenticator], data_id=0,
                                 freshness_bits=rig.secoc.freshness_length, crc_byte=e2e)
    except SecOCError as exc:
        raise fail(key, str(exc)) from None
    kind, stream = streams[name]
    return RigSecOC(sec.freshness, sec.authenticator, rig.secoc.freshness_length, kind, stream)


def _sync(rig: Rig, m: Message, streams: dict[str, tuple[int, str]], fail: Fail) -> RigSync:
    """The rig's sync message, its signals and their places checked in `m`."""
    s = rig.secoc
    assert s is not None
    if s.message in rig.messages:
        raise fail("secoc.sync", f"{s.message} carries the model's signals; the sync message "
                   "must be a message of its own")
    sigs = {x.name: x for x in m.signals}
    for field in ("kind", "freshness", "authenticator"):
        if getattr(s, field) not in sigs:
            raise fail(f"secoc.{field}", f"{m.name} has no signal {getattr(s, field)}")
    try:
        layout = SyncLayout.from_signals(m, sigs[s.kind], sigs[s.freshness],
                                         sigs[s.authenticator], data_id=0,
                                         freshness_bits=s.freshness_length)
    except SecOCError as exc:
        raise fail("secoc", str(exc)) from None
    top = max(k for k, _ in streams.values())
    if top >> layout.kind_bits:
        raise fail("secoc.kind", f"{m.name}.{s.kind} has {layout.kind_bits} bit(s), too few "
                   f"for SyncKind {top}")
    return RigSync(s.message, s.kind, s.freshness, s.authenticator, s.freshness_length)


@dataclass(frozen=True)
class _Bus:
    """A rig's bus checked against its DBC: what `RigCodec` is built from."""

    messages: list[RigMessage]
    resolve: Resolver
    nodes: list[int]
    sync: RigSync | None

    def scaled(self) -> str | None:
        """The first signal whose values the decoder scales to the model's unit (its key),
        None if every factor is 1: what `MotorDatabase`, which never scales, can serve."""
        for m in self.messages:
            for i, _, f in m.inputs:
                if f != 1.0:
                    return f"signals.inputs[{i}].unit (the DBC's values scaled)"
            for j, (_, f) in enumerate(m.outputs):  # every output is in this one message
                if f != 1.0:
                    return f"signals.outputs[{j}].unit (the DBC's values scaled)"
        return None


def _load(rig: Rig, fail: Fail) -> Database:
    """The rig's DBC files as one database (a mistake: one line on bus.dbc); a CANopen
    rig's PDOs as the same description (`monitor.bus.canopen`)."""
    if rig.canopen is not None:
        from monitor.rig.canopen import canopen_database, file_key  # CANopen rigs only

        try:
            return canopen_database(rig.canopen)
        except CodecError as exc:
            raise fail(file_key(rig.canopen), str(exc)) from None
    try:
        return load_rig_dbcs(rig.dbc)
    except CodecError as exc:
        if rig.source is None:  # the built-in rig with --dbc: the error names the file
            raise
        raise fail("bus.dbc", str(exc)) from None


def _check_bus(rig: Rig, db: Database, fail: Fail) -> _Bus:
    """Every rig's checks against its DBC, our own bus's too: messages and signals exist
    for the nodes, units parse, convert and suit the model, protection and SecOC signals
    sit where they must."""
    resolve, found = _resolver(rig, db, fail)
    nodes = list(rig.nodes) if rig.nodes is not None else found
    if not nodes:
        raise fail("bus.nodes", "the DBC holds the rig's messages for no node")

    def sample(name: str) -> Message:
        for n in nodes:
            hit = resolve(name, n)
            if hit is not None:
                return hit[0]
        raise fail(_key_of(rig, name), f"no {name} message for nodes {nodes}")

    streams = _streams(rig, fail)
    messages = _rig_messages(rig, sample, streams, fail)
    sync = None if rig.secoc is None else _sync(rig, sample(rig.secoc.message), streams, fail)
    return _Bus(messages, resolve, nodes, sync)


_OURS: Final = {"MonitorDiagnosis": "the monitor sends no MonitorDiagnosis frames",
                "SecOCSync": "our bus's SecOC is not verified"}


def _our_bus_extras(db: Database) -> dict[str, str]:
    """What `MotorDatabase` serves on this DBC and `RigCodec` does not (message name without
    the node -> what is lost), found by the names our DBC gives those messages (nothing
    for any other DBC)."""
    names = {hit["name"] for m in db.messages if (hit := _SUFFIX.match(m.name)) is not None}
    return {name: lost for name, lost in _OURS.items() if name in names}


def build_decoder(rig: Rig, *, secoc_key: bytes | None = None,
                  fail: Fail | None = None) -> MotorDatabase | RigCodec:
    """The frame decoder of the rig, after every rig's checks: `MotorDatabase` where the
    rig says exactly what it implements (our own bus as the built-in rig describes it, no
    unit scaled: `builtin_difference`), else a `RigCodec` reading every key of the rig."""
    fail = fail or _default_fail(rig)
    differs = builtin_difference(rig)
    db = _load(rig, fail)
    if differs is None:
        try:
            ours = MotorDatabase(db, str(rig.dbc[0]), secoc_key)
        except CodecError as exc:
            if rig.source is None:  # the built-in rig with --dbc: the error names the file
                raise
            raise fail("bus.dbc", str(exc)) from None
        differs = _check_bus(rig, db, fail).scaled()
        if differs is None:
            return ours
        db = _load(rig, fail)  # a copy without the AUTOSAR properties MotorDatabase attached
    bus = _check_bus(rig, db, fail)
    extras = _our_bus_extras(db)
    if secoc_key is not None and rig.secoc is None:
        ours_too = ("; our bus's own SecOC needs the bus described as the built-in rig "
                    f"(rigs/motor.toml) does, and this rig differs at {differs}"
                    if "SecOCSync" in extras else "")
        raise fail("secoc", "a SecOC key (--key) was given, but no message of the rig has "
                   f"SecOC (protection.<message>.secoc){ours_too}")
    if extras:
        _tell_once(rig, f"not our bus as the built-in rig describes it ({differs}): read by "
                        f"the rig codec, so {'; '.join(extras.values())}")
    try:
        codec = RigCodec(db, ", ".join(p.name for p in rig.dbc), bus.messages, bus.resolve,
                         bus.nodes, sync=bus.sync, secoc_key=secoc_key)
    except CodecError as exc:
        raise fail("bus", str(exc)) from None
    if rig.canopen is not None:  # the engines read what the drives say about themselves
        from monitor.rig.canopen import watch_canopen

        watch_canopen(codec, rig.canopen)
    return codec


def build_model(rig: Rig, fail: Fail | None = None) -> ContinuousDescriptor:
    """The rig's continuous model (`model.discretize(1 / rig.rate)` for the estimator); a
    rig without one is refused (`model_of`)."""
    fail = fail or _default_fail(rig)
    spec, rate = model_of(rig)
    try:
        if spec.kind == "dc_motor":
            params = replace(DCMotorParameters(), **spec.motor)
            return dc_motor(params, q=spec.process_noise, r=spec.output_sigma[0] ** 2,
                            speed_noise_ratio=spec.speed_noise_ratio)
        fr = spec.friction
        return model_from_matrices(
            domain=spec.domain, T=1.0 / rate, fault_inputs=spec.fault_inputs,
            friction=None if fr is None else Friction(
                B=np.asarray(fr.B, dtype=float), speed=fr.speed, output=fr.output,
                width=fr.width),
            state_names=spec.state_names or None,
            input_names=tuple(r.signal for r in rig.inputs),
            output_names=tuple(r.signal for r in rig.outputs),
            **{k: [list(r) for r in v] for k, v in spec.matrices.items()},
        ).continuous
    except ModelError as exc:  # exc.key "rate": the model is fine, not at this rate
        raise fail(f"model.{exc.key}" if exc.key else "model", str(exc)) from None


def check_rig(rig: Rig, fail: Fail) -> Rig:
    """Everything checked that can be before the bus opens; returns the rig (unit factors
    are recomputed by the decoder). A rig without a model (identify's input) has its bus
    checked; its model is checked once identify has learned it."""
    build_decoder(rig, fail=fail)
    if rig.model is None or rig.rate is None:
        return rig
    model = build_model(rig, fail)
    try:
        # the estimator's bias states (`[model] bias`): an explicit kind the outputs
        # cannot observe is refused here, in one line
        model.discretize(1.0 / rig.rate).bias_plan(rig.model.bias, BIAS_WINDOW_S)
    except ModelError as exc:
        raise fail(f"model.{exc.key}" if exc.key else "model", str(exc)) from None
    if model.B.shape[1] != len(rig.inputs) or model.C.shape[0] != len(rig.outputs):
        raise fail("model", f"the model has {model.B.shape[1]} input(s) and "
                   f"{model.C.shape[0]} output(s); the rig's signals name "
                   f"{len(rig.inputs)} and {len(rig.outputs)}")
    return rig


def _default_fail(rig: Rig) -> Fail:
    shown = str(rig.source) if rig.source is not None else "<built-in rig>"

    def fail(key: str, problem: str) -> MonitorError:
        return RigError(f"rig file {shown}: {key}: {problem}")

    return fail




def signal_units(rig: Rig) -> tuple[tuple[str | None, ...], tuple[str | None, ...]]:
    """The unit each model input and output is in (the decoder converts to it), as written:
    the rig's, else its DBC signal's, else the one a dc_motor model fixes (V, A), else None
    (a plain number). For naming what is exported (`monitor.sinks.samples`); the rig has
    been checked by then, so its DBC loads and has every signal."""
    fail = _default_fail(rig)
    db = _load(rig, fail)
    resolve, found = _resolver(rig, db, fail)
    nodes = list(rig.nodes) if rig.nodes is not None else found

    def dbc_unit(ref: SignalRef) -> str | None:
        for n in nodes:
            hit = resolve(ref.message, n)
            if hit is not None:
                sigs = {s.name: s for s in hit[0].signals}
                sig = sigs.get(ref.signal)
                return None if sig is None else _written(sig.unit)
        return None

    dc = rig.model is not None and rig.model.kind == "dc_motor"
    ins = tuple(_written(r.unit) or dbc_unit(r) or (_DC_INPUT.unit if dc else None)
                for r in rig.inputs)
    outs = tuple(_written(r.unit) or dbc_unit(r) or (_DC_OUTPUT.unit if dc else None)
                 for r in rig.outputs)
    return ins, outs
