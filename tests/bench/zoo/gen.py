"""One random rig of the zoo: plant, bus, rig file, and the captures of its runs.

Everything is drawn from `numpy.random.default_rng(seed)`, so a rig is re-made from its
seed alone; the runs' own randomness (commands, noise, fault times) is drawn from
`default_rng([seed, run, node])`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import can
import numpy as np
from cantools.database.can import Message, Signal
from numpy.typing import NDArray

from .bus import (
    UNITS,
    MessageSpec,
    SignalEnc,
    build_database,
    check_packing,
    float_encoding,
    integer_encoding,
    pack,
    place,
    signal_entry,
    toml_str,
)
from .plant import (
    INPUT_KINDS,
    OUTPUT_KINDS,
    Drive,
    Plant,
    build,
    simulate,
    step_gamma,
    structures,
)

Array = NDArray[np.float64]

SUB = 4  # fine steps per output period: input frames may come at quarter periods
RATES = (50.0, 100.0, 200.0, 250.0, 500.0, 1000.0, 2000.0)
MAX_FRAMES_PER_S = 4500.0  # about 60 % of a 1 Mbit/s bus
IDENTIFY_S = 60.0

OUT_NAMES = ("Feedback", "Status", "AxisFb", "DriveStatus", "Measure", "Telemetry")
IN_NAMES = ("Command", "Setpoint", "AxisCmd", "DriveCmd", "Demand")
BOTH_NAMES = ("DriveFrame", "AxisCycle", "LoopData")
SIG_NAMES = {
    "voltage": ("VoltageCmd", "UCmd", "ArmatureVoltage", "VSet"),
    "current": ("CurrentCmd", "ISet", "IqRef", "CurrentDemand"),
    "torque": ("TorqueCmd", "TorqueRef", "TSet"),
}
OUT_SIG_NAMES = {
    "current": ("CurrentFb", "Iact", "PhaseCurrent", "CoilCurrent"),
    "speed": ("SpeedFb", "Velocity", "MotorSpeed", "WAct"),
    "position": ("PositionFb", "Angle", "Pos", "ShaftAngle"),
}
EXPLICIT_SUFFIXES = (("Left", "Right", "Rear"), ("_A", "_B", "_C"), ("Axis1", "Axis2", "Axis3"),
                     ("Lift", "Tilt", "Swing"))


@dataclass
class Timeline:
    """One capture: its name, length, the faulted node and gamma's steps."""

    name: str
    duration: float
    index: int
    faulted_node: int | None = None
    steps: list[tuple[float, float]] = field(default_factory=list)  # (t, gamma from t on)

    def gamma_at(self, t: Array) -> Array:
        return step_gamma(self.steps, t)


@dataclass
class Rig:
    seed: int
    rate: float
    plant: Plant
    nodes: list[int]
    layout: str
    node_bits: tuple[int, int] | None
    extended: bool
    msgs: list[MessageSpec]
    in_msg: MessageSpec
    out_msg: MessageSpec
    level: float
    amplitude: float
    clock_s: float
    excitation: str  # "prbs" or "steps"
    extras: list[str]
    sigma_ratio: float
    offset_ratio: float
    quant_ratio: float
    jitter: float  # output timestamp jitter, share of the period
    latency: float  # output frame after its sample, share of the period
    node_shift: dict[int, float]
    foreign: list[tuple[int, bool, float]]  # (id, extended, rate) frames no DBC names
    extra_msgs: list[Message]
    nodes_key: str  # how `[bus] nodes` is written
    sigma: float = 0.0  # sensor noise, SI (set once the healthy minute is simulated)
    offset: float = 0.0
    quantum: float = 0.0
    notes: list[str] = field(default_factory=list)
    # the healthy minute's PRBS takes two levels (the README asks for several: a user who
    # records a binary sequence anyway, each of whose rigs identify must refuse or get right)
    binary_prbs: bool = False

    @property
    def kinds(self) -> str:
        s = self.plant.structure
        return f"{s.in_kind}->{s.out_kind}"

    @property
    def period(self) -> float:
        return 1.0 / self.rate


