"""Reading a rig file (TOML) into a `Rig`, every key checked before the bus opens.

Each mistake is one `RigError` line naming the file, the key and what is wrong: an unknown
key, a value of the wrong type, a DBC that does not load, a message or signal the DBC does
not have, a unit that does not convert, a model whose shapes disagree or whose fault the
outputs cannot see. The format is explained key by key in docs/rig-file.md and in
the example rigs/motor.toml, which is the built-in default.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any, TypeVar

from monitor.estimation.friction import FRICTION_SPEEDS
from monitor.estimation.model import BIAS_MODES
from monitor.files import MIB, UserFileError, read_user_toml, shown_path, user_file_problem
from monitor.pipeline.samples import input_delay_problem, input_window_problem
from monitor.rig.check import check_rig
from monitor.rig.errors import NO_MODEL, RigError
from monitor.rig.spec import (
    CanopenSpec,
    DiagnosisSpec,
    FrictionSpec,
    LayoutSpec,
    ModelSpec,
    ProtectionSpec,
    Rig,
    SecOCSpec,
    SignalRef,
    SyncSpec,
    builtin_rig,
    model_of,
)

__all__ = ["MAX_RATE_HZ", "MIN_RATE_HZ", "NO_MODEL", "RigError", "builtin_rig", "load_rig",
           "model_of", "parse_rig", "rate_problem"]

T = TypeVar("T")

_MOTOR_KEYS = ("J", "b", "Ke", "Ki", "Ra", "La")
_MATRICES = ("E", "A", "B", "C", "D", "Q", "R")
RIG_FILE_LIMIT = 16 * MIB
"""The largest rig file read: room for the matrices of a model of a few hundred states
(a 200-state A is about 1 MB of TOML), far below what would exhaust the monitor."""


class _Table:
    """One TOML table being read: each key taken once; what is left over is unknown."""

    def __init__(self, data: Mapping[str, Any], where: str, fail: Callable[[str, str], RigError]
                 ) -> None:
        self.data = dict(data)
        self.where = where
        self.fail = fail

    def key(self, name: str) -> str:
        return f"{self.where}.{name}" if self.where else name

    def take(self, name: str, kind: type[T] | tuple[type, ...], default: Any = ...) -> Any:
        if name not in self.data:
            if default is ...:
                raise self.fail(self.key(name), "missing")
            return default
        value = self.data.pop(name)
        kinds = kind if isinstance(kind, tuple) else (kind,)
        if float in kinds and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if isinstance(value, bool) and bool not in kinds:
            raise self.fail(self.key(name), f"must be {_names(kinds)}, got a boolean")
        if not isinstance(value, kinds):
            raise self.fail(self.key(name), f"must be {_names(kinds)}, "
                                            f"got {type(value).__name__}")
        return value

    def number(self, name: str, default: float | None = None, *, positive: bool = False,
               at_least: float | None = None) -> float:
        value = self.take(name, float, ... if default is None else default)
        if not math.isfinite(value):
            raise self.fail(self.key(name), f"must be a finite number, got {value!r}")
        if positive and not value > 0:
            raise self.fail(self.key(name), f"must be > 0, got {value!r}")
        if at_least is not None and value < at_least:
            raise self.fail(self.key(name), f"must be >= {at_least:g}, got {value!r}")
        return float(value)

    def table(self, name: str, required: bool = False) -> _Table:
        value = self.take(name, dict, ... if required else {})
        return _Table(value, self.key(name), self.fail)

    def done(self) -> None:
        if self.data:
            extra = ", ".join(sorted(self.data))
            raise self.fail(self.key(next(iter(sorted(self.data)))),
                            f"unknown key (not one of the rig format's keys): {extra}")


def _names(kinds: tuple[type, ...]) -> str:
    words = {str: "a string", float: "a number", int: "an integer", list: "an array",
             dict: "a table", bool: "true or false"}
    return " or ".join(words.get(k, k.__name__) for k in kinds)


def load_rig(path: str | Path, *, model_optional: bool = False) -> Rig:
    """Read and check a rig file (DBC paths are relative to it). `model_optional`: a file
    without [model] is a rig whose model is still to be learned (`identify`'s input; its
    `Rig.model` and `Rig.rate` are None); without it such a file is refused in one line
    that says to run identify first."""
    p = Path(path)
    try:
        doc = read_user_toml(p, what="rig file", limit=RIG_FILE_LIMIT)
    except UserFileError as exc:
        raise RigError(str(exc)) from None
    return parse_rig(doc, source=p, model_optional=model_optional)


def parse_rig(doc: Mapping[str, Any], *, source: Path | None = None,
              model_optional: bool = False) -> Rig:
    """A `Rig` from a parsed TOML document; `source` names the file in errors and anchors
    relative DBC paths; `model_optional` as `load_rig`'s."""
    shown = str(source) if source is not None else "<rig>"

    def fail(key: str, problem: str) -> RigError:
        return RigError(f"rig file {shown}: {key}: {problem}")

    top = _Table(doc, "", fail)
    bus = top.table("bus", required=True)
    base = source.resolve().parent if source is not None else Path.cwd()
    protocol = bus.take("protocol", str, "dbc")
    canopen: CanopenSpec | None = None
    dbc: tuple[Path, ...]
    nodes: tuple[int, ...] | None
    if protocol == "canopen":
        from monitor.rig.canopen import canopen_bus  # the canopen library: CANopen rigs only

        canopen = canopen_bus(bus, base, fail)
        dbc, layout, nodes = (canopen.file,), LayoutSpec("name_suffix"), canopen.nodes
    elif protocol == "dbc":
        dbc_value = bus.take("dbc", (str, list))
        dbc_list = [dbc_value] if isinstance(dbc_value, str) else dbc_value
        if not dbc_list or not all(isinstance(d, str) for d in dbc_list):
            raise fail("bus.dbc", "must be a file name or an array of file names")
        dbc = tuple((base / d) for d in dbc_list)
        for i, d in enumerate(dbc):
            if (problem := user_file_problem(d)) is not None:
                raise fail(f"bus.dbc[{i}]" if isinstance(dbc_value, list) else "bus.dbc",
                           f"{shown_path(d)}: {problem}")
        layout = _layout(bus, fail)
        nodes = _nodes(bus.take("nodes", (str, list), "all"), fail)
    else:
        raise fail("bus.protocol", f"must be dbc or canopen, got {protocol!r}")
    bus.done()

    signals = top.table("signals", required=True)
    by_object = canopen is not None  # a CANopen signal names an object; its PDO is found
    inputs = _refs(signals, "inputs", fail, by_object)
    outputs = _refs(signals, "outputs", fail, by_object)
    truth_t = signals.take("truth", dict, None)
    truth = (None if truth_t is None
             else _ref(_Table(truth_t, "signals.truth", fail), by_object))
    signals.done()
    if canopen is not None:
        from monitor.rig.canopen import canopen_refs

        inputs, outputs, truth = canopen_refs(canopen, inputs, outputs, truth, fail)
    out_msgs = {r.message for r in outputs}
    if len(out_msgs) > 1:
        raise fail("signals.outputs", "every output must come in one message (the one whose "
                   f"arrival is a sample); got {', '.join(sorted(out_msgs))}")

    prot_t = top.table("protection")
    protection: dict[str, ProtectionSpec] = {}
    for name in list(prot_t.data):
        protection[name] = _protection(prot_t.table(name), fail)
    prot_t.done()
    secoc = _sync(top.take("secoc", dict, None), protection, fail)

    model: ModelSpec | None = None
    rate: float | None = None
    if "model" in top.data or not model_optional:
        if "model" not in top.data:
            raise fail("model", NO_MODEL)
        model_t = top.table("model", required=True)
        model, rate = _model(model_t, len(inputs), len(outputs), fail)
        model_t.done()

    diag_t = top.table("diagnosis")
    diagnosis = _diagnosis(diag_t, fail)
    diag_t.done()
    # without a model there is no rate yet: identify's rig is checked once it has one
    if rate is not None and diagnosis.silence_timeout_s <= SILENT_PERIODS / rate:
        # Otherwise the node would be declared silent (no_data) between two samples.
        raise fail("diagnosis.silence_timeout_s", f"{diagnosis.silence_timeout_s:g} s is not "
                   f"longer than {SILENT_PERIODS} sample periods at model.rate = {rate:g} Hz "
                   f"({SILENT_PERIODS / rate:g} s): give a longer timeout or a higher rate")
    top.done()
    rig = Rig(dbc=dbc, layout=layout, inputs=inputs, outputs=outputs, truth=truth,
              protection=protection, model=model, rate=rate, diagnosis=diagnosis,
              nodes=nodes, source=source, secoc=secoc, canopen=canopen)
    return check_rig(rig, fail)  # the DBC and the model, checked against the rig


