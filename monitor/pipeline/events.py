"""What the pipeline hands to its sinks: typed, immutable events, nothing Rerun- or
CAN-specific. Each outlet (the Rerun recording, the diagnosis frames on the bus, JSON lines,
the log) is a `monitor.sinks.Sink` that takes the events it needs."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from typing import Final

import can
import numpy as np
from numpy.typing import NDArray

from monitor.bus.cia402 import DriveReport, report_level, report_text
from monitor.bus.faults import describe_error_frame
from monitor.diagnosis.classifier import HealthState

__all__ = ["DRIVE", "HEALTH", "MODEL_MISMATCH", "BusEvent", "Diagnosis", "DiagnosisEvent",
           "DriveEvent", "InputSample", "PlantSignals", "Sample", "SampleColumns",
           "drive_event"]


@dataclass(frozen=True)
class PlantSignals:
    """The names and units of a node's inputs and outputs, in the model's order: the rig's
    DBC signal names, each with its unit (None: a plain number). What the tuples of `Sample`
    and the index of `InputSample` refer to, for the outlets that name them (the recording's
    entities, the samples file's columns). The default is the built-in rig's, our bus (a test
    keeps the two equal)."""

    inputs: tuple[tuple[str, str | None], ...] = (("VoltageCommand", "V"),)
    outputs: tuple[tuple[str, str | None], ...] = (("ArmatureCurrent", "A"),)

    def input(self, i: int) -> tuple[str, str | None]:
        """Input `i`'s (name, unit); ``u<i+1>`` without a unit beyond the names given, so
        that a producer with more inputs than names still has every one named."""
        return self.inputs[i] if i < len(self.inputs) else (f"u{i + 1}", None)

    def output(self, j: int) -> tuple[str, str | None]:
        """Output `j`'s (name, unit); ``y<j+1>`` beyond the names given."""
        return self.outputs[j] if j < len(self.outputs) else (f"y{j + 1}", None)

    def fault_unit(self, fault_inputs: tuple[int, ...]) -> str | None:
        """The unit of the fault (`Diagnosis.fault_input`): the one unit of the inputs that
        may lose effectiveness, None if they have none or differ (the fault is the worst
        one's, which an event does not name)."""
        units = {self.input(i)[1] for i in fault_inputs}
        return units.pop() if len(units) == 1 else None


@dataclass(frozen=True, slots=True)
class Sample:
    """One estimator step of a node: the measured and estimated output, gamma^ (the
    estimated loss of effectiveness), the rule count, the reported health state, the
    normalised innovation squared and, from a virtual ECU, the true gamma.

    `measured`/`estimated` are the first output (what the recording plots); `inputs`
    (held at the sample), `outputs`, `predicted` (the estimate's outputs) and `gammas`
    (gamma^ per input, 0 for a known one) carry every signal of a multi-input
    multi-output rig, in the rig's order, for the samples file (empty where a producer
    fills none); `gamma_sd` is the standard deviation of `gamma` (NaN: none), which the
    diagnosis weighs an alarm by (`monitor.diagnosis.rules.cls_update`). `output_noise`
    (per output, in the rig's order; empty: none) and `process_noise` (NaN: none) are the
    noises the estimator has adapted to after the sample, as factors on its model's
    (`EstimatorOutput.output_noise`, `.process_noise`): 1 where the model's noise fits."""

    node: int
    t: float
    measured: float
    estimated: float
    gamma: float
    rules: int
    state: HealthState
    nis: float
    true_gamma: float | None = None
    model_mismatch: bool = False  # the node's flag after this step (`DiagnosisEvent`)
    inputs: tuple[float, ...] = ()
    outputs: tuple[float, ...] = ()
    predicted: tuple[float, ...] = ()
    gammas: tuple[float, ...] = ()
    gamma_sd: float = math.nan
    output_noise: tuple[float, ...] = ()
    process_noise: float = math.nan


@dataclass(frozen=True, slots=True)
class InputSample:
    """An input of a node as a frame carries it (the first input of the frame), at the
    frame's own rate: `index` says which input (`PlantSignals.inputs`), `value` is in its
    unit."""

    node: int
    t: float
    value: float
    index: int = 0


HEALTH: Final = "health"
"""`DiagnosisEvent.kind` of a change of the health state."""
MODEL_MISMATCH: Final = "model_mismatch"
"""`DiagnosisEvent.kind` of a change of the model-mismatch flag."""


@dataclass(frozen=True)
class DiagnosisEvent:
    """A change of a node's diagnosis: of its health state or of its model-mismatch flag
    (also written as a JSON line by `replay` and `--events`).

    Every event carries the node's state and flag after it (`state`, `model_mismatch`), so
    a reader of the events alone knows both at any time. `kind` says which changed:

    * ``"health"``: `previous` -> `state`; `cause` ``"estimate"`` (the classifier of (76)
      moved), ``"silence"`` (no frames for the silence timeout) or ``"model"`` (an alarm
      held while the flag was up, `reported_state`, reported as the flag falls).
    * ``"model_mismatch"``: the flag rose or fell (to `model_mismatch`); the state is
      unchanged (`previous` == `state`): the flag stands beside the diagnosis, it does not
      replace it. `cause` ``"nis"`` (the windowed NIS left its band, or came back, for the
      dwell: `MismatchDetector`), ``"silence"`` or ``"restart"`` (the estimator restarted
      after a gap or a numerical failure; the detector forgets its history with it).

    When both change at one sample, the flag's event comes first.

    `fault_input` is what `Diagnosis.fault_input` is, in `fault_input_unit`. A reader of
    an events file also takes the line of an older monitor, which names it ``fault_volts``
    and has no unit (`monitor.runtime.paths`).
    """

    t: float
    node: int
    state: str
    previous: str
    gamma: float
    fault_input: float
    rules: int
    cause: str
    model_mismatch: bool = False
    kind: str = HEALTH
    fault_input_unit: str | None = None
    """The unit of `fault_input` where the outlet knows it (`PlantSignals.fault_unit`)."""

    def to_json(self) -> str:
        return json.dumps(asdict(self), separators=(",", ":"))

    @property
    def text(self) -> str:
        """One human line, as the log and the recording show it."""
        if self.kind == MODEL_MISMATCH:
            what = "raised" if self.model_mismatch else "cleared"
            return (f"model mismatch {what} ({self.cause}; diagnosis {self.state}, "
                    f"gamma^ = {self.gamma:.3f})")
        flag = ", model mismatch" if self.model_mismatch else ""
        return (f"{self.previous} -> {self.state} (gamma^ = {self.gamma:.3f}, "
                f"{self.rules} rules, {self.cause}{flag})")

    @property
    def level(self) -> str:
        """INFO for a return to fault-free or a cleared flag, WARN for anything else."""
        if self.kind == MODEL_MISMATCH:
            return "WARN" if self.model_mismatch else "INFO"
        return "INFO" if self.state == HealthState.FAULT_FREE.label else "WARN"


@dataclass(frozen=True, slots=True)
class Diagnosis:
    """What the monitor reports about a node now: due on every state change and at the
    publication rate (the bus publisher turns it into a MonitorDiagnosis frame).

    `fault_input` is the largest gamma^ times its input: the estimated part of that input
    the fault takes away, in the input's unit.
    """

    node: int
    t: float
    state: HealthState
    gamma: float
    fault_input: float
    rules: int
    model_mismatch: bool = False  # the flag beside the state (`DiagnosisEvent`)


@dataclass(frozen=True, slots=True)
class BusEvent:
    """Something that happened to the bus, not to a node: error frames, interface outages."""

    t: float
    text: str
    level: str = "WARN"  # INFO, WARN or ERROR


DRIVE: Final = "drive"
"""The `kind` of a `DriveEvent`'s line in the events."""


@dataclass(frozen=True, slots=True)
class DriveEvent(BusEvent):
    """What a CANopen drive says about itself (`monitor.bus.cia402.DriveReport`): an EMCY,
    its NMT state, the loss of its heartbeat, its CiA 402 state. Shown where bus events are
    (the recording puts it on its node), and, unlike them, a line of the events beside the
    diagnosis (`to_json`, kind ``drive``): a drive's own Fault explains what the monitor
    reports of its node."""

    node: int = 0
    report: str = ""  # the report's kind: emcy, nmt, heartbeat_lost, cia402
    value: int = 0  # the EMCY error code, the NMT state, the statusword

    def to_json(self) -> str:
        return json.dumps({"t": self.t, "node": self.node, "kind": DRIVE,
                           "report": self.report, "value": self.value, "text": self.text,
                           "level": self.level}, separators=(",", ":"))


def error_frame_event(msg: can.Message) -> tuple[list[str], BusEvent]:
    """The conditions a SocketCAN error frame reports (`monitor.bus.faults`, one
    `bus/errors/<condition>` counter each) and its event, the one form both engines give:
    an error when the controller is bus-off, error-passive or lost frames, else a warning."""
    names = describe_error_frame(msg)
    severe = any(n in ("bus_off", "controller/rx_overflow") or n.endswith("error_passive")
                 for n in names)
    return names, BusEvent(float(msg.timestamp), "CAN error frame: " + ", ".join(names),
                           "ERROR" if severe else "WARN")


def drive_event(report: DriveReport) -> DriveEvent:
    """The event of a drive's report: the one form both engines give it."""
    return DriveEvent(report.t, report_text(report), report_level(report), node=report.node,
                      report=report.kind, value=report.value)


_STATES = tuple(HealthState)


@dataclass
class SampleColumns:
    """A node's estimator samples, one row each (`Sample`'s fields as columns; true_gamma
    NaN where none; `inputs`, `outputs`, `predicted`, `gammas` and `output_noise` one row
    per sample and one column per signal, None where a producer fills none; so is
    `process_noise`, one value per sample)."""

    t: NDArray[np.float64]
    measured: NDArray[np.float64]
    estimated: NDArray[np.float64]
    gamma: NDArray[np.float64]
    rules: NDArray[np.int64]
    state: NDArray[np.int64]
    nis: NDArray[np.float64]
    true_gamma: NDArray[np.float64]
    model_mismatch: NDArray[np.bool_]
    inputs: NDArray[np.float64] | None = None
    outputs: NDArray[np.float64] | None = None
    predicted: NDArray[np.float64] | None = None
    gammas: NDArray[np.float64] | None = None
    gamma_sd: NDArray[np.float64] | None = None
    output_noise: NDArray[np.float64] | None = None
    process_noise: NDArray[np.float64] | None = None

    def rows(self, node: int) -> list[Sample]:
        tg = self.true_gamma
        mm = self.model_mismatch
        n = len(self.t)

        def per_row(a: NDArray[np.float64] | None) -> list[tuple[float, ...]]:
            return [()] * n if a is None else [tuple(r) for r in a.tolist()]

        u, y, yh, gs, on = (per_row(a) for a in (self.inputs, self.outputs, self.predicted,
                                                 self.gammas, self.output_noise))
        sd = [math.nan] * n if self.gamma_sd is None else self.gamma_sd.tolist()
        pn = [math.nan] * n if self.process_noise is None else self.process_noise.tolist()
        return [Sample(node, float(self.t[i]), float(self.measured[i]),
                       float(self.estimated[i]), float(self.gamma[i]), int(self.rules[i]),
                       _STATES[int(self.state[i])], float(self.nis[i]),
                       None if tg[i] != tg[i] else float(tg[i]), bool(mm[i]),
                       inputs=u[i], outputs=y[i], predicted=yh[i], gammas=gs[i],
                       gamma_sd=sd[i], output_noise=on[i], process_noise=pn[i])
                for i in range(n)]