def _pick(rng: np.random.Generator, seq: tuple[str, ...] | list[str]) -> str:
    return str(seq[int(rng.integers(0, len(seq)))])


def make_rig(seed: int, *, binary_prbs: bool = False) -> Rig:
    rng = np.random.default_rng(seed)
    rate = float(rng.choice(RATES, p=[0.12, 0.2, 0.14, 0.1, 0.16, 0.16, 0.12]))
    # -- plant
    while True:
        in_kind = _pick(rng, INPUT_KINDS)
        out_kind = _pick(rng, OUTPUT_KINDS)
        cands = structures(in_kind, out_kind)
        if cands:
            break
    orders = sorted({s.order for s in cands})
    order = int(rng.choice(orders))
    same = [s for s in cands if s.order == order]
    struct = same[int(rng.integers(0, len(same)))]
    plant = build(rng, struct, rate)
    extras: list[str] = []
    mech = struct.mech != "none"
    if mech and rng.random() < 0.35:
        plant.coulomb = float(rng.uniform(0.01, 0.05) * plant.torque_scale)
        extras.append("coulomb")
    if rng.random() < 0.4:
        plant.dead = int(rng.integers(1, 4))
        extras.append(f"dead{plant.dead}")
    plant.process_sigma = float(rng.uniform(0.001, 0.01) * plant.u_range)

    # -- operating point and excitation
    if plant.integrating:
        level = 0.0
        amplitude = float(rng.uniform(0.05, 0.3) * plant.u_range)
    else:
        level = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.2, 0.6) * plant.u_range)
        amplitude = float(rng.uniform(0.05, 0.2) * plant.u_range)
    if rng.random() < 0.3:
        # it bites on the excitation's peaks but takes at most ~8 % of the command there:
        # clipping more would itself be a loss of effectiveness the truth does not count
        plant.saturation = float((abs(level) + amplitude) * rng.uniform(0.92, 0.98))
        extras.append("sat")
    if mech and rng.random() < 0.25:
        plant.load_step = float(rng.uniform(0.05, 0.2) * plant.torque_scale
                                * (abs(level) + amplitude) / plant.u_range)
        extras.append("load")
    tau = plant.dominant_tau()
    clock_s = float(min(3.0, max(3.0 / rate, tau * rng.uniform(1.0, 3.0))))
    excitation = "prbs" if rng.random() < 0.6 else "steps"
    sigma_ratio = float(math.exp(rng.uniform(math.log(0.01), math.log(0.15))))
    offset_ratio = 0.0
    if rng.random() < 0.3:
        offset_ratio = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.005, 0.05))
        extras.append("offset")
    quant_ratio = 0.0
    if rng.random() < 0.3:
        quant_ratio = float(rng.uniform(0.3, 2.0))
        extras.append("quant")
    if rng.random() < 0.3:
        extras.append("foreign")

    # -- bus: layout and nodes
    layout = _pick(rng, ("id_bits", "name_suffix", "explicit"))
    extended = bool(rng.random() < 0.4)
    nnodes = int(rng.integers(1, 4))
    node_bits: tuple[int, int] | None = None
    if layout == "id_bits":
        count = int(rng.integers(2, 5))
        width = 29 if extended else 11
        first = int(rng.integers(0, width - count - 2))
        node_bits = (first, count)
        nodes = sorted(int(x) for x in rng.choice(1 << count, size=nnodes, replace=False))
    else:
        nodes = sorted(int(x) for x in rng.choice(16, size=nnodes, replace=False))

    # -- messages
    combined = bool(rng.random() < 0.3)
    in_period = SUB
    in_phase = 0
    if not combined:
        in_period = int(rng.choice([2, 4, 4, 8, 12, 20, 40]))
        while rate * SUB / in_period < 5.0:
            in_period //= 2
        in_phase = int(rng.integers(0, min(in_period, SUB)))
    # bus load: fewer nodes or a slower input if the bus would be too full
    while True:
        fps = len(nodes) * (rate + (0 if combined else rate * SUB / in_period))
        if fps <= MAX_FRAMES_PER_S:
            break
        if len(nodes) > 1:
            nodes = nodes[:-1]
        elif not combined and in_period < 8:
            in_period *= 2
        else:
            break
    out_kind_sig = SignalEnc(name=_pick(rng, OUT_SIG_NAMES[out_kind]), role="output", length=16,
                             is_float=False, is_signed=True, scale=1.0, offset=0.0,
                             minimum=0.0, maximum=0.0, bus_factor=1.0, dbc_unit=None,
                             model_unit=None)
    in_sig = SignalEnc(name=_pick(rng, SIG_NAMES[in_kind]), role="input", length=16,
                       is_float=False, is_signed=True, scale=1.0, offset=0.0, minimum=0.0,
                       maximum=0.0, bus_factor=1.0, dbc_unit=None, model_unit=None)
    for sig, kind in ((in_sig, in_kind), (out_kind_sig, out_kind)):
        _units(rng, sig, kind)
        sig.byte_order = "big_endian" if rng.random() < 0.5 else "little_endian"
    # the input's encoding is known now (its range); the output's once simulated
    u_span = 1.2 * plant.u_range * in_sig.bus_factor
    if rng.random() < 0.35:
        float_encoding(in_sig, u_span)
    else:
        q = plant.u_range * in_sig.bus_factor / float(2 ** rng.uniform(9, 14))
        if not integer_encoding(rng, in_sig, u_span, q, symmetric=True):
            float_encoding(in_sig, u_span)
    # a placeholder length for placement: 32 bits (re-placed once the output is encoded)
    out_kind_sig.length = 32
    out_kind_sig.is_float = bool(rng.random() < 0.35)
    fillers = [SignalEnc(name=_pick(rng, ("Mode", "Temperature", "Flags", "BusVoltage")),
                         role="filler", length=int(rng.choice([4, 8, 12])), is_float=False,
                         is_signed=False, scale=1.0, offset=0.0, minimum=0.0, maximum=0.0,
                         bus_factor=1.0, dbc_unit=None, model_unit=None)
               for _ in range(2)]
    for f in fillers:
        f.maximum = float((1 << f.length) - 1)
    if combined:
        key = _pick(rng, BOTH_NAMES)
        m = MessageSpec(key=key, signals=[in_sig, out_kind_sig, fillers[0]], extended=extended,
                        period=SUB, phase=0, is_output=True)
        msgs = [m]
        in_msg = out_msg = m
    else:
        out_msg = MessageSpec(key=_pick(rng, OUT_NAMES), signals=[out_kind_sig, fillers[0]],
                              extended=extended, period=SUB, phase=0, is_output=True)
        in_msg = MessageSpec(key=_pick(rng, IN_NAMES), signals=[in_sig, fillers[1]],
                             extended=extended, period=in_period, phase=in_phase)
        msgs = [in_msg, out_msg] if rng.random() < 0.5 else [out_msg, in_msg]
    for m in msgs:
        m.signals = [m.signals[int(i)] for i in rng.permutation(len(m.signals))]
    _names_and_ids(rng, msgs, nodes, layout, node_bits, extended)
    extra_msgs: list[Message] = []
    if rng.random() < 0.4:  # an unrelated message the DBC knows (sent at 10 Hz)
        fid = _free_id(rng, msgs, nodes, layout, node_bits, extended, [])
        extra_msgs.append(Message(frame_id=fid, name="Diagnostics", length=8, senders=["Drive"],
                                  signals=[Signal("ErrorCode", 0, 16), Signal("Uptime", 16, 32)],
                                  is_extended_frame=extended, strict=True))
    foreign: list[tuple[int, bool, float]] = []
    if "foreign" in extras:
        taken = [m.frame_id for m in extra_msgs]
        for _ in range(int(rng.integers(1, 3))):
            ext = bool(rng.random() < 0.5)
            fid = _free_id(rng, msgs, nodes, layout, node_bits, ext, taken)
            taken.append(fid)
            foreign.append((fid, ext, float(rng.choice([10.0, 20.0, 50.0, 100.0]))))
    nodes_key = "all" if layout != "id_bits" and rng.random() < 0.4 else "list"
    return Rig(
        seed=seed, rate=rate, plant=plant, nodes=nodes, layout=layout, node_bits=node_bits,
        extended=extended, msgs=msgs, in_msg=in_msg, out_msg=out_msg, level=level,
        amplitude=amplitude, clock_s=clock_s, excitation=excitation, extras=extras,
        sigma_ratio=sigma_ratio, offset_ratio=offset_ratio, quant_ratio=quant_ratio,
        jitter=float(rng.uniform(0.0, 0.03)), latency=float(rng.uniform(0.02, 0.2)),
        node_shift={n: float(rng.uniform(0.0, 1.0)) for n in nodes}, foreign=foreign,
        extra_msgs=extra_msgs, nodes_key=nodes_key, binary_prbs=binary_prbs)