def _layout(bus: _Table, fail: Callable[[str, str], RigError]) -> LayoutSpec:
    kind = bus.take("layout", str, "name_suffix")
    if kind == "name_suffix":
        return LayoutSpec("name_suffix")
    if kind == "id_bits":
        bits_value = bus.take("node_bits", list)
        if (len(bits_value) != 2 or not all(isinstance(v, int) and not isinstance(v, bool)
                                            for v in bits_value)):
            raise fail("bus.node_bits", "must be [first bit, number of bits], e.g. [5, 4]")
        shift, width = bits_value
        if not (0 <= shift <= 28 and 1 <= width <= 8 and shift + width <= 29):
            raise fail("bus.node_bits", f"bits {shift}..{shift + width - 1} do not fit a "
                       "29-bit ID with at most 8 node bits")
        return LayoutSpec("id_bits", shift=shift, bits=width)
    if kind == "explicit":
        table = bus.table("node_messages", required=True)
        explicit: dict[int, dict[str, str]] = {}
        for key in list(table.data):
            try:
                node = int(key)
            except ValueError:
                raise fail(f"bus.node_messages.{key}", "keys are node numbers") from None
            names = table.take(key, dict)
            if not all(isinstance(v, str) for v in names.values()):
                raise fail(f"bus.node_messages.{key}", "values must be DBC message names")
            explicit[node] = dict(names)
        if not explicit:
            raise fail("bus.node_messages", "needs one table per node")
        return LayoutSpec("explicit", explicit=explicit)
    raise fail("bus.layout", f"must be name_suffix, id_bits or explicit, got {kind!r}")


