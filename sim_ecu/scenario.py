"""Fault and voltage scenarios: what the virtual ECU and the benchmarks inject.

A scenario is a timeline of actuator loss of effectiveness gamma(t) (eqs 3-5) and a
voltage command u(t), plus noise levels. It is read from TOML or taken from a built-in
name. Example::

    name = "my-test"
    duration = 12.0            # s
    [noise]
    current_sigma = 0.5        # A, measurement noise (R = sigma^2)
    process = 1.0              # scale on the model's process-noise intensity
    [voltage]
    steps = [[0.0, 220.0], [8.0, 180.0]]   # piecewise-constant command [t, V], or
    # prbs = { level = 220.0, amplitude = 15.0, clock = 0.5, seed = 0, levels = 5 }  # 5 levels
    #   over 205-235 V, drawn every 0.5 s (levels: 2 by default, +-15 V)
    [[fault]]                  # abrupt: gamma from start until end
    start = 3.0
    end = 6.0
    gamma = 0.4
    [[fault]]
    kind = "ramp"              # incipient: linear from gamma_from to gamma_to
    start = 6.0
    end = 9.0
    gamma_from = 0.0
    gamma_to = 0.6
    [[fault]]
    kind = "intermittent"      # gamma during the first `duty` of every `period`
    start = 9.0
    end = 11.0
    gamma = 0.5
    period = 0.5
    duty = 0.4

Faults on the same actuator do not overlap; where they would, the later one wins.
"""

from __future__ import annotations

import itertools
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from monitor.errors import MonitorError
from monitor.files import MIB, UserFileError, finite_number, read_user_toml, shown_path

__all__ = [
    "BUILTIN_SCENARIOS",
    "SCENARIO_FILE_LIMIT",
    "FaultSegment",
    "Scenario",
    "ScenarioError",
    "load_scenario",
    "scenario_document",
]

SCENARIO_FILE_LIMIT = 16 * MIB
"""The largest scenario file read: room for a voltage profile of hundreds of thousands of
steps."""


class ScenarioError(MonitorError, ValueError):
    """A scenario that cannot be run; the message is one line naming the problem."""


FAULT_KINDS = ("step", "ramp", "intermittent")


@dataclass(frozen=True)
class FaultSegment:
    start: float
    end: float
    kind: str = "step"
    gamma: float = 0.0
    gamma_from: float = 0.0
    gamma_to: float = 0.0
    period: float = 1.0
    duty: float = 0.5
    actuator: int = 0

    def gamma_at(self, t: float) -> float | None:
        """gamma at time t, or None when t is outside this segment."""
        if not (self.start <= t < self.end):
            return None
        if self.kind == "step":
            return self.gamma
        if self.kind == "ramp":
            frac = (t - self.start) / (self.end - self.start)
            return self.gamma_from + frac * (self.gamma_to - self.gamma_from)
        phase = math.fmod(t - self.start, self.period) / self.period
        return self.gamma if phase < self.duty else 0.0


@dataclass(frozen=True)
class Scenario:
    name: str
    duration: float
    faults: tuple[FaultSegment, ...] = ()
    voltage_steps: tuple[tuple[float, float], ...] = ((0.0, 220.0),)
    current_sigma: float = 0.5
    process: float = 1.0
    actuators: int = 1
    description: str = ""
    extra: Mapping[str, Any] = field(default_factory=dict)

    def gamma_at(self, t: float) -> list[float]:
        g = [0.0] * self.actuators
        for seg in self.faults:
            v = seg.gamma_at(t)
            if v is not None:
                g[seg.actuator] = v
        return g

    def voltage_at(self, t: float) -> float:
        v = self.voltage_steps[0][1]
        for t0, volts in self.voltage_steps:
            if t >= t0:
                v = volts
            else:
                break
        return v


def _number(table: Mapping[str, Any], key: str, where: str, default: float | None = None) -> float:
    if key not in table:
        if default is None:
            raise ScenarioError(f"{where}: missing '{key}'")
        return default
    v = finite_number(table[key])
    if v is None:
        raise ScenarioError(f"{where}: '{key}' must be a finite number, got {table[key]!r}")
    return v