def _units(rng: np.random.Generator, sig: SignalEnc, kind: str) -> None:
    """DBC unit (or none) and the rig's unit (or none); the bus's factor from SI."""
    units = UNITS[kind]
    names = sorted(units)
    if rng.random() < 0.2:
        sig.dbc_unit = None
        if rng.random() < 0.8:
            sig.model_unit = _pick(rng, names)
            sig.bus_factor = units[sig.model_unit]
        else:
            sig.model_unit = None
            sig.bus_factor = 1.0
    else:
        sig.dbc_unit = _pick(rng, names)
        sig.bus_factor = units[sig.dbc_unit]
        r = rng.random()
        if r < 0.3:
            sig.model_unit = sig.dbc_unit
        elif r < 0.7:
            sig.model_unit = _pick(rng, names)
        else:
            sig.model_unit = None


def _id_ok(fid: int, extended: bool) -> bool:
    return 0 < fid < ((1 << 29) if extended else (1 << 11))


def _names_and_ids(rng: np.random.Generator, msgs: list[MessageSpec], nodes: list[int],
                   layout: str, node_bits: tuple[int, int] | None, extended: bool) -> None:
    width = 29 if extended else 11
    taken: set[int] = set()
    if layout == "id_bits":
        assert node_bits is not None
        first, count = node_bits
        field_mask = ((1 << count) - 1) << first
        for m in msgs:
            while True:
                base = int(rng.integers(1, 1 << width)) & ~field_mask
                ids = {n: base | (n << first) for n in [0, *nodes]}
                if all(_id_ok(i, extended) for i in ids.values()) and not (
                        set(ids.values()) & taken):
                    break
            taken |= set(ids.values())
            m.frame_ids = ids
            m.dbc_names = {n: m.key for n in [0, *nodes]}
        return
    suffixes = EXPLICIT_SUFFIXES[int(rng.integers(0, len(EXPLICIT_SUFFIXES)))]
    for m in msgs:
        consecutive = rng.random() < 0.6
        while True:
            if consecutive:
                base = int(rng.integers(1, (1 << width) - 16))
                ids = {n: base + n for n in nodes}
            else:
                ids = {n: int(rng.integers(1, 1 << width)) for n in nodes}
            if len(set(ids.values())) == len(ids) and not (set(ids.values()) & taken):
                break
        taken |= set(ids.values())
        m.frame_ids = ids
        if layout == "name_suffix":
            m.dbc_names = {n: f"{m.key}_N{n}" for n in nodes}
        else:
            base_name = m.key
            m.dbc_names = {n: f"{base_name}{suffixes[i]}" for i, n in enumerate(nodes)}
            m.key = "Cmd" if m.key in IN_NAMES else ("Fb" if m.key in OUT_NAMES else "Cycle")