def _nodes(value: str | list[Any], fail: Callable[[str, str], RigError]
           ) -> tuple[int, ...] | None:
    if value == "all":
        return None
    if (not isinstance(value, list) or not value
            or not all(isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 256
                       for v in value)):
        raise fail("bus.nodes", "must be \"all\" or an array of node numbers 0..255")
    return tuple(sorted(set(value)))


def _ref(t: _Table, by_object: bool = False) -> SignalRef:
    """A signal reference; `by_object` (a CANopen rig): the message (the PDO) may be left
    out, `monitor.rig.canopen.canopen_refs` finds it."""
    message = t.take("message", str, "") if by_object else t.take("message", str)
    ref = SignalRef(message, t.take("signal", str), t.take("unit", str, None))
    t.done()
    return ref


def _refs(signals: _Table, name: str, fail: Callable[[str, str], RigError],
          by_object: bool = False) -> tuple[SignalRef, ...]:
    items = signals.take(name, list)
    if not items:
        raise fail(f"signals.{name}", "needs at least one signal")
    refs = []
    for i, item in enumerate(items):
        if not isinstance(item, dict):
            raise fail(f"signals.{name}[{i}]", "must be a table {message = ..., signal = ...}")
        refs.append(_ref(_Table(item, f"signals.{name}[{i}]", fail), by_object))
    return tuple(refs)


def _protection(t: _Table, fail: Callable[[str, str], RigError]) -> ProtectionSpec:
    kind = t.take("kind", str, "none")
    secoc_t = t.take("secoc", dict, None)
    secoc = None if secoc_t is None else _secoc(_Table(secoc_t, t.key("secoc"), fail))
    if kind == "none":
        spec = ProtectionSpec("none", secoc=secoc)
    elif kind == "e2e_profile2":
        data_id = t.take("data_id", (int, str), "id_low_byte")
        if data_id == "id_low_byte":
            did: int | None = None
        elif isinstance(data_id, int) and not isinstance(data_id, bool) and 0 <= data_id <= 255:
            did = data_id
        else:
            raise fail(t.key("data_id"), "must be \"id_low_byte\" or an integer 0..255")
        spec = ProtectionSpec("e2e_profile2", t.take("counter", str), t.take("crc", str), did,
                              secoc)
    else:
        raise fail(t.key("kind"), f"must be none or e2e_profile2, got {kind!r}")
    t.done()
    return spec


def _secoc(t: _Table) -> SecOCSpec:
    kind = t.take("sync_kind", int, None)
    if kind is not None and kind < 0:
        raise t.fail(t.key("sync_kind"), f"must be >= 0, got {kind}")
    spec = SecOCSpec(t.take("freshness", str, SecOCSpec.freshness),
                     t.take("authenticator", str, SecOCSpec.authenticator), kind)
    t.done()
    return spec