def _prbs_steps(table: object, duration: float, where: str) -> list[list[float]]:
    """The steps of a pseudo-random command: level + amplitude s, s drawn anew every `clock`
    seconds from `levels` (2 by default: +-amplitude) evenly spaced values over [-1, 1]
    (`monitor.identify.prbs`), the excitation `identify` wants."""
    from monitor.identify import prbs

    if not isinstance(table, dict):
        raise ScenarioError(f"{where}: must be a table {{level, amplitude, clock, seed}}")
    level = _number(table, "level", where)
    amplitude = _number(table, "amplitude", where)
    clock = _number(table, "clock", where)
    seed = int(_number(table, "seed", where, 0.0))
    levels = _number(table, "levels", where, 2.0)
    if not (clock > 0 and amplitude >= 0):
        raise ScenarioError(f"{where}: needs clock > 0 and amplitude >= 0")
    if not (levels >= 2 and levels == int(levels) and levels <= 1000):
        raise ScenarioError(f"{where}: levels must be a whole number from 2 to 1000, "
                            f"got {levels:g}")
    values = prbs(duration, clock, level=level, amplitude=amplitude, clock=clock, seed=seed,
                  levels=int(levels))
    return [[k * clock, float(v)] for k, v in enumerate(values[:, 0])]


def scenario_from_dict(data: Mapping[str, Any], default_name: str = "scenario") -> Scenario:
    """Validate a parsed TOML table into a Scenario (one-line ScenarioError on any fault)."""
    name = str(data.get("name", default_name))
    duration = _number(data, "duration", name)
    if duration <= 0:
        raise ScenarioError(f"{name}: duration must be positive, got {duration}")
    noise = data.get("noise", {})
    if not isinstance(noise, dict):
        raise ScenarioError(f"{name}: [noise] must be a table")
    sigma = _number(noise, "current_sigma", f"{name} [noise]", 0.5)
    process = _number(noise, "process", f"{name} [noise]", 1.0)
    if sigma <= 0 or process < 0:
        raise ScenarioError(f"{name}: noise needs current_sigma > 0 and process >= 0")
    volt = data.get("voltage", {"steps": [[0.0, 220.0]]})
    if isinstance(volt, dict) and "prbs" in volt:
        volt = {"steps": _prbs_steps(volt["prbs"], duration, f"{name} [voltage.prbs]")}
    if not isinstance(volt, dict) or "steps" not in volt:
        raise ScenarioError(f"{name}: [voltage] needs steps = [[t, volts], ...] or a prbs table")
    steps_raw = volt["steps"]
    if not isinstance(steps_raw, list) or not steps_raw:
        raise ScenarioError(f"{name}: voltage steps must be a non-empty list of [t, volts]")
    steps: list[tuple[float, float]] = []
    for i, s in enumerate(steps_raw):
        if (
            not isinstance(s, list)
            or len(s) != 2
            or not all(finite_number(x) is not None for x in s)
        ):
            raise ScenarioError(f"{name}: voltage step {i} must be [t, volts] numbers, got {s!r}")
        steps.append((float(s[0]), float(s[1])))
    if any(b[0] <= a[0] for a, b in itertools.pairwise(steps)):
        raise ScenarioError(f"{name}: voltage steps must be in increasing time order")
    if abs(steps[0][0]) > 0:
        steps.insert(0, (0.0, steps[0][1]))
    faults_raw = data.get("fault", [])
    if not isinstance(faults_raw, list):
        raise ScenarioError(f"{name}: faults must be given as [[fault]] tables")
    faults: list[FaultSegment] = []
    actuators = int(data.get("actuators", 1)) if isinstance(data.get("actuators", 1), int) else 0
    if actuators < 1:
        raise ScenarioError(f"{name}: actuators must be a positive integer")
    for i, f in enumerate(faults_raw):
        where = f"{name} fault {i}"
        if not isinstance(f, dict):
            raise ScenarioError(f"{where}: must be a table")
        kind = f.get("kind", "step")
        if kind not in FAULT_KINDS:
            kinds = ", ".join(FAULT_KINDS)
            raise ScenarioError(f"{where}: kind must be one of {kinds}, got {kind!r}")
        start = _number(f, "start", where)
        end = _number(f, "end", where, duration)
        if not 0 <= start < end:
            raise ScenarioError(f"{where}: need 0 <= start < end, got start={start}, end={end}")
        act = f.get("actuator", 0)
        if not isinstance(act, int) or not 0 <= act < actuators:
            raise ScenarioError(f"{where}: actuator must be an integer in [0, {actuators})")
        seg = FaultSegment(
            start=start,
            end=end,
            kind=kind,
            gamma=_number(f, "gamma", where, 0.0 if kind == "ramp" else None),
            gamma_from=_number(f, "gamma_from", where, 0.0),
            gamma_to=_number(f, "gamma_to", where, 0.0 if kind != "ramp" else None),
            period=_number(f, "period", where, 1.0),
            duty=_number(f, "duty", where, 0.5),
            actuator=act,
        )
        for g in (seg.gamma, seg.gamma_from, seg.gamma_to):
            if not 0.0 <= g <= 1.0:
                raise ScenarioError(f"{where}: gamma values must lie in [0, 1] (eq 3), got {g}")
        if kind == "intermittent" and not (seg.period > 0 and 0 < seg.duty < 1):
            raise ScenarioError(f"{where}: intermittent needs period > 0 and 0 < duty < 1")
        faults.append(seg)
    return Scenario(
        name=name,
        duration=duration,
        faults=tuple(faults),
        voltage_steps=tuple(steps),
        current_sigma=sigma,
        process=process,
        actuators=actuators,
        description=str(data.get("description", "")),
    )