def _free_id(rng: np.random.Generator, msgs: list[MessageSpec], nodes: list[int], layout: str,
             node_bits: tuple[int, int] | None, extended: bool, taken: list[int]) -> int:
    """An ID no rig message of any possible node uses (nor the node field would map)."""
    width = 29 if extended else 11
    used = {i for m in msgs for i in m.frame_ids.values()} | set(taken)
    while True:
        fid = int(rng.integers(1, 1 << width))
        if fid in used:
            continue
        if layout == "id_bits" and node_bits is not None:
            first, count = node_bits
            mask = ((1 << count) - 1) << first
            if any((fid & ~mask) == m.frame_ids[0] for m in msgs):
                continue  # it would read as a rig message of some node
        return fid


# --------------------------------------------------------------------------- runs


def timelines(rig: Rig) -> list[Timeline]:
    """The healthy minute for identify, then the four scored runs."""
    rng = np.random.default_rng([rig.seed, 1000])
    out = [Timeline("identify", IDENTIFY_S, 0)]
    for i, name in enumerate(("loss30", "loss60", "outage", "healthy"), start=1):
        dur = float(round(rng.uniform(30.0, 45.0), 1))
        tl = Timeline(name, dur, i)
        if name != "healthy":
            tl.faulted_node = int(rng.choice(rig.nodes))
            t0 = float(round(rng.uniform(10.0, min(20.0, dur - 12.0)), 3))
            if name == "outage":
                t1 = float(round(t0 + rng.uniform(5.0, min(10.0, dur - t0 - 6.0)), 3))
                tl.steps = [(t0, 1.0), (t1, 0.0)]
            else:
                tl.steps = [(t0, 0.3 if name == "loss30" else 0.6)]
        out.append(tl)
    return out