def _sync(doc: Mapping[str, Any] | None, protection: Mapping[str, ProtectionSpec],
          fail: Callable[[str, str], RigError]) -> SyncSpec | None:
    """The [secoc] table: needed exactly when a message has protection.<message>.secoc."""
    secured = [name for name, p in protection.items() if p.secoc is not None]
    if doc is None:
        if secured:
            raise fail("secoc.sync", f"missing: protection.{secured[0]}.secoc needs the "
                       "rig's SecOC sync message ([secoc] sync = \"<message>\")")
        return None
    t = _Table(doc, "secoc", fail)
    if not secured:
        raise fail("secoc", "no message is secured (protection.<message>.secoc): remove "
                   "[secoc] or secure a message")
    length = t.take("freshness_length", int, SyncSpec.freshness_length)
    if length % 8 or not 8 <= length <= 64:
        raise fail(t.key("freshness_length"), f"must be a multiple of 8 in 8..64, got {length}")
    spec = SyncSpec(t.take("sync", str), t.take("kind", str, SyncSpec.kind),
                    t.take("freshness", str, SyncSpec.freshness),
                    t.take("authenticator", str, SyncSpec.authenticator), length)
    t.done()
    return spec


def _matrix(t: _Table, name: str) -> tuple[tuple[float, ...], ...] | None:
    value = t.take(name, list, None)
    if value is None:
        return None
    rows = value if value and isinstance(value[0], list) else [value]
    out = []
    for r in rows:
        if not isinstance(r, list) or not all(
                isinstance(v, int | float) and not isinstance(v, bool) for v in r):
            raise t.fail(t.key(name), "must be a matrix: an array of arrays of numbers")
        out.append(tuple(float(v) for v in r))
    if len({len(r) for r in out}) > 1:
        raise t.fail(t.key(name), "rows of different lengths")
    return tuple(out)


# The output rates the monitor can use (model.rate, and --rate on the command line).
MIN_RATE_HZ = 0.2
"""A period of at most 5 s: the pipeline restarts a node's estimator after 5 s without a
sample (`MonitorConfig.max_gap_s`), so at a slower rate every sample would start afresh
and nothing would ever be estimated."""
MAX_RATE_HZ = 100_000.0
"""No CAN bus carries more samples a second (classic CAN at 1 Mbit/s about 20 000
frames/s, CAN FD below 100 000), and the estimator keys its steps by the microsecond."""


def rate_problem(rate: float) -> str | None:
    """What is wrong with an output rate in Hz for the monitor, None if nothing."""
    if not (math.isfinite(rate) and rate > 0):
        return f"must be a positive number of Hz, got {rate!r}"
    if rate < MIN_RATE_HZ:
        return (f"must be at least {MIN_RATE_HZ:g} Hz, got {rate:g}: a sample period above "
                f"{1 / MIN_RATE_HZ:g} s is a gap after which the monitor restarts the "
                "estimator, so no sample would ever be estimated")
    if rate > MAX_RATE_HZ:
        return (f"must be at most {MAX_RATE_HZ:g} Hz, got {rate:g}: no CAN bus carries more "
                "samples a second (about 20000 frames/s at 1 Mbit/s, CAN FD below 100000)")
    return None


def _model(t: _Table, m: int, p: int, fail: Callable[[str, str], RigError]
           ) -> tuple[ModelSpec, float]:
    kind = t.take("kind", str)
    rate = t.number("rate", positive=True)
    problem = rate_problem(rate)
    if problem is not None:
        raise fail("model.rate", problem)
    spec, rate = _model_kind(t, kind, rate, m, p, fail)
    delay = t.take("input_delay", int, 0)
    problem = input_delay_problem(delay)
    if problem is not None:
        raise fail("model.input_delay", problem)
    input_window = t.number("input_window", 0.0)
    problem = input_window_problem(input_window)
    if problem is not None:
        raise fail("model.input_window", problem)
    adaptive = t.take("adaptive_noise", bool, True)
    window = t.number("noise_window_s", 2.0, positive=True)
    bias = t.take("bias", str, "auto")
    if bias not in BIAS_MODES:
        raise fail("model.bias", f"must be one of {', '.join(BIAS_MODES)}, got {bias!r}")
    return replace(spec, input_delay=delay, input_window=input_window, adaptive_noise=adaptive,
                   noise_window_s=window, bias=bias), rate


