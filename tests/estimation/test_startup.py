"""Start-up without a false alarm: the estimator starts from what the first output says.

A monitor meets a motor at rest when the first command comes (the first current one period
into the response, or measured before the command acts), a motor running at the steady
state of its command or of an earlier one, and the same again after a silence (a gap over
`max_gap_s` restarts the node's estimator; a shorter one is predicted through). From the
first sample on, the reported health state must be fault_free and gamma^ below F1: the
estimator starting from the steady state of the first command read a motor at rest as an
outage (no current at full voltage) for 60-80 ms. Checked through the real pipeline on the
frames of the virtual ECUs, for the paper's DC motor (Table 1, 100 Hz) and the 24 V servo
rig of tests/rigs/servo.toml (1 kHz, back-EMF dominated and stiff), and the columnar replay
engine must report the same samples. A fault present when the monitor attaches must still
be found.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from monitor.app.options import monitor_config
from monitor.bus.codec import load_database
from monitor.bus.rigcodec import RigCodec
from monitor.columnar.replay import replay_file
from monitor.diagnosis import HealthState
from monitor.estimation.fuzzy_ukf import FuzzyUKF, select_kernel, start_state
from monitor.estimation.model import dc_motor
from monitor.pipeline import MonitorConfig, MonitorPipeline
from monitor.pipeline.feed import feed_log
from monitor.rig import build_decoder, load_rig
from sim_ecu.ecu import VirtualECU
from sim_ecu.plant import PlantSimulator, steady_state
from sim_ecu.rig_ecu import RigECU
from sim_ecu.scenario import scenario_from_dict
from tests.support.paths import TEST_RIGS
from tests.support.pipeline import Recorder

T0 = 1000.0


@dataclass(frozen=True)
class Plant:
    """A plant on its bus: `frames(steps, duration, faults)` runs its virtual ECU from its
    steady state at t = 0 (rest for a first command of 0)."""

    name: str
    volts: float
    output_id: int  # arbitration id of the node's output frames
    frames: Callable[[list[list[float]], float, list[dict[str, Any]]], list[can.Message]]
    decoder: Callable[[], Any]
    config: MonitorConfig


def _scenario(steps: list[list[float]], duration: float, faults: list[dict[str, Any]]
              ) -> Any:
    return scenario_from_dict({"name": "startup", "duration": duration,
                               "voltage": {"steps": steps}, "fault": faults})


def _paper() -> Plant:
    def frames(steps: list[list[float]], duration: float, faults: list[dict[str, Any]]
               ) -> list[can.Message]:
        ecu = VirtualECU(None, load_database(), 0, _scenario(steps, duration, faults), seed=7)
        return list(ecu.frames(start_time=T0))

    return Plant("paper", 220.0, 0x110, frames, load_database, MonitorConfig(nodes=(0,)))


def _servo() -> Plant:
    rig = load_rig(TEST_RIGS / "servo.toml")

    def rig_codec() -> RigCodec:
        codec = build_decoder(rig)
        assert isinstance(codec, RigCodec)
        return codec

    def frames(steps: list[list[float]], duration: float, faults: list[dict[str, Any]]
               ) -> list[can.Message]:
        sc = _scenario(steps, duration, faults)
        ecu = RigECU(None, rig_codec(), rig, 1, sc, seed=7)
        return list(ecu.frames(start_time=T0))

    fid = rig_codec().frame_id(rig.output_message, 1)
    cfg = monitor_config(argparse.Namespace(nodes=None, rate=None, thresholds=None), rig)
    return Plant("servo", 24.0, fid, frames, rig_codec, cfg)


PLANTS = {"paper": _paper, "servo": _servo}


def _attached(frames: list[can.Message], t: float) -> list[can.Message]:
    """What a monitor attached at scenario time t receives."""
    return [m for m in frames if m.timestamp >= T0 + t - 1e-9]


def _input_first(frames: list[can.Message], output_id: int) -> list[can.Message]:
    """The frames of each sample with its output frame last (an ECU that sends the command
    first: the first output the monitor pairs with a new command is measured before the
    command acts, not one period into the response)."""
    out: list[can.Message] = []
    i = 0
    while i < len(frames):
        j = i
        while j < len(frames) and frames[j].timestamp == frames[i].timestamp:
            j += 1
        group = frames[i:j]
        out += [m for m in group if m.arbitration_id != output_id]
        out += [m for m in group if m.arbitration_id == output_id]
        i = j
    return out


def _silent(frames: list[can.Message], t0: float, t1: float) -> list[can.Message]:
    """The ECU silent from scenario time t0 to t1; other traffic on the bus (a frame of an
    unknown ID every 50 ms) lets the replay see the silence, as a live monitor's timer does."""
    kept = [m for m in frames if not T0 + t0 - 1e-9 <= m.timestamp < T0 + t1 - 1e-9]
    other = [can.Message(arbitration_id=0x7F3, data=bytes(8), is_extended_id=False,
                         timestamp=T0 + t) for t in np.arange(t0 + 0.0007, t1, 0.05)]
    return sorted(kept + other, key=lambda m: m.timestamp)


