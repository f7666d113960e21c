"""The virtual motor ECU: a seeded DC-motor plant behind the bus layout of `monitor.bus.codec`.

For one node, every sample k at scenario time t = k / rate the ECU

1. takes gamma(t) and the voltage command u(t) from the scenario,
2. measures the armature current y = plant.output(u, gamma) (noisy; the plant sees the
   faulty effective voltage (1 - gamma) u),
3. emits ``MotorCurrent`` (y), ``MotorVoltage`` (the *commanded* u: the monitor knows the
   command, not the faulty effective voltage) when due, and ``SimTruth`` (true gamma,
   noise-free current, true speed) unless disabled,
4. advances the plant one sample period.

`VirtualECU.frames` produces those frames offline (timestamps ``start_time + k / rate``, no
bus, no sleeping); `VirtualECU.run` sends the same frames on a python-can bus paced in real
time. The plant starts at the fault-free steady state of u(0), as `sim_ecu.plant.simulate`
does, and draws its noise in the same order, so for equal seeds the current frames carry
``simulate(...).y`` quantised to the DBC resolution.

After the scenario's duration the inputs of its last sample hold (gamma and u frozen; the
plant and its noise keep running), so a run may be longer than its scenario.

With a SecOC key (``VirtualECU(..., key=...)``, or a database loaded with ``secoc_key``)
current and voltage frames carry a freshness value and a truncated AES-CMAC
(`monitor.bus.secoc`). The freshness counters live in the ECU's database and never go back:
a second `VirtualECU.frames` call continues them (a freshness value is never reused under
a key), so its frames equal the first call's except for freshness, MAC and CRC. A keyed
ECU also sends one ``SecOCSync`` frame per stream (current, then voltage) at sample 0,
before the first data frame, and then once per second of scenario time (a sync that
falls on a skipped sample goes out with the next sent one), so a monitor that starts
late, restarts or lost frames resynchronises by itself; they count as kind ``sync`` in
`ECUStats`. Without a key none are sent.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Final, Protocol

import can
import numpy as np
from numpy.typing import NDArray

from monitor.bus.codec import N_NODES, SECOC_KINDS, CodecError, Kind, MotorDatabase
from monitor.errors import MonitorError
from monitor.estimation.model import DCMotorParameters, ModelError, dc_motor
from monitor.files import finite_number
from monitor.runtime.canbus import send_frame
from sim_ecu.plant import PlantSimulator, steady_state
from sim_ecu.scenario import BUILTIN_SCENARIOS, Scenario, ScenarioError, scenario_document

__all__ = [
    "ECU_KINDS",
    "ECUError",
    "ECUStats",
    "VirtualECU",
    "load_motor_parameters",
    "motor_parameters",
]

log = logging.getLogger(__name__)

Array = NDArray[np.float64]

ECU_KINDS: Final[tuple[Kind, ...]] = ("current", "voltage", "truth")
"""The message kinds a virtual ECU sends (and ``sync`` with a SecOC key)."""

MOTOR_KEYS: Final[tuple[str, ...]] = tuple(f.name for f in fields(DCMotorParameters))

DEFAULT_MAX_CATCH_UP: Final = 3
"""Samples the real-time loop may send back to back when late; further behind, it skips."""


class ECUError(MonitorError, ValueError):
    """A virtual-ECU configuration that cannot run; the message is one line."""


@dataclass
class ECUStats:
    """Counters of one `VirtualECU.frames` or `VirtualECU.run` call.

    `produced` counts frames built per kind; `sent` frames the bus accepted (run only);
    `send_errors` frames the bus refused (`can.CanError` on send); `overruns` samples the
    real-time loop skipped because it fell behind (simulated, counters advanced, not sent);
    `clipped` frames per kind in which a value was clipped to its DBC range.
    """

    samples: int = 0
    produced: dict[str, int] = field(default_factory=lambda: dict.fromkeys(ECU_KINDS, 0))
    sent: dict[str, int] = field(default_factory=lambda: dict.fromkeys(ECU_KINDS, 0))
    send_errors: int = 0
    overruns: int = 0
    clipped: dict[str, int] = field(default_factory=lambda: dict.fromkeys(ECU_KINDS, 0))
    elapsed: float = 0.0  # wall-clock seconds of run(); 0 for frames()

    @property
    def total_sent(self) -> int:
        return sum(self.sent.values())

    @property
    def total_clipped(self) -> int:
        return sum(self.clipped.values())

    def summary(self) -> str:
        """One line for logs and the CLI."""
        sent = " ".join(f"{k}={v}" for k, v in self.sent.items())
        return (
            f"{self.samples} samples in {self.elapsed:.2f} s, sent {sent}, "
            f"send errors {self.send_errors}, overruns {self.overruns}, "
            f"clipped {self.total_clipped}"
        )


# ----------------------------------------------------------------------------- motor


def motor_parameters(table: Mapping[str, Any], where: str = "[motor]") -> DCMotorParameters:
    """DC-motor parameters from a ``[motor]`` table (J, b, Ke, Ki, Ra, La; missing = Table 1).

    Raises `ECUError` with one line for unknown keys, non-numbers or values `dc_motor`
    rejects (J, b, Ke, Ki, Ra must be positive, La >= 0).
    """
    if not isinstance(table, Mapping):
        raise ECUError(f"{where} must be a table")
    unknown = sorted(set(table) - set(MOTOR_KEYS))
    if unknown:
        raise ECUError(
            f"{where}: unknown key(s) {', '.join(unknown)}; expected {', '.join(MOTOR_KEYS)}"
        )
    values: dict[str, float] = {}
    for key, v in table.items():
        number = finite_number(v)
        if number is None:
            raise ECUError(f"{where}: '{key}' must be a finite number, got {v!r}")
        values[key] = number
    params = DCMotorParameters(**values)
    try:
        dc_motor(params)
    except ModelError as exc:
        raise ECUError(f"{where}: {exc}") from None
    return params


def load_motor_parameters(name_or_path: str | Path) -> DCMotorParameters | None:
    """The ``[motor]`` table of a scenario TOML file, or None (built-in name, no table).

    Call after `sim_ecu.scenario.load_scenario` accepted the same argument: a file that
    cannot be read or parsed here is reported as an `ECUError` line as well.
    """
    key = str(name_or_path)
    if key in BUILTIN_SCENARIOS:
        return None
    path = Path(key)
    try:
        data = scenario_document(path)
    except ScenarioError as exc:
        raise ECUError(str(exc)) from None
    if "motor" not in data:
        return None
    return motor_parameters(data["motor"], f"{path} [motor]")


# ----------------------------------------------------------------------------- ECU


def _positive(name: str, value: float) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ECUError(f"{name} must be a number, got {value!r}")
    if not (math.isfinite(value) and value > 0):
        raise ECUError(f"{name} must be a positive number, got {value!r}")
    return float(value)


@dataclass(frozen=True, slots=True)
class _Limits:
    lo: float
    hi: float

    def clip(self, value: float) -> tuple[float, bool]:
        """(value clipped to [lo, hi], whether it was changed); NaN becomes 0 clipped."""
        if value != value:  # NaN: nothing sensible to send, but never an encode error
            return min(max(0.0, self.lo), self.hi), True
        if value < self.lo:
            return self.lo, True
        if value > self.hi:
            return self.hi, True
        return value, False


class _Simulation:
    """One pass through the scenario: plant state, alive counters, voltage schedule."""

    def __init__(self, ecu: VirtualECU, stats: ECUStats) -> None:
        self.ecu = ecu
        self.stats = stats
        plant = PlantSimulator(
            ecu.model,
            1.0 / ecu.rate,
            seed=ecu.seed,
            process=ecu.scenario.process,
            current_sigma=ecu.scenario.current_sigma,
        )
        plant.x = steady_state(plant, np.full(1, ecu.scenario.voltage_at(0.0)))
        self.plant = plant
        self.k = 0
        self.counters: dict[Kind, int] = {"current": 0, "voltage": 0}
        self.last_u: float | None = None  # command of the previous sample
        self.voltage_pending = False  # a change fell on a skipped sample
        self.sync_pending = False  # a SecOC sync fell on a skipped sample

    def _scheduled(self, k: int) -> bool:
        """Whether sample k is a regular voltage-frame sample."""
        ratio = self.ecu.voltage_rate / self.ecu.rate
        if k == 0 or ratio >= 1.0:
            return True
        # A frame whenever floor(k * ratio) ticks over: every rate/voltage_rate samples for
        # integer ratios, evenly spread otherwise (eps guards exact multiples against
        # round-off in k * ratio).
        return math.floor(k * ratio + 1e-9) != math.floor((k - 1) * ratio + 1e-9)

    def _sync_due(self, k: int) -> bool:
        """Whether sample k starts a second of scenario time (SecOC sync frames due)."""
        if not self.ecu.sync:
            return False
        rate = self.ecu.rate
        return k == 0 or math.floor(k / rate + 1e-9) != math.floor((k - 1) / rate + 1e-9)

    def _counter(self, kind: Kind) -> int:
        c = self.counters[kind]
        self.counters[kind] = (c + 1) & 0xF
        return c

    def step(self, emit: bool, time_base: float) -> list[can.Message]:
        """Simulate sample k and return its frames, or none when not `emit`.

        A skipped sample (not `emit`) still advances the alive counters of the frames it
        would have sent; a voltage change that falls on a skipped sample is sent with the
        next emitted one.
        """
        ecu, stats, plant = self.ecu, self.stats, self.plant
        k = self.k
        t = k / ecu.rate
        t_in = min(t, ecu.last_scenario_time)  # after the scenario: its last inputs hold
        g = float(ecu.scenario.gamma_at(t_in)[0])
        u_cmd = float(ecu.scenario.voltage_at(t_in))
        u = np.full(1, u_cmd)
        gamma = np.full(1, g)
        y = float(plant.output(u, gamma)[0])
        changed = u_cmd != self.last_u
        self.last_u = u_cmd
        voltage_due = changed or self._scheduled(k)
        sync_due = self._sync_due(k)
        msgs: list[can.Message] = []
        if emit:
            voltage_due = voltage_due or self.voltage_pending
            self.voltage_pending = False
            if sync_due or self.sync_pending:
                self.sync_pending = False
                msgs = self._sync(time_base + t)
            msgs += self._encode(time_base + t, y, u_cmd, g, voltage_due, u, gamma)
        else:
            self.voltage_pending = self.voltage_pending or changed
            self.sync_pending = self.sync_pending or sync_due
            self._counter("current")
            if voltage_due:
                self._counter("voltage")
        plant.advance(u, gamma)
        self.k += 1
        stats.samples += 1
        return msgs

    def _sync(self, ts: float) -> list[can.Message]:
        """One SecOCSync frame per authenticated stream, at the freshness signed so far."""
        ecu = self.ecu
        msgs = [ecu._message("sync", ecu.db.encode_sync(ecu.node, kind), ts)
                for kind in SECOC_KINDS]
        self.stats.produced["sync"] += len(msgs)
        return msgs

    def _encode(
        self,
        ts: float,
        y: float,
        u_cmd: float,
        g: float,
        voltage_due: bool,
        u: Array,
        gamma: Array,
    ) -> list[can.Message]:
        ecu, clipped, produced = self.ecu, self.stats.clipped, self.stats.produced
        db, node, lim = ecu.db, ecu.node, ecu.limits
        cur, c_cur = lim["ArmatureCurrent"].clip(y)
        payload = db.encode_current(node, cur, self._counter("current"))
        msgs = [ecu._message("current", payload, ts)]
        produced["current"] += 1
        clipped["current"] += c_cur
        if voltage_due:
            volts, c_volt = lim["VoltageCommand"].clip(u_cmd)
            payload = db.encode_voltage(node, volts, self._counter("voltage"))
            msgs.append(ecu._message("voltage", payload, ts))
            produced["voltage"] += 1
            clipped["voltage"] += c_volt
        if ecu.truth:
            plant = self.plant
            true_current = float(plant.true_output(u, gamma)[0])
            speed = 0.0 if ecu.speed_index is None else float(plant.x[ecu.speed_index])
            tg, c1 = lim["TrueGamma"].clip(g)
            tc, c2 = lim["TrueCurrent"].clip(true_current)
            tw, c3 = lim["TrueSpeed"].clip(speed)
            msgs.append(ecu._message("truth", db.encode_truth(node, tg, tc, tw), ts))
            produced["truth"] += 1
            clipped["truth"] += c1 or c2 or c3
        return msgs


class VirtualECU:
    """The virtual motor ECU of one node (m = 1: the DC motor of
    `monitor.estimation.model.dc_motor`).

    `bus` may be None for offline use of `frames`. `rate` is the sample rate (Hz: one
    current and one truth frame per sample), `voltage_rate` the rate of voltage frames (one
    every rate/voltage_rate samples, and always at a change of the command; >= rate means
    every sample). `motor` overrides the Table 1 parameters; when None, a ``motor`` mapping
    in ``scenario.extra`` is used if present. `send_timeout` (default a quarter period) is
    how long a send may wait for a full queue (`monitor.runtime.canbus.send_frame`);
    `max_catch_up` is how many late samples `run` may send back to back before it skips
    ahead instead. `key` (16 or 32 bytes, e.g. from
    `monitor.bus.secoc.load_key`) signs the current and voltage frames with SecOC on a copy of
    `db` of the ECU's own (None: sign only if `db` has a key). Raises `ECUError` (one line)
    on a bad configuration.
    """

    def __init__(
        self,
        bus: can.BusABC | None,
        db: MotorDatabase,
        node: int,
        scenario: Scenario,
        *,
        rate: float = 100.0,
        voltage_rate: float = 20.0,
        seed: int = 0,
        truth: bool = True,
        motor: DCMotorParameters | None = None,
        send_timeout: float | None = None,
        max_catch_up: int = DEFAULT_MAX_CATCH_UP,
        key: bytes | None = None,
    ) -> None:
        if isinstance(node, bool) or not isinstance(node, int) or not 0 <= node < N_NODES:
            raise ECUError(f"node must be an integer in 0..{N_NODES - 1}, got {node!r}")
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ECUError(f"seed must be a non-negative integer, got {seed!r}")
        if scenario.actuators != 1:
            raise ECUError(
                f"scenario {scenario.name!r} has {scenario.actuators} actuators; "
                "the DC-motor ECU drives exactly 1"
            )
        if not isinstance(max_catch_up, int) or max_catch_up < 1:
            raise ECUError(f"max_catch_up must be a positive integer, got {max_catch_up!r}")
        if key is not None:
            try:
                db = db.with_secoc_key(key)
            except CodecError as exc:
                raise ECUError(f"SecOC: {exc}") from None
        self.bus = bus
        self.db = db
        self.node = node
        self.sync = db.secoc_enabled  # keyed: SecOC sync frames at start and every second
        self.kinds: tuple[Kind, ...] = (*ECU_KINDS, "sync") if self.sync else ECU_KINDS
        self.scenario = scenario
        self.rate = _positive("rate", rate)
        self.voltage_rate = _positive("voltage rate", voltage_rate)
        self.seed = seed
        self.truth = bool(truth)
        self.period = 1.0 / self.rate
        self.send_timeout = (
            self.period / 4 if send_timeout is None else _positive("send timeout", send_timeout)
        )
        self.max_catch_up = max_catch_up
        if motor is None and isinstance(scenario.extra.get("motor"), Mapping):
            motor = motor_parameters(scenario.extra["motor"], f"{scenario.name} [motor]")
        self.motor = motor or DCMotorParameters()
        try:
            self.model = dc_motor(self.motor)
        except ModelError as exc:
            raise ECUError(f"motor model: {exc}") from None
        names = self.model.standard_form().state_names
        self.speed_index: int | None = names.index("speed") if "speed" in names else None
        # Scenario inputs hold from the last sample inside the scenario's duration on.
        n_scn = self.samples_for(scenario.duration)
        self.last_scenario_time = (max(n_scn, 1) - 1) / self.rate
        try:
            self.frame_ids: dict[Kind, int] = {k: db.frame_id(k, node) for k in self.kinds}
            signals: tuple[tuple[Kind, str], ...] = (
                ("current", "ArmatureCurrent"),
                ("voltage", "VoltageCommand"),
                ("truth", "TrueGamma"),
                ("truth", "TrueCurrent"),
                ("truth", "TrueSpeed"),
            )
            self.limits = {sig: self._limits(kind, sig) for kind, sig in signals}
        except (CodecError, KeyError) as exc:
            raise ECUError(f"DBC {db.source}: {exc}") from None
        self.kind_of: dict[int, Kind] = {fid: k for k, fid in self.frame_ids.items()}
        self.stats = self._new_stats()

    def _new_stats(self) -> ECUStats:
        """Stats with a ``sync`` entry when this ECU sends SecOC sync frames."""
        return ECUStats(produced=dict.fromkeys(self.kinds, 0),
                        sent=dict.fromkeys(self.kinds, 0))

    def _limits(self, kind: Kind, signal: str) -> _Limits:
        sig = self.db.message(kind, self.node).get_signal_by_name(signal)
        lo = -math.inf if sig.minimum is None else float(sig.minimum)
        hi = math.inf if sig.maximum is None else float(sig.maximum)
        return _Limits(lo, hi)

    def _message(self, kind: Kind, payload: bytes, timestamp: float) -> can.Message:
        return can.Message(
            timestamp=timestamp,
            arbitration_id=self.frame_ids[kind],
            is_extended_id=False,
            data=payload,
        )

    def samples_for(self, duration: float) -> int:
        """Samples k with k / rate < duration (ceil, robust to round-off in duration * rate)."""
        return max(0, math.ceil(duration * self.rate - 1e-9))

    def _n_samples(self, duration: float | None) -> int | None:
        """Samples to produce, None for forever (duration = inf)."""
        if duration is None:
            return self.samples_for(self.scenario.duration)
        if isinstance(duration, bool) or not isinstance(duration, int | float):
            raise ECUError(f"duration must be a number of seconds, got {duration!r}")
        if duration != duration or duration < 0:
            raise ECUError(f"duration must be >= 0 seconds (inf: forever), got {duration!r}")
        if math.isinf(duration):
            return None
        return self.samples_for(duration)

    # -- offline ----------------------------------------------------------------------

    def frames(
        self, duration: float | None = None, start_time: float = 0.0
    ) -> Iterator[can.Message]:
        """All frames of a fresh run of `duration` seconds (None: the scenario's duration).

        Sample k's frames (SecOC syncs when due, current, voltage when due, truth) carry
        timestamp ``start_time + k / rate``; the scenario always starts at its t = 0. Each
        call starts from the steady state with the ECU's seed, so equal seeds give equal
        frames.
        `self.stats` is reset and counts what has been produced so far. ``duration=inf``
        never ends.
        """
        n = self._n_samples(duration)  # validated now, not at the first next()
        self.stats = self._new_stats()
        return self._frames(_Simulation(self, self.stats), n, start_time)

    @staticmethod
    def _frames(sim: _Simulation, n: int | None, start_time: float) -> Iterator[can.Message]:
        k = 0
        while n is None or k < n:
            yield from sim.step(True, start_time)
            k += 1

    # -- real time --------------------------------------------------------------------

    def run(
        self, duration: float | None = None, stop: threading.Event | None = None
    ) -> ECUStats:
        """Send the frames of `frames` on the bus in real time until done or `stop` is set.

        Sample k is due at ``start + k / rate`` on `time.monotonic` (no cumulative drift).
        Up to `max_catch_up` late samples go out back to back; when further behind, the
        loop simulates the missed samples without sending them (their alive counters
        advance, so a receiver sees the gap) and counts them as `overruns`. A `can.CanError`
        on send is counted and logged once per burst of failures. Returns the stats (also
        in `self.stats`).
        """
        if self.bus is None:
            raise ECUError("run() needs a bus; use frames() offline")
        n = self._n_samples(duration)
        self.stats = stats = self._new_stats()
        return run_paced(self.bus, _Simulation(self, stats), stats, n, self.rate, self.node,
                         stop, self.send_timeout, self.max_catch_up,
                         lambda msg: self.kind_of[msg.arbitration_id])


class SampleSource(Protocol):
    """One sample of a simulated ECU at a time: its frames (none when not `emit`)."""

    def step(self, emit: bool, time_base: float) -> list[can.Message]: ...


def run_paced(bus: can.BusABC, sim: SampleSource, stats: ECUStats, n: int | None, rate: float,
              node: int, stop: threading.Event | None, send_timeout: float, max_catch_up: int,
              kind_of: Callable[[can.Message], str]) -> ECUStats:
    """Send `sim`'s samples on `bus` in real time: sample k is due at ``start + k / rate`` on
    `time.monotonic` (no cumulative drift). Up to `max_catch_up` late samples go out back to
    back; when further behind, the missed samples are simulated without being sent (their
    alive counters advance, so a receiver sees the gap) and counted as `overruns`. A
    `can.CanError` on send is counted and logged once per burst of failures."""
    stop = stop if stop is not None else threading.Event()
    failing = 0  # consecutive failed sends (the current burst)
    wall0 = time.time()
    start = time.monotonic()
    k = 0
    try:
        while (n is None or k < n) and not stop.is_set():
            now = time.monotonic()
            deadline = start + k / rate
            if now < deadline:
                if stop.wait(deadline - now):
                    break
            else:
                behind = math.floor((now - deadline) * rate)
                if behind > max_catch_up:
                    skip = behind if n is None else min(behind, n - k)
                    log.warning(
                        "node %d: %.1f ms behind schedule at t=%.3f s: skipped %d sample(s)",
                        node, 1e3 * (now - deadline), k / rate, skip,
                    )
                    for _ in range(skip):
                        sim.step(False, wall0)
                    k += skip
                    stats.overruns += skip
                    continue
            for msg in sim.step(True, wall0):
                try:
                    send_frame(bus, msg, send_timeout)
                except (can.CanError, OSError) as exc:
                    stats.send_errors += 1
                    if failing == 0:
                        log.warning(
                            "node %d: send failed at t=%.3f s: %s (failures are counted, "
                            "not logged, until a send succeeds)",
                            node, k / rate, exc,
                        )
                    failing += 1
                else:
                    stats.sent[kind_of(msg)] += 1
                    if failing:
                        log.warning(
                            "node %d: sending again at t=%.3f s after %d failed frame(s)",
                            node, k / rate, failing,
                        )
                        failing = 0
            k += 1
    finally:
        stats.elapsed = time.monotonic() - start
    return stats