def _model_kind(t: _Table, kind: str, rate: float, m: int, p: int,
                fail: Callable[[str, str], RigError]) -> tuple[ModelSpec, float]:
    if kind == "dc_motor":
        if "friction" in t.data:
            raise fail("model.friction", "only a state_space model has friction (its column "
                       "B gives one number per state)")
        if (m, p) != (1, 1):
            raise fail("model.kind", f"dc_motor has one input and one output; the rig "
                       f"names {m} input(s) and {p} output(s)")
        motor = {k: t.number(k) for k in _MOTOR_KEYS if k in t.data}
        q = t.number("process_noise", 1.44, at_least=0.0)
        kappa = t.number("speed_noise_ratio", 1.0, positive=True)
        sigma = t.number("output_sigma", 0.5, positive=True)
        return ModelSpec("dc_motor", motor=motor, process_noise=q, speed_noise_ratio=kappa,
                         output_sigma=(sigma,)), rate
    if kind == "state_space":
        domain = t.take("domain", str, "continuous")
        if domain not in ("continuous", "discrete"):
            raise fail("model.domain", f"must be continuous or discrete, got {domain!r}")
        matrices = {}
        for name in _MATRICES:
            mat = _matrix(t, name)
            if mat is not None:
                matrices[name] = mat
        for name in ("A", "B", "C", "Q", "R"):
            if name not in matrices:
                raise fail(f"model.{name}", "missing (state_space needs A, B, C, Q and R)")
        faults_value = t.take("fault_inputs", list, None)
        faults = None
        if faults_value is not None:
            if not all(isinstance(v, int) and not isinstance(v, bool) and 0 <= v < m
                       for v in faults_value) or not faults_value:
                raise fail("model.fault_inputs", f"must list input indices 0..{m - 1}")
            faults = tuple(sorted(set(faults_value)))
        names = t.take("states", list, [])
        if not all(isinstance(v, str) for v in names):
            raise fail("model.states", "must be an array of names")
        friction = _friction(t.table("friction"), p) if "friction" in t.data else None
        return ModelSpec("state_space", domain=domain,
                         matrices=matrices, fault_inputs=faults,
                         state_names=tuple(names), friction=friction), rate
    raise fail("model.kind", f"must be dc_motor or state_space, got {kind!r}")


def _friction(t: _Table, p: int) -> FrictionSpec:
    """`[model.friction]` (`FrictionSpec`); the length of B against the states is the
    model's check (`monitor.estimation.model`)."""
    b = t.take("B", list)
    if not b or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in b):
        raise t.fail(t.key("B"), "must be an array of numbers, one per state")
    speed = t.take("speed", str)
    if speed not in FRICTION_SPEEDS:
        raise t.fail(t.key("speed"), f"must be one of {', '.join(FRICTION_SPEEDS)}, got "
                     f"{speed!r}")
    output = t.take("output", int, 0)
    if not 0 <= output < p:
        raise t.fail(t.key("output"), f"must be an output index from 0 to {p - 1}, got "
                     f"{output}")
    width = t.number("width", positive=True)
    t.done()
    return FrictionSpec(B=tuple(float(v) for v in b), speed=speed, output=output,
                        width=width)


SILENT_PERIODS = 2
"""The silence timeout must span more than this many sample periods."""


def _diagnosis(t: _Table, fail: Callable[[str, str], RigError]) -> DiagnosisSpec:
    d = DiagnosisSpec()
    spec = DiagnosisSpec(
        f1=t.number("f1", d.f1), f2=t.number("f2", d.f2),
        dwell_s=t.number("dwell_s", d.dwell_s, at_least=0.0),
        hysteresis=t.number("hysteresis", d.hysteresis, at_least=0.0),
        significance=t.number("significance", d.significance, at_least=0.0),
        silence_timeout_s=t.number("silence_timeout_s", d.silence_timeout_s, positive=True),
        mismatch_window_s=t.number("mismatch_window_s", d.mismatch_window_s, positive=True),
        mismatch_dwell_s=t.number("mismatch_dwell_s", d.mismatch_dwell_s, positive=True),
        withhold_alarms_on_mismatch=t.take("withhold_alarms_on_mismatch", bool,
                                           d.withhold_alarms_on_mismatch),
    )
    if not 0.0 < spec.f1 < spec.f2 < 1.0:
        raise fail("diagnosis.f1", f"thresholds must satisfy 0 < f1 < f2 < 1, got "
                   f"f1 = {spec.f1:g}, f2 = {spec.f2:g}")
    if not spec.hysteresis < 0.5 * (spec.f2 - spec.f1):
        raise fail("diagnosis.hysteresis", "must be less than (f2 - f1) / 2")
    return spec
