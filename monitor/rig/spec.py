"""What a rig file describes, as plain immutable data (the loader is `monitor.rig.load`).

A rig is the bus and the plant in front of the monitor: which DBC files define the bus, how
a frame belongs to a node, which DBC signals are the model's inputs u and outputs y, how
each message is protected, the linear model of every node and the diagnosis settings.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from monitor.diagnosis.thresholds import DiagnosisSpec
from monitor.rig.errors import NO_MODEL, RigError

__all__ = ["CanopenSpec", "DiagnosisSpec", "LayoutSpec", "ModelSpec", "ObjectScale", "PdoSpec",
           "ProtectionSpec", "Rig", "SecOCSpec", "SignalRef", "SyncSpec", "builtin_rig",
           "model_of"]

LayoutKind = Literal["name_suffix", "id_bits", "explicit"]
ProtectionKind = Literal["none", "e2e_profile2"]
ModelKind = Literal["dc_motor", "state_space"]


@dataclass(frozen=True)
class SignalRef:
    """A DBC signal that is one of the model's inputs or outputs.

    `message` is the message's name as the DBC writes it for node 0 (layout id_bits), as
    the template for every node (layout name_suffix: ``<message>_N<node>``), or the key
    of the per-node table (layout explicit). `unit` is the model's unit; the decoder converts
    the DBC's physical value to it where the DBC's unit differs. Where the DBC gives no unit
    the rig's is the signal's; where the rig gives none, the DBC's is the model's. A
    `dc_motor` model takes its input in V and its output in A (its parameters are SI); the
    truth is a plain fraction, never scaled.
    """

    message: str
    signal: str
    unit: str | None = None


@dataclass(frozen=True)
class LayoutSpec:
    """How a frame belongs to a node.

    name_suffix: message names carry the node, ``<message>_N<node>`` (our DBC).
    id_bits: the node number is held in bits of the arbitration ID, ``node =
      (id >> shift) & (2**bits - 1)``; the DBC lists node 0's messages only (a node's ID is
      node 0's ID with those bits set); standard or 29-bit IDs.
    explicit: a table per node maps each message of the rig to that node's DBC message.
    """

    kind: LayoutKind = "name_suffix"
    shift: int = 0
    bits: int = 4
    explicit: Mapping[int, Mapping[str, str]] = field(default_factory=dict)


@dataclass(frozen=True)
class SecOCSpec:
    """A message authenticated with SecOC (`monitor.bus.secoc`: a truncated AES-CMAC over
    the frame and a freshness counter): the DBC signals that carry the truncated freshness
    value and the truncated MAC, and the SyncKind value of its stream in the rig's sync
    frames (None: its place among the rig's secured messages, from 0)."""

    freshness: str = "FreshnessValue"
    authenticator: str = "Authenticator"
    sync_kind: int | None = None


@dataclass(frozen=True)
class SyncSpec:
    """The rig's SecOC freshness synchronisation message (one per node, through the
    layout, like every rig message), its signals, and the full freshness length of every
    secured stream (bits, a multiple of 8)."""

    message: str
    kind: str = "SyncKind"
    freshness: str = "SyncFreshness"
    authenticator: str = "SyncAuthenticator"
    freshness_length: int = 64


@dataclass(frozen=True)
class ProtectionSpec:
    """How a message is protected: not at all, or AUTOSAR E2E profile 2 (CRC-8 over the
    payload and a data ID, a 4-bit alive counter); either with SecOC or without. `data_id`
    is an int, or None for our bus's rule ``frame_id & 0xFF``."""

    kind: ProtectionKind = "none"
    counter: str | None = None
    crc: str | None = None
    data_id: int | None = None
    secoc: SecOCSpec | None = None


@dataclass(frozen=True)
class FrictionSpec:
    """`[model.friction]` of a state_space model: Coulomb friction
    (`monitor.estimation.friction`): its column `B` (one number per state), the `speed` it
    follows ("output": the output is a speed; "rate": the output's rate of change, a
    position), the `output` it is read from (index) and the `width` within which it fades."""

    B: tuple[float, ...]
    speed: str
    output: int
    width: float


@dataclass(frozen=True)
class ModelSpec:
    """The plant model of every node: the DC motor's physical parameters (`dc_motor`), or
    matrices (`state_space`, continuous or discrete, descriptor E optional); `input_delay`:
    the estimator's step for output sample k takes the input held at sample k - input_delay
    (`monitor.pipeline.samples`); `input_window`: an input frame received less than this
    share of a period before an output frame is held from the next sample on (the same
    module, rule 1); `adaptive_noise`: the estimator learns output and process noise above
    R and Q from its innovations over `noise_window_s` (`monitor.estimation.kernel`, steps
    5b and 5c); `bias`: the estimator's bias states for a load or an offset the model
    lacks ("auto", "none", "input", "output"; `monitor.estimation.fuzzy_ukf`, step 8);
    `friction`: a state_space model's Coulomb friction (`FrictionSpec`), None without."""

    kind: ModelKind = "dc_motor"
    motor: Mapping[str, float] = field(default_factory=dict)  # J, b, Ke, Ki, Ra, La
    process_noise: float = 1.44
    speed_noise_ratio: float = 1.0
    output_sigma: tuple[float, ...] = (0.5,)
    domain: Literal["continuous", "discrete"] = "continuous"
    matrices: Mapping[str, tuple[tuple[float, ...], ...]] = field(default_factory=dict)
    fault_inputs: tuple[int, ...] | None = None  # None: every input
    state_names: tuple[str, ...] = ()
    input_delay: int = 0
    input_window: float = 0.0
    adaptive_noise: bool = True
    noise_window_s: float = 2.0
    bias: str = "auto"
    friction: FrictionSpec | None = None


@dataclass(frozen=True)
class PdoSpec:
    """A PDO's mapping and communication as the rig file sets them (`[bus.pdo.TPDO1]`),
    over what the EDS or DCF says; None: the file's. `objects`: (index, subindex) in
    order; `transmission`: the transmission type (1..240 every n-th SYNC, 254/255 on the
    event timer); `cob_id`: the COB-ID of node 1's PDO, the node's ID added for the others
    (the pre-defined connection set's rule)."""

    name: str  # "TPDO1".."TPDO512", "RPDO1".."RPDO512"
    enabled: bool | None = None
    objects: tuple[tuple[int, int], ...] | None = None
    transmission: int | None = None
    event_timer_ms: int | None = None
    cob_id: int | None = None


@dataclass(frozen=True)
class ObjectScale:
    """The scaling of an object's raw value to its physical value (`factor`, in `unit`),
    as the rig file sets it (`[bus.objects."0x606C"]`), over the EDS and CiA 402's."""

    factor: float | None = None
    unit: str | None = None


@dataclass(frozen=True)
class CanopenSpec:
    """A CANopen bus (`[bus] protocol = "canopen"`): the drive's EDS or DCF file, the node
    IDs, and what the rig file sets over the file: PDOs and the scaling of objects (keyed
    by (index, subindex)). The bus description the codec reads is built from it by
    `monitor.bus.canopen`."""

    file: Path
    nodes: tuple[int, ...]
    pdos: tuple[PdoSpec, ...] = ()
    objects: Mapping[tuple[int, int], ObjectScale] = field(default_factory=dict)


@dataclass(frozen=True)
class Rig:
    """A whole rig; `source` is the file it came from (None: the built-in default); `model`
    and `rate` are None for a rig whose model is still to be learned (`identify`'s input,
    `load_rig(model_optional=True)`; `model_of` refuses it elsewhere)."""

    dbc: tuple[Path, ...]
    layout: LayoutSpec
    inputs: tuple[SignalRef, ...]
    outputs: tuple[SignalRef, ...]
    truth: SignalRef | None
    protection: Mapping[str, ProtectionSpec]
    model: ModelSpec | None
    rate: float | None
    diagnosis: DiagnosisSpec
    nodes: tuple[int, ...] | None = None
    source: Path | None = None
    secoc: SyncSpec | None = None  # the sync message, when a message has SecOC
    canopen: CanopenSpec | None = None  # a CANopen bus: `dbc` then holds its EDS or DCF

    @property
    def messages(self) -> tuple[str, ...]:
        """The rig's messages (as the rig names them), inputs first, no repeats."""
        refs = (*self.inputs, *self.outputs, *(() if self.truth is None else (self.truth,)))
        return tuple(dict.fromkeys(r.message for r in refs))

    @property
    def bus_messages(self) -> tuple[str, ...]:
        """`messages` and the SecOC sync message: every message the layout resolves."""
        return self.messages + (() if self.secoc is None else (self.secoc.message,))

    @property
    def output_message(self) -> str:
        """The message whose arrival is one sample: it carries every output."""
        return self.outputs[0].message


def model_of(rig: Rig) -> tuple[ModelSpec, float]:
    """The rig's model and rate; one `RigError` line (`NO_MODEL`) for a rig whose model is
    still to be learned (`load_rig(model_optional=True)`)."""
    if rig.model is None or rig.rate is None:
        shown = str(rig.source) if rig.source is not None else "<rig>"
        raise RigError(f"rig file {shown}: model: {NO_MODEL}")
    return rig.model, rig.rate


def builtin_rig() -> Rig:
    """Our own bus and the paper's motor: what every command uses without --rig. The same
    rig is written out as rigs/motor.toml (a test keeps the two equal)."""
    # the codec (cantools) only when the built-in rig is asked for: the rig's data model
    # alone imports nothing of the bus
    from monitor.bus.codec import default_dbc_path

    return Rig(
        dbc=(default_dbc_path(),),
        layout=LayoutSpec("name_suffix"),
        inputs=(SignalRef("MotorVoltage", "VoltageCommand", "V"),),
        outputs=(SignalRef("MotorCurrent", "ArmatureCurrent", "A"),),
        truth=SignalRef("SimTruth", "TrueGamma"),
        protection={m: ProtectionSpec("e2e_profile2", "Counter", "CRC")
                    for m in ("MotorVoltage", "MotorCurrent")},
        model=ModelSpec(),
        rate=100.0,
        diagnosis=DiagnosisSpec(),
    )