def _per_frame(plant: Plant, frames: Iterable[can.Message]) -> tuple[MonitorPipeline, Recorder]:
    rec = Recorder()
    pipe = MonitorPipeline(plant.decoder(), plant.config, sink=rec)
    feed_log(pipe, frames)
    return pipe, rec


def _assert_fault_free(plant: Plant, rec: Recorder, min_samples: int) -> None:
    f1 = plant.config.thresholds.f1
    assert len(rec.samples) >= min_samples
    gammas = np.array([s.gamma for s in rec.samples])
    bad = [(round(s.t - T0, 3), s.state.label, round(s.gamma, 3)) for s in rec.samples
           if s.state != HealthState.FAULT_FREE or not s.gamma < f1]
    assert not bad, f"{plant.name}: {bad[:5]} (max gamma^ {gammas.max():.3f})"
    # only silences interrupt fault_free: the first sample is reported fault_free at once
    states = [(e.previous, e.state) for e in rec.transitions]
    assert states[0] == ("no_data", "fault_free"), states
    assert all({a, b} == {"no_data", "fault_free"} for a, b in states), states
    assert rec.transitions[0].t == rec.samples[0].t


def _same_in_columnar(plant: Plant, frames: list[can.Message], rec: Recorder,
                      tmp_path: Path) -> None:
    """The columnar replay engine starts and restarts the estimator the same way."""
    path = tmp_path / f"{plant.name}.log"
    with can.Logger(str(path)) as lg:
        for m in frames:
            lg.on_message_received(m)
    col = Recorder()
    replay_file(path, plant.decoder(), plant.config, col, chunk_frames=997)
    assert [(s.t, s.state, s.gamma) for s in col.samples] == \
        [(s.t, s.state, s.gamma) for s in rec.samples]
    assert col.transitions == rec.transitions


# (steps [t, volts] as fractions of the plant's voltage, duration, attached at)
STARTS = {
    # at rest when the first command comes: the ECU sends the output of a sample before
    # its command, so the first current paired with it is one period into the response
    "rest-step": ([[0.0, 0.0], [1.0, 1.0]], 3.0, 1.0),
    # running at the steady state of its command
    "running": ([[0.0, 1.0]], 3.0, 1.503),
    # running at the steady state of an earlier command, the first one seen is another
    "running-other-command": ([[0.0, 0.5], [1.5, 1.0]], 3.5, 1.5),
}


@pytest.mark.parametrize("plant_name", sorted(PLANTS))
@pytest.mark.parametrize("start", sorted(STARTS))
def test_start_reports_fault_free_from_the_first_sample(plant_name: str, start: str,
                                                        tmp_path: Path) -> None:
    plant = PLANTS[plant_name]()
    steps, duration, t_attach = STARTS[start]
    frames = _attached(plant.frames([[t, f * plant.volts] for t, f in steps], duration, []),
                       t_attach)
    pipe, rec = _per_frame(plant, frames)
    _assert_fault_free(plant, rec, int((duration - t_attach - 0.1) * plant.config.rate))
    est = next(iter(pipe.nodes.values())).estimator
    assert est.repairs == 0
    _same_in_columnar(plant, frames, rec, tmp_path)


@pytest.mark.parametrize("plant_name", sorted(PLANTS))
def test_start_at_rest_with_the_command_before_the_output(plant_name: str) -> None:
    # the first output the monitor pairs with the command was measured before it acted
    plant = PLANTS[plant_name]()
    frames = plant.frames([[0.0, 0.0], [1.0, plant.volts]], 3.0, [])
    _, rec = _per_frame(plant, _input_first(_attached(frames, 1.0), plant.output_id))
    _assert_fault_free(plant, rec, int(1.9 * plant.config.rate))
    assert abs(rec.samples[0].measured) < 0.05 * abs(rec.samples[-1].measured)  # at rest


