"""What the pipeline hands to its sinks: typed, immutable events, nothing Rerun- or
CAN-specific. Each outlet (the Rerun recording, the diagnosis frames on the bus, JSON lines,
the log) is a `monitor.sinks.Sink` that takes the events it needs."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import NDArray

from monitor.diagnosis.classifier import HealthState

__all__ = ["BusEvent", "Diagnosis", "DiagnosisEvent", "Sample", "SampleColumns", "VoltageSample"]


@dataclass(frozen=True, slots=True)
class Sample:
    """One estimator step of a node: the measured and estimated output, gamma^ (the
    estimated loss of effectiveness), the rule count, the reported health state, the
    normalised innovation squared and, from a virtual ECU, the true gamma."""

    node: int
    t: float
    measured: float
    estimated: float
    gamma: float
    rules: int
    state: HealthState
    nis: float
    true_gamma: float | None = None


@dataclass(frozen=True, slots=True)
class VoltageSample:
    """A voltage command (the estimator's input) of a node."""

    node: int
    t: float
    volts: float


@dataclass(frozen=True)
class DiagnosisEvent:
    """A change of a node's health state (also written as a JSON line by `replay`)."""

    t: float
    node: int
    state: str
    previous: str
    gamma: float
    fault_volts: float
    rules: int
    cause: str  # "estimate" or "silence"

    def to_json(self) -> str:
        return json.dumps(asdict(self), separators=(",", ":"))

    @property
    def text(self) -> str:
        """One human line, as the log and the recording show it."""
        return (f"{self.previous} -> {self.state} (gamma^ = {self.gamma:.3f}, "
                f"{self.rules} rules, {self.cause})")

    @property
    def level(self) -> str:
        """INFO for a return to fault-free, WARN for anything else."""
        return "INFO" if self.state == HealthState.FAULT_FREE.label else "WARN"


@dataclass(frozen=True, slots=True)
class Diagnosis:
    """What the monitor reports about a node now: due on every state change and at the
    publication rate (the bus publisher turns it into a MonitorDiagnosis frame).

    `fault_volts` is gamma^ times the voltage command: the estimated lost input, in V.
    """

    node: int
    t: float
    state: HealthState
    gamma: float
    fault_volts: float
    rules: int


@dataclass(frozen=True, slots=True)
class BusEvent:
    """Something that happened to the bus, not to a node: error frames, interface outages."""

    t: float
    text: str
    level: str = "WARN"  # INFO, WARN or ERROR


_STATES = tuple(HealthState)


@dataclass
class SampleColumns:
    """A node's estimator samples, one row each (`Sample`'s fields as columns; true_gamma
    NaN where none)."""

    t: NDArray[np.float64]
    measured: NDArray[np.float64]
    estimated: NDArray[np.float64]
    gamma: NDArray[np.float64]
    rules: NDArray[np.int64]
    state: NDArray[np.int64]
    nis: NDArray[np.float64]
    true_gamma: NDArray[np.float64]

    def rows(self, node: int) -> list[Sample]:
        tg = self.true_gamma
        return [Sample(node, float(self.t[i]), float(self.measured[i]),
                       float(self.estimated[i]), float(self.gamma[i]), int(self.rules[i]),
                       _STATES[int(self.state[i])], float(self.nis[i]),
                       None if tg[i] != tg[i] else float(tg[i]))
                for i in range(len(self.t))]