@dataclass
class NodeRun:
    """One node's part of a capture: the commands on input frames, the noise-free output."""

    u_frames: Array  # command at each input frame, SI (as on the bus)
    y: Array  # noise-free output at each sample, SI
    y_free: Array  # the same run without the fault (for the detectability figure)
    load_changes: list[tuple[float, float]] = field(default_factory=list)  # (t, N*m)


def commands(rig: Rig, tl: Timeline, node: int) -> Array:
    """The command at each input frame of the run (not yet quantised)."""
    rng = np.random.default_rng([rig.seed, tl.index, node, 1])
    h = rig.period / SUB
    nfine = round(tl.duration * rig.rate) * SUB
    p = rig.in_msg.period
    nin = (nfine - rig.in_msg.phase + p - 1) // p
    clock = max(1, round(rig.clock_s / (p * h)))
    clock = max(clock, math.ceil(3 * SUB / p))
    vals = np.empty(nin)
    if tl.name == "identify" and rig.excitation == "prbs":
        k = 0
        if rig.binary_prbs:
            # a maximal-length 9-bit LFSR (x^9 + x^5 + 1), one bit per clock
            reg = int(rng.integers(1, 512))
            while k < nin:
                bit = ((reg >> 8) ^ (reg >> 4)) & 1
                reg = ((reg << 1) | bit) & 0x1FF
                vals[k:k + clock] = rig.level + rig.amplitude * (1.0 if bit else -1.0)
                k += clock
        else:
            # a multi-level PRBS, as the README asks a user to record: 3-7 levels evenly
            # spaced over the band (how many from a stream of its own: the rig's other
            # draws stay)
            levels = np.linspace(-1.0, 1.0,
                                 int(np.random.default_rng([rig.seed, 7]).integers(3, 8)))
            while k < nin:
                vals[k:k + clock] = rig.level + rig.amplitude * float(rng.choice(levels))
                k += clock
    else:  # random steps within the band, random holds of 0.5-2 clocks
        k = 0
        while k < nin:
            hold = max(1, round(clock * rng.uniform(0.5, 2.0)))
            vals[k:k + hold] = rig.level + rig.amplitude * rng.uniform(-1.0, 1.0)
            k += hold
    return vals


