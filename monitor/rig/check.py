"""A rig checked against its DBC files and its model: messages and signals exist, units
convert, protection signals sit where AUTOSAR E2E profile 2 and SecOC put them, the model's shapes
agree with the signals and its faults are observable. Builds what the monitor runs with:
the frame decoder and the discrete model."""

from __future__ import annotations

import copy
import functools
import re
from collections.abc import Callable
from dataclasses import replace

from cantools.database.can import Database, Message, Signal

from monitor.bus.codec import MotorDatabase, load_database
from monitor.bus.errors import CodecError, SecOCError
from monitor.bus.rigcodec import RigCodec, RigMessage, RigSecOC, RigSync, load_rig_dbcs
from monitor.bus.secoc import SecOCLayout, SyncLayout
from monitor.errors import MonitorError
from monitor.estimation.model import ContinuousDescriptor, DCMotorParameters, ModelError, dc_motor
from monitor.rig.spec import Rig, SignalRef

__all__ = ["build_decoder", "build_model", "check_rig", "unit_factor"]

Fail = Callable[[str, str], MonitorError]
_SUFFIX = re.compile(r"^(?P<name>.+)_N(?P<node>\d{1,3})$")
MAX_NODES = 256


@functools.cache
def _units():  # type: ignore[no-untyped-def]
    import pint  # a 0.4 s import: only for rigs whose units differ from their DBC's

    return pint.UnitRegistry()


def unit_factor(dbc_unit: str | None, model_unit: str | None) -> float:
    """The factor from a DBC signal's unit to the unit the model wants (pint)."""
    if not model_unit or not dbc_unit or dbc_unit == model_unit:
        return 1.0
    ureg = _units()
    try:
        q = ureg.Quantity(1.0, dbc_unit).to(model_unit)
        zero = ureg.Quantity(0.0, dbc_unit).to(model_unit)
    except Exception as exc:  # pint: undefined unit, dimensionality error
        raise ValueError(f"cannot convert {dbc_unit!r} to {model_unit!r}: {exc}") from None
    if abs(float(zero.magnitude)) > 1e-12:
        raise ValueError(f"{dbc_unit!r} to {model_unit!r} has an offset (not a scale)")
    return float(q.magnitude)


def is_builtin_bus(rig: Rig) -> bool:
    """Our own bus: served by `MotorDatabase` (SecOC, MonitorDiagnosis frames)."""
    return (rig.layout.kind == "name_suffix"
            and [(r.message, r.signal) for r in rig.inputs] == [("MotorVoltage", "VoltageCommand")]
            and [(r.message, r.signal) for r in rig.outputs] == [("MotorCurrent",
                                                                    "ArmatureCurrent")]
            and len(rig.dbc) == 1)


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

        def factor(ref: SignalRef, key: str, m: Message = m,
                   sigs: dict[str, Signal] = sigs) -> float:
            if ref.signal not in sigs:
                raise fail(f"{key}.signal", f"{m.name} has no signal {ref.signal} (it has "
                           f"{', '.join(sorted(sigs))})")
            try:
                return unit_factor(sigs[ref.signal].unit, ref.unit)
            except ValueError as exc:
                raise fail(f"{key}.unit", str(exc)) from None

        inputs = tuple((i, r.signal, factor(r, f"signals.inputs[{i}]"))
                       for i, r in enumerate(rig.inputs) if r.message == name)
        outputs = tuple((r.signal, factor(r, f"signals.outputs[{i}]"))
                        for i, r in enumerate(rig.outputs) if r.message == name)
        truth = None
        if rig.truth is not None and rig.truth.message == name:
            factor(rig.truth, "signals.truth")
            truth = rig.truth.signal
        prot = rig.protection.get(name)
        e2e = prot is not None and prot.kind == "e2e_profile2"
        if e2e:
            assert prot is not None and prot.counter is not None and prot.crc is not None
            crc, cnt = sigs.get(prot.crc), sigs.get(prot.counter)
            if crc is None or (crc.start, crc.length, crc.byte_order) != (0, 8, "little_endian"):
                raise fail(f"protection.{name}.crc", f"{m.name}: E2E profile 2 needs the CRC "
                           "(8 bits) in byte 0")
            if cnt is None or (cnt.start, cnt.length, cnt.byte_order) != (8, 4,
                                                                          "little_endian"):
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


def build_decoder(rig: Rig, *, secoc_key: bytes | None = None,
                  fail: Fail | None = None) -> MotorDatabase | RigCodec:
    """The frame decoder of the rig: `MotorDatabase` for our own bus, else a `RigCodec`."""
    fail = fail or _default_fail(rig)
    if is_builtin_bus(rig):
        try:
            return load_database(rig.dbc[0], secoc_key=secoc_key)
        except CodecError as exc:
            if rig.source is None:  # our rig with --dbc: the error names the file already
                raise
            raise fail("bus.dbc", str(exc)) from None
    if secoc_key is not None and rig.secoc is None:
        raise fail("secoc", "a SecOC key (--key) was given, but no message of the rig has "
                   "SecOC (protection.<message>.secoc)")
    try:
        db = load_rig_dbcs(rig.dbc)
    except CodecError as exc:
        raise fail("bus.dbc", str(exc)) from None
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
    try:
        return RigCodec(db, ", ".join(p.name for p in rig.dbc), messages, resolve, nodes,
                        sync=sync, secoc_key=secoc_key)
    except CodecError as exc:
        raise fail("bus", str(exc)) from None


def build_model(rig: Rig, fail: Fail | None = None) -> ContinuousDescriptor:
    """The rig's continuous model (`model.discretize(1 / rig.rate)` for the estimator)."""
    fail = fail or _default_fail(rig)
    spec = rig.model
    try:
        if spec.kind == "dc_motor":
            params = replace(DCMotorParameters(), **spec.motor)
            return dc_motor(params, q=spec.process_noise, r=spec.output_sigma[0] ** 2,
                            speed_noise_ratio=spec.speed_noise_ratio)
        from monitor.estimation.model import model_from_matrices

        return model_from_matrices(
            domain=spec.domain, T=1.0 / rig.rate, fault_inputs=spec.fault_inputs,
            state_names=spec.state_names or None,
            input_names=tuple(r.signal for r in rig.inputs),
            output_names=tuple(r.signal for r in rig.outputs),
            **{k: [list(r) for r in v] for k, v in spec.matrices.items()},
        ).continuous
    except ModelError as exc:
        raise fail("model", str(exc)) from None


def check_rig(rig: Rig, fail: Fail) -> Rig:
    """Everything checked that can be before the bus opens; returns the rig (unit factors
    are recomputed by the decoder)."""
    build_decoder(rig, fail=fail)
    model = build_model(rig, fail)
    try:
        model.discretize(1.0 / rig.rate)
    except ModelError as exc:
        raise fail("model", str(exc)) from None
    if model.B.shape[1] != len(rig.inputs) or model.C.shape[0] != len(rig.outputs):
        raise fail("model", f"the model has {model.B.shape[1]} input(s) and "
                   f"{model.C.shape[0]} output(s); the rig's signals name "
                   f"{len(rig.inputs)} and {len(rig.outputs)}")
    return rig


def _default_fail(rig: Rig) -> Fail:
    shown = str(rig.source) if rig.source is not None else "<built-in rig>"

    def fail(key: str, problem: str) -> MonitorError:
        from monitor.rig.load import RigError

        return RigError(f"rig file {shown}: {key}: {problem}")

    return fail