# (steps as fractions of the plant's voltage, duration, silence from, to, restarts)
SILENCES = {
    # the motor keeps running through a silence longer than max_gap_s: restarted
    "restart-running": ([[0.0, 1.0]], 9.5, 1.0, 7.0, 1),
    # the motor stopped in the silence and is started again with the first command after
    "restart-from-rest": ([[0.0, 1.0], [1.0, 0.0], [7.0, 1.0]], 9.0, 1.0, 7.0, 1),
    # a silence shorter than max_gap_s: predicted through, not restarted
    "predicted-through": ([[0.0, 1.0]], 4.0, 1.0, 2.0, 0),
}


@pytest.mark.parametrize("plant_name", sorted(PLANTS))
@pytest.mark.parametrize("silence", sorted(SILENCES))
def test_after_a_silence_the_node_reports_fault_free_at_once(plant_name: str, silence: str,
                                                             tmp_path: Path) -> None:
    plant = PLANTS[plant_name]()
    steps, duration, s0, s1, restarts = SILENCES[silence]
    assert s1 - s0 > plant.config.silence_timeout_s
    assert (s1 - s0 > plant.config.max_gap_s) == (restarts == 1)
    frames = _silent(plant.frames([[t, f * plant.volts] for t, f in steps], duration, []),
                     s0, s1)
    pipe, rec = _per_frame(plant, _attached(frames, 0.5))
    _assert_fault_free(plant, rec, int((duration - 0.5 - (s1 - s0) - 0.1) * plant.config.rate))
    assert pipe.counters.get("estimator/restarts", 0) == restarts
    assert [e.state for e in rec.transitions] == ["fault_free", "no_data", "fault_free"]
    back = next(s for s in rec.samples if s.t >= T0 + s1 - 1e-9)
    assert rec.transitions[-1].t == back.t  # fault_free again on the first sample back
    _same_in_columnar(plant, _attached(frames, 0.5), rec, tmp_path)


@pytest.mark.parametrize("plant_name", sorted(PLANTS))
def test_a_fault_present_when_the_monitor_attaches_is_still_found(plant_name: str) -> None:
    # attached to a running motor that has lost 40 % of its input for seconds: the start
    # does not read the fault as a start-up transient for ever, and not as an outage
    plant = PLANTS[plant_name]()
    frames = plant.frames([[0.0, plant.volts]], 5.0, [{"start": 0.0, "gamma": 0.4}])
    _, rec = _per_frame(plant, _attached(frames, 3.0))
    states = [e.state for e in rec.transitions]
    assert states[-1] == "fault" and "outage" not in states, states
    assert rec.transitions[-1].t - rec.samples[0].t < 0.6
    assert all(s.state != HealthState.OUTAGE for s in rec.samples)
    assert np.mean([s.gamma for s in rec.samples[-100:]]) == pytest.approx(0.4, abs=0.03)


# ----------------------------------------------------------------------------- the estimator


def _rest_start(plant: str) -> tuple[Any, np.ndarray, np.ndarray, float]:
    """(model, u, y, T): a motor at rest, its command stepped at the first sample (the
    estimator's convention: u[k] acted over the step into y[k])."""
    if plant == "paper":
        cont, T, volts, sigma = dc_motor(), 0.01, 220.0, 0.5
    else:
        rig = load_rig(TEST_RIGS / "servo.toml")
        cont, T, volts, sigma = monitor_config(
            argparse.Namespace(nodes=None, rate=None, thresholds=None), rig).plant(), \
            1e-3, 24.0, 0.01
    sim = PlantSimulator(cont, T, seed=11, current_sigma=sigma)
    N = round(0.5 / T)
    u = np.full((N, 1), volts)
    y = np.zeros((N, 1))
    for k in range(N):
        sim.advance(u[k], np.zeros(1))
        y[k] = sim.output(u[k], np.zeros(1))
    return cont.discretize(T), u, y, T


