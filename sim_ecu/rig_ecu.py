"""A virtual twin of a user's ECU: the rig's model simulated in real time, speaking the
rig's DBC and node layout (`sim-ecu --rig`).

Each sample the plant (the rig's model, `sim_ecu.plant.PlantSimulator`, with the rig's
process and measurement noise scaled by the scenario) is stepped with the scenario's input
command on every input and its loss of effectiveness gamma on each faulty actuator; the
output message goes out every sample, messages that carry only inputs at `input_rate` and
whenever the command changes, and the truth message (if the rig names one) every sample.
Protected messages get their alive counter and E2E CRC from `monitor.bus.rigcodec`; with a
SecOC key (a codec built with one) secured messages are signed, and the rig's sync message
announces each secured stream's freshness at start, before its first frame, and then once
per second, as our own ECU does.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator

import can
import numpy as np
from cantools.database.can import Message

from monitor.bus.rigcodec import RigCodec
from monitor.rig import Rig, build_model, model_of
from sim_ecu.ecu import DEFAULT_MAX_CATCH_UP, ECUError, ECUStats, run_paced
from sim_ecu.plant import PlantSimulator, steady_state
from sim_ecu.scenario import Scenario

__all__ = ["RigECU"]


class RigECU:
    """One node of a rig, simulated. `frames` offline, `run` in real time on `bus`."""

    def __init__(self, bus: can.BusABC | None, codec: RigCodec, rig: Rig, node: int,
                 scenario: Scenario, *, seed: int = 0, input_rate: float | None = None,
                 max_catch_up: int = DEFAULT_MAX_CATCH_UP) -> None:
        if node not in codec.nodes:
            raise ECUError(f"node {node} has no messages on this rig (nodes: "
                           f"{', '.join(map(str, codec.nodes))})")
        self.model = build_model(rig)
        m = self.model.B.shape[1]
        if scenario.actuators not in (1, m):
            raise ECUError(f"scenario {scenario.name!r} has {scenario.actuators} actuators; "
                           f"the rig's model has {m}")
        self.bus, self.codec, self.rig, self.node = bus, codec, rig, node
        self.scenario = scenario
        self.seed = seed
        _, self.rate = model_of(rig)
        self.input_rate = min(self.rate, input_rate if input_rate else self.rate / 5.0)
        if not self.input_rate > 0:
            raise ECUError(f"input rate must be positive, got {input_rate!r}")
        self.m = m
        self.send_timeout = 0.25 / self.rate
        self.max_catch_up = max_catch_up
        self.out_name = rig.output_message
        self.input_names = tuple(n for n, s in codec.specs.items()
                                 if s.inputs and not s.outputs)
        self.truth_name = rig.truth.message if rig.truth is not None else None
        sent = tuple(dict.fromkeys((self.out_name, *self.input_names,
                                    *(() if self.truth_name is None else (self.truth_name,)))))
        # the secured streams it announces in sync frames (only when it signs)
        self.synced = tuple(n for n in sent if codec.specs[n].secoc is not None
                            ) if codec.secoc_enabled else ()
        self.kinds = (*sent, "sync") if self.synced else sent
        self.kind_of = {codec.frame_id(k, node): k for k in sent}
        if self.synced:
            assert codec.sync is not None
            self.kind_of[codec.frame_id(codec.sync.message, node)] = "sync"
        self.stats = self._new_stats()

    @property
    def voltage_rate(self) -> float:
        """The rate of messages that carry only inputs (the voltage frames of our bus)."""
        return self.input_rate

    def _new_stats(self) -> ECUStats:
        return ECUStats(produced=dict.fromkeys(self.kinds, 0), sent=dict.fromkeys(self.kinds, 0),
                        clipped=dict.fromkeys(self.kinds, 0))

    def samples_for(self, duration: float) -> int:
        return max(0, math.ceil(duration * self.rate - 1e-9))

    def frames(self, duration: float | None = None, start_time: float = 0.0
               ) -> Iterator[can.Message]:
        """All frames of a fresh run (sample k at ``start_time + k / rate``)."""
        n = self.samples_for(self.scenario.duration if duration is None else duration)
        self.stats = self._new_stats()
        sim = self._simulation(self.stats)
        for _ in range(n):
            yield from sim.step(True, start_time)

    def run(self, duration: float | None = None, stop: threading.Event | None = None
            ) -> ECUStats:
        """Send in real time until done (None: the scenario's duration; inf: forever) or
        `stop` is set."""
        if self.bus is None:
            raise ECUError("run() needs a bus; use frames() offline")
        d = self.scenario.duration if duration is None else duration
        n = None if math.isinf(d) else self.samples_for(d)
        self.stats = stats = self._new_stats()
        return run_paced(self.bus, self._simulation(stats), stats, n, self.rate, self.node,
                         stop, self.send_timeout, self.max_catch_up,
                         lambda msg: self.kind_of[msg.arbitration_id])

    def _simulation(self, stats: ECUStats) -> _RigSimulation:
        """A fresh pass through the scenario, counting into `stats`."""
        return _RigSimulation(self, stats)


class _RigSimulation:
    """One pass through the scenario: plant state, alive counters, input schedule."""

    def __init__(self, ecu: RigECU, stats: ECUStats) -> None:
        self.ecu, self.stats = ecu, stats
        R = ecu.model.R
        sigma = float(np.sqrt(np.mean(np.diag(R)))) * ecu.scenario.current_sigma / 0.5
        self.plant = PlantSimulator(ecu.model, 1.0 / ecu.rate, seed=ecu.seed,
                                    process=ecu.scenario.process, current_sigma=sigma)
        self.plant.x = steady_state(self.plant, self._u(0.0))
        self.k = 0
        self.counters: dict[str, int] = {}
        self.last_u: float | None = None
        self.sync_pending = False
        self.last_scenario_time = (max(ecu.samples_for(ecu.scenario.duration), 1) - 1) / ecu.rate

    def _u(self, t: float) -> np.ndarray:
        return np.full(self.ecu.m, float(self.ecu.scenario.voltage_at(t)))

    def _gamma(self, t: float) -> np.ndarray:
        g = self.ecu.scenario.gamma_at(t)
        out = np.zeros(self.ecu.m)
        out[: len(g)] = g
        return out

    def _counter(self, name: str) -> int | None:
        if not self.ecu.codec.specs[name].e2e:
            return None
        c = self.counters.get(name, 0)
        self.counters[name] = (c + 1) & 0xF
        return c

    def _input_due(self, k: int) -> bool:
        ratio = self.ecu.input_rate / self.ecu.rate
        return k == 0 or math.floor(k * ratio + 1e-9) != math.floor((k - 1) * ratio + 1e-9)

    def sample(self) -> tuple[int, float, np.ndarray, np.ndarray, np.ndarray]:
        """This step's sample index k, its time, the scenario's input and gamma (held after
        its end) and the plant's output."""
        k = self.k
        t = k / self.ecu.rate
        t_in = min(t, self.last_scenario_time)
        u, gamma = self._u(t_in), self._gamma(t_in)
        return k, t, u, gamma, self.plant.output(u, gamma)

    def step(self, emit: bool, time_base: float) -> list[can.Message]:
        ecu, plant = self.ecu, self.plant
        k, t, u, gamma, y = self.sample()
        changed = float(u[0]) != self.last_u
        self.last_u = float(u[0])
        names = [ecu.out_name]
        if changed or self._input_due(k):
            names += [n for n in ecu.input_names if n != ecu.out_name]
        if ecu.truth_name is not None and ecu.truth_name not in names:
            names.append(ecu.truth_name)
        msgs: list[can.Message] = []
        # sync frames at start and each whole second (a second skipped while catching up
        # is sent with the next sample sent), before the sample's frames
        sync_due = bool(ecu.synced) and (k == 0 or math.floor(t + 1e-9) != math.floor(
            (k - 1) / ecu.rate + 1e-9))
        if emit and (sync_due or self.sync_pending):
            self.sync_pending = False
            for name in ecu.synced:
                msgs.append(self._message(*ecu.codec.encode_sync(name, ecu.node),
                                          time_base + t, ecu.codec.sync_message(ecu.node)))
                self.stats.produced["sync"] += 1
        else:
            self.sync_pending = self.sync_pending or sync_due
        for name in names:
            counter = self._counter(name)
            if not emit:
                continue
            fid, ext, data = ecu.codec.encode_sample(name, ecu.node, u, y,
                                                      float(gamma.max()), counter)
            msgs.append(self._message(fid, ext, data, time_base + t,
                                      ecu.codec.message(name, ecu.node)))
            self.stats.produced[name] += 1
        plant.advance(u, gamma)
        self.k += 1
        self.stats.samples += 1
        return msgs

    @staticmethod
    def _message(fid: int, ext: bool, data: bytes, ts: float,
                 dbc_message: Message) -> can.Message:
        fd = bool(dbc_message.is_fd)  # as the rig's DBC says
        return can.Message(timestamp=ts, arbitration_id=fid, is_extended_id=ext, is_fd=fd,
                           bitrate_switch=fd, data=data)