def _builtin() -> dict[str, Scenario]:
    def mk(d: dict[str, Any]) -> Scenario:
        return scenario_from_dict(d)

    return {
        "healthy": mk({"name": "healthy", "duration": 20.0, "description": "no fault"}),
        "fault-outage-recovery": mk(
            {
                "name": "fault-outage-recovery",
                "duration": 16.0,
                "description": "fault-free, 40 % loss at 4 s, outage at 8 s, recovery at 11 s",
                "fault": [
                    {"start": 4.0, "end": 8.0, "gamma": 0.4},
                    {"start": 8.0, "end": 11.0, "gamma": 1.0},
                ],
            }
        ),
        "incipient": mk(
            {
                "name": "incipient",
                "duration": 20.0,
                "description": "slowly growing loss from 0 to 0.6 between 4 s and 14 s",
                "fault": [
                    {"kind": "ramp", "start": 4.0, "end": 14.0, "gamma_from": 0.0, "gamma_to": 0.6},
                    {"start": 14.0, "end": 20.0, "gamma": 0.6},
                ],
            }
        ),
        "intermittent": mk(
            {
                "name": "intermittent",
                "duration": 16.0,
                "description": "50 % loss for 1 s in every 2 s between 4 s and 12 s",
                "fault": [
                    {
                        "kind": "intermittent",
                        "start": 4.0,
                        "end": 12.0,
                        "gamma": 0.5,
                        "period": 2.0,
                        "duty": 0.5,
                    }
                ],
            }
        ),
    }


BUILTIN_SCENARIOS: dict[str, Scenario] = _builtin()


def load_scenario(name_or_path: str | Path) -> Scenario:
    """A built-in scenario by name, or a TOML file (ScenarioError with one line on failure)."""
    key = str(name_or_path)
    if key in BUILTIN_SCENARIOS:
        return BUILTIN_SCENARIOS[key]
    path = Path(key)
    if path.suffix != ".toml" and not os.path.lexists(path):
        raise ScenarioError(
            f"unknown scenario {shown_path(key, 60)!r}: use one of "
            f"{', '.join(BUILTIN_SCENARIOS)} or a .toml file"
        )
    doc = scenario_document(path)
    try:
        return scenario_from_dict(doc, default_name=path.stem)
    except ScenarioError as exc:
        raise ScenarioError(f"scenario file {shown_path(path)}: {exc}") from None


def scenario_document(path: Path) -> dict[str, Any]:
    """The parsed TOML of a scenario file, read as every file a user names is
    (`monitor.files.read_user_toml`); `ScenarioError`, one line, if it cannot be."""
    try:
        return read_user_toml(path, what="scenario file", limit=SCENARIO_FILE_LIMIT)
    except UserFileError as exc:
        raise ScenarioError(str(exc)) from None