def simulate_run(rig: Rig, tl: Timeline, node: int, u_frames: Array) -> NodeRun:
    rng = np.random.default_rng([rig.seed, tl.index, node, 2])
    n_out = round(tl.duration * rig.rate)
    nfine = n_out * SUB
    h = rig.period / SUB
    p, ph = rig.in_msg.period, rig.in_msg.phase
    # hold each command from its frame's fine step on (the first one also before it)
    idx = np.clip((np.arange(nfine) - ph) // p, 0, u_frames.size - 1)
    u_fine = u_frames[idx]
    t_fine = np.asarray(np.arange(nfine) * h, dtype=np.float64)
    gamma = tl.gamma_at(t_fine) if tl.faulted_node == node else np.zeros(nfine)
    load = np.zeros(nfine)
    changes: list[tuple[float, float]] = []
    if rig.plant.load_step > 0:
        t = 0.0
        lvl = float(rng.uniform(-1, 1)) * rig.plant.load_step
        while t < tl.duration:
            t_next = t + float(rng.uniform(4.0, 12.0))
            load[(t_fine >= t) & (t_fine < t_next)] = lvl
            changes.append((round(t, 4), lvl))
            lvl = float(rng.uniform(-1, 1)) * rig.plant.load_step
            t = t_next
    proc_seed = int(rng.integers(0, 2**31))
    y = simulate(rig.plant, h, SUB, Drive(u_fine, gamma, load),
                 np.random.default_rng(proc_seed))
    if np.any(gamma > 0):
        y_free = simulate(rig.plant, h, SUB, Drive(u_fine, np.zeros(nfine), load),
                          np.random.default_rng(proc_seed))
    else:
        y_free = y
    return NodeRun(u_frames=u_frames, y=y, y_free=y_free, load_changes=changes)


def encode_output(rig: Rig, ys: list[Array]) -> None:
    """Sensor noise, offset and quantum from the healthy minute; the output's DBC encoding."""
    rng = np.random.default_rng([rig.seed, 2000])
    y_id = ys[0]
    swing = output_swing(rig, y_id)
    rig.sigma = max(rig.sigma_ratio * swing, 1e-9)
    rig.offset = rig.offset_ratio * max(float(np.max(np.abs(y_id))), swing)
    rig.quantum = rig.quant_ratio * rig.sigma
    sig = rig.out_msg.signal("output")
    assert sig is not None
    peak = max(float(np.max(np.abs(y))) for y in ys)
    span = (1.5 * peak + abs(rig.offset) + 8 * rig.sigma) * sig.bus_factor
    q = rig.sigma * sig.bus_factor * float(rng.uniform(0.05, 0.5))
    if sig.is_float or not integer_encoding(rng, sig, span, q, symmetric=False):
        float_encoding(sig, span)
    # place every message's signals now that all lengths are known
    for m in rig.msgs:
        while True:
            if any(place(rng, m.signals) for _ in range(50)):
                break
            fillers = [s for s in m.signals if s.role == "filler"]
            if not fillers:
                raise RuntimeError(f"seed {rig.seed}: cannot place the signals of {m.key}")
            m.signals.remove(fillers[0])  # no room left for it in 8 bytes


def output_swing(rig: Rig, y: Array) -> float:
    """How much the excitation moves the output: the rms change over one clock / sqrt 2.

    (The plain standard deviation would count an integrating plant's drift as signal.)
    """
    c = max(1, min(y.size // 4, round(rig.clock_s * rig.rate)))
    return float(np.std(y[c:] - y[:-c]) / math.sqrt(2.0))


def measured(rig: Rig, tl: Timeline, node: int, y: Array) -> Array:
    rng = np.random.default_rng([rig.seed, tl.index, node, 3])
    ym = y + rig.offset + rng.normal(0.0, rig.sigma, y.size)
    if rig.quantum > 0:
        ym = np.round(ym / rig.quantum) * rig.quantum
    return np.asarray(ym, dtype=np.float64)


def quantise_input(rig: Rig, u: Array) -> Array:
    sig = rig.in_msg.signal("input")
    assert sig is not None
    return sig.from_raw(sig.to_raw(u))


# --------------------------------------------------------------------------- files


def write_dbc(rig: Rig, path: Path) -> str:
    db = build_database(rig.msgs, rig.nodes, rig.layout, rig.extra_msgs)
    text = str(db.as_dbc_string())
    path.write_text(text)
    return text


def rig_toml(rig: Rig, dbc_name: str) -> str:
    """The rig file a user would write: no [model] (identify learns it)."""
    lines = [f"# zoo rig, seed {rig.seed}: {rig.kinds}, {rig.plant.structure.describe()}, "
             f"{rig.rate:g} Hz", "", "[bus]", f"dbc = {toml_str(dbc_name)}",
             f"layout = {toml_str(rig.layout)}"]
    if rig.layout == "id_bits":
        assert rig.node_bits is not None
        lines.append(f"node_bits = [{rig.node_bits[0]}, {rig.node_bits[1]}]")
    if rig.nodes_key == "all":
        lines.append('nodes = "all"')
    else:
        lines.append("nodes = [" + ", ".join(str(n) for n in rig.nodes) + "]")
    if rig.layout == "explicit":
        for n in rig.nodes:
            lines.append(f"[bus.node_messages.{n}]")
            for m in rig.msgs:
                lines.append(f"{m.key} = {toml_str(m.dbc_names[n])}")
    ins = rig.in_msg.signal("input")
    outs = rig.out_msg.signal("output")
    assert ins is not None and outs is not None
    lines += ["", "[signals]", f"inputs = [{signal_entry(rig.in_msg.key, ins)}]",
              f"outputs = [{signal_entry(rig.out_msg.key, outs)}]", ""]
    return "\n".join(lines)


def write_capture(rig: Rig, tl: Timeline, runs: dict[int, NodeRun], path: Path,
                  check: bool = False, db_text: str = "") -> int:
    """The candump -L log of one run (every node, fillers, foreign frames); frames written."""
    base_t = 1_760_000_000.0 + rig.seed * 1000.0 + tl.index * 100.0
    T = rig.period
    h = T / SUB
    times: list[Array] = []
    ids: list[NDArray[np.int64]] = []
    exts: list[NDArray[np.bool_]] = []
    datas: list[NDArray[np.uint8]] = []
    lens: list[int] = []
    for node, nr in runs.items():
        rng = np.random.default_rng([rig.seed, tl.index, node, 4])
        n_out = nr.y.size
        ym = measured(rig, tl, node, nr.y)
        shift = rig.node_shift[node] * T
        samples: dict[str, NDArray[np.uint8]] = {}
        raws_all: dict[str, dict[str, NDArray[np.int64]]] = {}
        for m in rig.msgs:
            if m.is_output:
                k = np.arange(n_out)
                t = k * T + rig.latency * T
                jit = np.clip(rng.normal(0.0, rig.jitter * T + 1e-12, n_out), -0.1 * T, 0.1 * T)
                t = t + jit
            else:
                nin = nr.u_frames.size
                t = (np.arange(nin) * m.period + m.phase) * h
                t = t + np.abs(rng.normal(0.0, rig.jitter * T + 1e-12, nin)).clip(0, 0.1 * T)
            n = t.size
            raws: dict[str, NDArray[np.int64]] = {}
            for sig in m.signals:
                if sig.role == "output":
                    raws[sig.name] = sig.to_raw(ym)
                elif sig.role == "input":
                    if m.is_output:  # combined frame: the command applied from this sample
                        fine = np.arange(n) * SUB
                        idx = np.clip((fine - rig.in_msg.phase) // rig.in_msg.period, 0,
                                      nr.u_frames.size - 1)
                        raws[sig.name] = sig.to_raw(nr.u_frames[idx])
                    else:
                        raws[sig.name] = sig.to_raw(nr.u_frames)
                else:
                    walk = np.cumsum(rng.integers(-1, 2, n)) + (1 << (sig.length - 1))
                    raws[sig.name] = np.clip(walk, 0, (1 << sig.length) - 1).astype(np.int64)
            payload = pack(m, raws, n)
            samples[m.key] = payload
            raws_all[m.key] = raws
            times.append(t + shift)
            ids.append(np.full(n, m.frame_ids[node], dtype=np.int64))
            exts.append(np.full(n, m.extended, dtype=bool))
            datas.append(payload)
            lens.append(n)
        if check:
            check_packing(db_text, rig.msgs, node, rig.layout, samples, raws_all)
    rng = np.random.default_rng([rig.seed, tl.index, 99])
    for em in rig.extra_msgs:
        t = np.arange(0.0, tl.duration, 0.1) + float(rng.uniform(0, 0.1))
        raw = rng.integers(0, 256, (t.size, 8)).astype(np.uint8)
        times.append(t)
        ids.append(np.full(t.size, em.frame_id, dtype=np.int64))
        exts.append(np.full(t.size, em.is_extended_frame, dtype=bool))
        datas.append(raw)
    for fid, ext, frate in rig.foreign:
        t = np.arange(0.0, tl.duration, 1.0 / frate) + float(rng.uniform(0, 1.0 / frate))
        raw = rng.integers(0, 256, (t.size, 8)).astype(np.uint8)
        times.append(t)
        ids.append(np.full(t.size, fid, dtype=np.int64))
        exts.append(np.full(t.size, ext, dtype=bool))
        datas.append(raw)
    t_all = np.concatenate(times)
    order = np.argsort(t_all, kind="stable")
    t_all = t_all[order] + base_t
    id_all = np.concatenate(ids)[order]
    ext_all = np.concatenate(exts)[order]
    data_all = np.concatenate(datas)[order]
    with can.CanutilsLogWriter(str(path), channel="can0") as writer:
        for j in range(t_all.size):
            writer.on_message_received(can.Message(
                timestamp=float(t_all[j]), arbitration_id=int(id_all[j]),
                is_extended_id=bool(ext_all[j]), dlc=8, data=data_all[j].tobytes(),
                channel="can0"))
    return int(t_all.size)


def identify_files(seed: int, d: Path, duration: float | None = None, *,
                   binary_prbs: bool = False) -> Rig:
    """Rig `seed`'s DBC, rig file (rig.dbc, rig.toml) and healthy minute (identify.log, or
    `duration` seconds of it) in directory `d`: what `identify` is given, without the
    scored runs (for tests of identify on one zoo rig)."""
    rig = make_rig(seed, binary_prbs=binary_prbs)
    tl = timelines(rig)[0]
    if duration is not None:
        tl = Timeline(tl.name, duration, tl.index)
    runs = {n: simulate_run(rig, tl, n, quantise_input(rig, commands(rig, tl, n)))
            for n in rig.nodes}
    encode_output(rig, [runs[n].y for n in rig.nodes])
    db_text = write_dbc(rig, d / "rig.dbc")
    (d / "rig.toml").write_text(rig_toml(rig, "rig.dbc"))
    write_capture(rig, tl, runs, d / "identify.log", db_text=db_text)
    return rig