@pytest.mark.parametrize("plant", ["paper", "servo"])
def test_start_state_follows_the_first_output(plant: str) -> None:
    model, u, y, T = _rest_start(plant)
    P = np.asarray(FuzzyUKF(model).P[:model.n, :model.n])  # the plant's (no bias states)
    # at rest: the output contradicts the steady state of the command -> from the output
    st = start_state(model, u[0], y[0], P)
    assert st.measured and not st.V.any()
    assert abs(st.x[0] - y[0, 0]) < 3.0 * np.sqrt(model.R[0, 0])  # the current, as measured
    assert np.sqrt(st.P[1, 1]) > 100.0 * np.sqrt(P[1, 1])  # the speed: wide open
    assert np.all(np.linalg.eigvalsh(st.P) > 0)
    # running at that steady state: the steady state, coupled to the unknown gamma
    A, B, _ = model.at(T)
    x_ss = np.linalg.solve(np.eye(model.n) - A, B @ u[0])
    st = start_state(model, u[0], model.C @ x_ss, P)
    assert not st.measured and np.allclose(st.x, x_ss) and st.V.any()


@pytest.mark.parametrize("plant", ["paper", "servo"])
def test_step_many_and_every_kernel_agree_on_a_start_from_the_output(plant: str) -> None:
    model, u, y, T = _rest_start(plant)
    dt = np.full(len(u), T)
    one = FuzzyUKF(model)
    rows = [(o.gamma.copy(), o.y_est.copy(), o.nis) for o in
            (one.step(u[k], y[k], T) for k in range(len(u)))]
    assert max(g.max() for g, _, _ in rows) < 0.15
    for chunk in (1, 7, len(u)):
        many = FuzzyUKF(model)
        got = []
        for i in range(0, len(u), chunk):
            r = many.step_many(u[i:i + chunk], y[i:i + chunk], dt[i:i + chunk])
            got += [(r.gamma[k], r.y_est[k], r.nis[k]) for k in range(r.count)]
        assert len(got) == len(rows)
        for (g1, e1, n1), (g2, e2, n2) in zip(rows, got, strict=True):
            assert np.array_equal(g1, g2) and np.array_equal(e1, e2) and n1 == n2
    # the interpreted kernel (what the AOT build compiles) computes the same
    py = FuzzyUKF(model)
    py.kernel_name, py._kernel = select_kernel("python")
    for k in range(len(u) if plant == "paper" else 150):
        o = py.step(u[k], y[k], T)
        assert np.allclose(o.gamma, rows[k][0], rtol=0, atol=1e-9)
        assert np.allclose(o.y_est, rows[k][1], rtol=1e-9, atol=1e-9)


def test_steady_start_stays_for_a_motor_running_at_the_first_command() -> None:
    # what steady_start exists for: attached to a running motor, no transient at all
    model = dc_motor().discretize(0.01)
    sim = PlantSimulator(dc_motor(), 0.01, seed=2, current_sigma=0.5)
    sim.x = steady_state(sim, np.array([220.0]))
    est = FuzzyUKF(model)
    g = []
    for _ in range(200):
        y = sim.output(np.array([220.0]), np.zeros(1))
        g.append(est.step([220.0], y, 0.01).gamma[0])
        sim.advance(np.array([220.0]), np.zeros(1))
    assert est._onset_floor == 0  # the kernel ran on the first sample: no start from the output
    assert max(g) < 0.1


@pytest.mark.parametrize("running", [False, True])
def test_a_start_the_output_cannot_tell_from_rest(running: bool) -> None:
    # A strongly back-EMF dominated motor with a noisy sensor: its steady current (0.87 A)
    # is within the noise (0.6 A) of rest's, so the first output cannot say whether it
    # runs at 157 rad/s or stands still. Started at that steady state while at rest, the
    # filter was sure of the speed and read the start-up current (18 A) as an outage.
    from monitor.estimation.model import DCMotorParameters

    cont = dc_motor(DCMotorParameters(J=6e-4, b=3.6e-3, Ke=0.655, Ki=0.655, Ra=0.32,
                                      La=0.045), q=1e-5, r=0.6**2)
    T, volts = 1e-3, 103.0
    model = cont.discretize(T)
    sim = PlantSimulator(cont, T, seed=3, current_sigma=0.6)
    u, z = np.array([volts]), np.zeros(1)
    if running:
        sim.x = steady_state(sim, u)
    else:
        sim.advance(u, z)  # the first output one period into the response
    est = FuzzyUKF(model)
    y = sim.output(u, z)
    assert start_state(model, u, y, np.asarray(est.P[:model.n, :model.n])).measured
    g = []
    for _ in range(1000):
        g.append(est.step(u, y, T).gamma[0])
        sim.advance(u, z)
        y = sim.output(u, z)
    assert max(g) < 0.15 and est.repairs == 0
