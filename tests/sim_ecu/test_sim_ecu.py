"""sim_ecu: the virtual motor ECU (offline frames, real-time run on a bus) and its CLI.

No mocks: buses are python-can's in-process ``virtual`` interface (two Bus objects on one
channel see each other's frames), the CLI runs as a subprocess, and the ``vcan``-marked test
runs it on a real SocketCAN vcan (natively or in User-Mode Linux).
"""

from __future__ import annotations

import json
import logging
import math
import os
import queue
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import IO

import can
import numpy as np
import pytest

from monitor.bus.codec import Decoded, MotorDatabase, load_database
from monitor.estimation.model import DCMotorParameters, dc_motor
from sim_ecu.cli import main
from sim_ecu.ecu import ECUError, VirtualECU, load_motor_parameters, motor_parameters
from sim_ecu.plant import simulate
from sim_ecu.scenario import load_scenario, scenario_from_dict
from tests.support.paths import ROOT
from tests.support.pipeline import decode_all
from tests.support.vcan_scripts import RunOnVcan, run_script, script_values


@pytest.fixture(scope="module")
def mdb() -> MotorDatabase:
    return load_database()


@pytest.fixture
def channel() -> str:
    return f"test-sim-ecu-{uuid.uuid4().hex[:8]}"


@pytest.fixture
def bus_pair(channel: str) -> Iterator[tuple[can.BusABC, can.BusABC]]:
    """(sender, receiver) on one fresh virtual channel."""
    tx = can.Bus(interface="virtual", channel=channel)
    rx = can.Bus(interface="virtual", channel=channel)
    try:
        yield tx, rx
    finally:
        tx.shutdown()
        rx.shutdown()


def _drain(bus: can.BusABC) -> list[can.Message]:
    out = []
    while (msg := bus.recv(timeout=0.0)) is not None:
        out.append(msg)
    return out


def _by_kind(decoded: list[Decoded], kind: str) -> list[Decoded]:
    return [d for d in decoded if d.kind == kind]


# ----------------------------------------------------------------------------- frames()


def test_frames_two_seconds_of_fault_outage_recovery(mdb: MotorDatabase) -> None:
    scenario = load_scenario("fault-outage-recovery")
    ecu = VirtualECU(None, mdb, 5, scenario, rate=100.0, voltage_rate=20.0, seed=1)
    frames = list(ecu.frames(2.0))
    decoded = decode_all(mdb, frames)
    assert all(d.node == 5 for d in decoded)
    current, voltage, truth = (_by_kind(decoded, k) for k in ("current", "voltage", "truth"))
    assert (len(current), len(voltage), len(truth)) == (200, 40, 200)
    assert ecu.stats.produced == {"current": 200, "voltage": 40, "truth": 200}
    assert ecu.stats.samples == 200
    # Alive counters: 0, 1, ..., 15, 0, ... per kind.
    for stream in (current, voltage):
        assert [d.counter for d in stream] == [i % 16 for i in range(len(stream))]
    # Timestamps k / rate; voltage every 5th sample.
    assert [d.timestamp for d in current] == pytest.approx([k / 100 for k in range(200)])
    assert [d.timestamp for d in truth] == pytest.approx([k / 100 for k in range(200)])
    assert [d.timestamp for d in voltage] == pytest.approx([5 * j / 100 for j in range(40)])
    assert all(d.value == pytest.approx(220.0) for d in voltage)
    for d in truth:
        assert d.value == pytest.approx(scenario.gamma_at(d.timestamp)[0], abs=1e-4)
    # Frame order within a sample: current, voltage (when due), truth.
    assert [mdb.decode_can(m).kind for m in frames[:4]] == ["current", "voltage", "truth",
                                                            "current"]


def test_keyed_ecu_sends_secoc_syncs_at_start_and_every_second(mdb: MotorDatabase) -> None:
    key = bytes(range(16))
    ecu = VirtualECU(None, mdb, 5, load_scenario("healthy"), rate=100.0, key=key)
    frames = list(ecu.frames(2.5))
    rx = load_database(secoc_key=key)
    decoded = decode_all(rx, frames)  # the syncs make a fresh monitor accept the rest
    syncs = _by_kind(decoded, "sync")
    assert [(d.timestamp, d.raw["SyncKind"], d.value) for d in syncs] == [
        (0.0, 0, 0), (0.0, 1, 0), (1.0, 0, 100), (1.0, 1, 20), (2.0, 0, 200), (2.0, 1, 40)]
    assert [d.kind for d in decoded[:3]] == ["sync", "sync", "current"]  # before the data
    assert ecu.stats.produced == {"current": 250, "voltage": 50, "truth": 250, "sync": 6}
    assert all(m.arbitration_id == 0x1F5 for m in frames if mdb.decode_can(m).kind == "sync")
    # without a key: no syncs, and the stats look as they always did
    plain = VirtualECU(None, mdb, 5, load_scenario("healthy"), rate=100.0)
    assert not any(d.kind == "sync" for d in decode_all(mdb, list(plain.frames(2.5))))
    assert "sync" not in plain.stats.produced and "sync" not in plain.stats.summary()


def test_a_sync_on_a_skipped_sample_goes_out_with_the_next_one(mdb: MotorDatabase) -> None:
    from sim_ecu.ecu import _Simulation

    key = bytes(range(16))
    ecu = VirtualECU(None, mdb, 2, load_scenario("healthy"), rate=100.0, key=key)
    sim = _Simulation(ecu, ecu.stats)
    kinds = [[mdb.decode_can(m).kind for m in sim.step(True, 0.0)] for _ in range(99)]
    assert kinds[0][:2] == ["sync", "sync"] and all("sync" not in k for k in kinds[1:])
    sim.step(False, 0.0)  # sample 100, a sync sample, skipped (an overrun)
    sim.step(False, 0.0)
    late = decode_all(mdb, sim.step(True, 0.0))
    assert [d.kind for d in late[:3]] == ["sync", "sync", "current"]
    assert late[0].value == 99  # the freshness signed so far: samples 100, 101 unsigned


def test_truth_follows_the_whole_scenario(mdb: MotorDatabase) -> None:
    scenario = load_scenario("fault-outage-recovery")
    ecu = VirtualECU(None, mdb, 0, scenario, seed=2)
    truth = _by_kind(decode_all(mdb, list(ecu.frames())), "truth")
    assert len(truth) == round(scenario.duration * 100)
    gammas = np.array([d.value for d in truth])
    expected = np.array([scenario.gamma_at(k / 100)[0] for k in range(len(truth))])
    np.testing.assert_allclose(gammas, expected, atol=1e-4)
    assert {0.0, 0.4, 1.0} <= {round(g, 4) for g in gammas}
    # The outage (gamma = 1) removes the effective voltage: current decays towards 0.
    outage = [d.raw["TrueCurrent"] for d in truth if 10.5 <= d.timestamp < 11.0]
    assert max(abs(c) for c in outage) < 5.0


def test_current_frames_carry_the_plant_simulation(mdb: MotorDatabase) -> None:
    """Same model, seed and noise order as sim_ecu.plant.simulate, up to DBC resolution."""
    scenario = load_scenario("incipient")
    ecu = VirtualECU(None, mdb, 3, scenario, seed=11)
    decoded = decode_all(mdb, list(ecu.frames()))
    current = np.array([d.value for d in _by_kind(decoded, "current")])
    truth = _by_kind(decoded, "truth")
    run = simulate(dc_motor(), scenario, 0.01, seed=11)
    np.testing.assert_allclose(current, run.y[:, 0], atol=0.005 + 1e-9)
    np.testing.assert_allclose([d.raw["TrueCurrent"] for d in truth], run.y_true[:, 0],
                               atol=0.005 + 1e-9)
    np.testing.assert_allclose([d.raw["TrueSpeed"] for d in truth], run.x[:, 1],
                               atol=0.005 + 1e-9)


def test_same_seed_same_frames_other_seed_other_currents(mdb: MotorDatabase) -> None:
    scenario = load_scenario("intermittent")

    def payloads(seed: int) -> list[tuple[int, bytes, float]]:
        ecu = VirtualECU(None, mdb, 1, scenario, seed=seed)
        return [(m.arbitration_id, bytes(m.data), m.timestamp) for m in ecu.frames(1.0)]

    a, b, c = payloads(4), payloads(4), payloads(5)
    assert a == b
    ecu = VirtualECU(None, mdb, 1, scenario, seed=4)
    assert [bytes(m.data) for m in ecu.frames(1.0)] == [p for _, p, _ in a]  # repeatable call

    def currents(frames: list[tuple[int, bytes, float]]) -> list[float]:
        return [
            d.value
            for fid, data, ts in frames
            if isinstance(d := mdb.decode(fid, data, False, False, False, ts), Decoded)
            and d.kind == "current"
        ]

    ca, cc = currents(a), currents(c)
    assert len(ca) == len(cc) == 100
    assert sum(x != y for x, y in zip(ca, cc, strict=True)) > 90


def test_voltage_frame_at_every_command_change(mdb: MotorDatabase) -> None:
    scenario = scenario_from_dict(
        {
            "name": "steps",
            "duration": 1.0,
            "voltage": {"steps": [[0.0, 100.0], [0.33, 150.0], [0.71, -50.0]]},
        }
    )
    ecu = VirtualECU(None, mdb, 2, scenario, voltage_rate=10.0)
    voltage = _by_kind(decode_all(mdb, list(ecu.frames())), "voltage")
    times = [round(d.timestamp * 100) for d in voltage]
    assert times == [0, 10, 20, 30, 33, 40, 50, 60, 70, 71, 80, 90]
    for d in voltage:
        assert d.value == pytest.approx(scenario.voltage_at(d.timestamp))
    assert [d.counter for d in voltage] == list(range(12))


def test_non_integer_voltage_ratio_spreads_frames(mdb: MotorDatabase) -> None:
    ecu = VirtualECU(None, mdb, 2, load_scenario("healthy"), rate=100.0, voltage_rate=30.0)
    voltage = _by_kind(decode_all(mdb, list(ecu.frames(1.0))), "voltage")
    assert len(voltage) == 30
    gaps = np.diff([round(d.timestamp * 100) for d in voltage])
    assert set(gaps) <= {3, 4}


def test_values_outside_the_dbc_range_are_clipped_and_counted(mdb: MotorDatabase) -> None:
    # 1000 V on the Table 1 motor: steady current ~ 308 A (> 300 A), command > 400 V.
    scenario = scenario_from_dict(
        {"name": "overdrive", "duration": 0.5, "voltage": {"steps": [[0.0, 1000.0]]}}
    )
    ecu = VirtualECU(None, mdb, 0, scenario)
    decoded = decode_all(mdb, list(ecu.frames()))
    assert all(d.value == pytest.approx(400.0) for d in _by_kind(decoded, "voltage"))
    assert max(d.value for d in _by_kind(decoded, "current")) == pytest.approx(300.0)
    assert ecu.stats.clipped["voltage"] == 10
    assert ecu.stats.clipped["current"] > 0
    assert ecu.stats.clipped["truth"] > 0


def test_inputs_hold_after_the_scenario_and_start_time(mdb: MotorDatabase) -> None:
    scenario = scenario_from_dict(
        {"name": "short", "duration": 1.0, "fault": [{"start": 0.5, "gamma": 0.3}]}
    )
    ecu = VirtualECU(None, mdb, 0, scenario, truth=True)
    truth = _by_kind(decode_all(mdb, list(ecu.frames(2.0, start_time=1000.0))), "truth")
    assert len(truth) == 200
    assert truth[0].timestamp == pytest.approx(1000.0)
    assert truth[-1].timestamp == pytest.approx(1001.99)
    assert [d.value for d in truth[:50]] == [0.0] * 50
    assert [d.value for d in truth[50:]] == pytest.approx([0.3] * 150)  # held past 1 s


def test_no_truth_and_infinite_frames(mdb: MotorDatabase) -> None:
    ecu = VirtualECU(None, mdb, 0, load_scenario("healthy"), truth=False)
    kinds = {d.kind for d in decode_all(mdb, list(ecu.frames(0.5)))}
    assert kinds == {"current", "voltage"}
    endless = ecu.frames(math.inf)
    assert len([next(endless) for _ in range(5000)]) == 5000  # past the 20 s scenario


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"node": 16}, "node"),
        ({"rate": 0.0}, "rate"),
        ({"rate": math.nan}, "rate"),
        ({"voltage_rate": -1.0}, "voltage rate"),
        ({"seed": -1}, "seed"),
    ],
)
def test_bad_configuration_is_one_ecu_error(
    mdb: MotorDatabase, kwargs: dict[str, float], message: str
) -> None:
    args: dict[str, object] = {"node": 0, **kwargs}
    node = args.pop("node")
    with pytest.raises(ECUError, match=message) as info:
        VirtualECU(None, mdb, node, load_scenario("healthy"), **args)  # type: ignore[arg-type]
    assert "\n" not in str(info.value)


def test_bad_duration_and_missing_bus(mdb: MotorDatabase) -> None:
    ecu = VirtualECU(None, mdb, 0, load_scenario("healthy"))
    for bad in (-1.0, math.nan):
        with pytest.raises(ECUError, match="duration"):
            ecu.frames(bad)  # raised at the call, not at the first next()
    with pytest.raises(ECUError, match="needs a bus"):
        ecu.run(0.1)
    assert list(ecu.frames(0.0)) == []


def test_motor_table(mdb: MotorDatabase, tmp_path: Path) -> None:
    path = tmp_path / "slow.toml"
    path.write_text('duration = 1.0\n[motor]\nRa = 4.0\nLa = 1\n', encoding="utf-8")
    params = load_motor_parameters(path)
    assert params == DCMotorParameters(Ra=4.0, La=1.0)
    assert load_motor_parameters("healthy") is None
    ecu = VirtualECU(None, mdb, 0, load_scenario(path), motor=params)
    first = decode_all(mdb, list(ecu.frames(0.01)))[0]
    # Steady current b u / (Ra b + Ke Ki) = 0.05 * 220 / (0.2 + 0.0625).
    assert first.value == pytest.approx(0.05 * 220 / 0.2625, abs=2.0)
    # La = 0 (singular E): the current is algebraic, truth still carries current and speed.
    ecu0 = VirtualECU(None, mdb, 0, load_scenario("healthy"), motor=DCMotorParameters(La=0.0))
    truth = _by_kind(decode_all(mdb, list(ecu0.frames(0.1))), "truth")
    assert truth[0].raw["TrueCurrent"] == pytest.approx(67.69, abs=0.02)
    assert truth[0].raw["TrueSpeed"] == pytest.approx(338.46, abs=0.02)
    for table, msg in (({"Rb": 1.0}, "unknown key"), ({"Ra": -1.0}, "Ra"), ({"J": "x"}, "J")):
        with pytest.raises(ECUError, match=msg):
            motor_parameters(table)


# ----------------------------------------------------------------------------- run()


def _sample_indices(counters: list[int], stamps: list[float], rate: float) -> list[int]:
    """Sample index of each frame from its 4-bit alive counter. A busy machine can make the
    ECU skip 16 samples or more (counted as overruns), which the counter alone cannot tell
    from fewer: the number of whole counter wraps is the one closest to the time between
    the frames (wraps are 80 ms apart at 200 Hz, far more than any jitter)."""
    ks = [counters[0]]
    for i in range(1, len(counters)):
        step = (counters[i] - counters[i - 1]) % 16 or 16
        wraps = max(0, round(((stamps[i] - stamps[i - 1]) * rate - step) / 16))
        ks.append(ks[-1] + step + 16 * wraps)
    return ks


def test_run_paces_frames_without_drift(
    mdb: MotorDatabase, bus_pair: tuple[can.BusABC, can.BusABC]
) -> None:
    tx, rx = bus_pair
    rate = 200.0
    ecu = VirtualECU(tx, mdb, 4, load_scenario("fault-outage-recovery"), rate=rate, seed=3)
    stats = ecu.run(0.5)
    received = decode_all(mdb, _drain(rx))
    current = _by_kind(received, "current")
    assert stats.samples == 100
    assert stats.send_errors == 0
    assert len(current) == stats.sent["current"] == 100 - stats.overruns
    assert len(_by_kind(received, "truth")) == stats.sent["truth"]
    assert len(_by_kind(received, "voltage")) == stats.sent["voltage"] >= 10 - stats.overruns
    counters = [d.counter for d in current if d.counter is not None]
    stamps = [d.timestamp for d in current if d.counter is not None]
    ks = _sample_indices(counters, stamps, rate)
    assert ks[-1] == 99
    # The virtual bus stamps frames at send time. Offsets from the schedule k / rate must
    # not grow: the mean period equals 1 / rate within 1 %. Medians over the first and the
    # last ten frames keep one frame delayed by a busy machine from deciding the outcome.
    offsets = np.array(stamps) - np.array(ks) / rate
    span = (np.median(ks[-10:]) - np.median(ks[:10])) / rate
    mean_period = (np.median(offsets[-10:]) - np.median(offsets[:10]) + span) / (span * rate)
    assert mean_period == pytest.approx(1.0 / rate, rel=0.01)
    assert stats.elapsed == pytest.approx(99 / rate, abs=0.05)


def test_run_stops_on_event(mdb: MotorDatabase, bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    tx, rx = bus_pair
    ecu = VirtualECU(tx, mdb, 0, load_scenario("healthy"))
    stop = threading.Event()
    timer = threading.Timer(0.3, stop.set)
    timer.start()
    t0 = time.monotonic()
    stats = ecu.run(math.inf, stop)
    assert time.monotonic() - t0 < 1.0
    assert 20 <= stats.samples <= 40
    assert len(_by_kind(decode_all(mdb, _drain(rx)), "current")) == stats.sent["current"]


def test_send_errors_are_counted_and_logged_once_per_burst(
    mdb: MotorDatabase, channel: str, caplog: pytest.LogCaptureFixture
) -> None:
    # A receiver whose 1-frame queue is never read: every send after the first fails with
    # CanOperationError ("Could not send message to one or more recipients").
    tx = can.Bus(interface="virtual", channel=channel)
    stuck = can.Bus(interface="virtual", channel=channel, rx_queue_size=1)
    try:
        ecu = VirtualECU(tx, mdb, 0, load_scenario("healthy"), send_timeout=0.0005)
        with caplog.at_level(logging.WARNING, logger="sim_ecu"):
            stats = ecu.run(0.3)
    finally:
        tx.shutdown()
        stuck.shutdown()
    assert stats.samples == 30
    assert stats.total_sent == 1
    assert stats.send_errors == sum(stats.produced.values()) - 1
    failures = [r for r in caplog.records if "send failed" in r.getMessage()]
    assert len(failures) == 1


def test_late_loop_skips_ahead_and_counts_overruns(mdb: MotorDatabase, channel: str) -> None:
    # Each send blocks 40 ms on a full receiver queue: far slower than the 10 ms period.
    tx = can.Bus(interface="virtual", channel=channel)
    stuck = can.Bus(interface="virtual", channel=channel, rx_queue_size=1)
    try:
        ecu = VirtualECU(tx, mdb, 0, load_scenario("healthy"), send_timeout=0.04)
        stats = ecu.run(0.5)
    finally:
        tx.shutdown()
        stuck.shutdown()
    assert stats.samples == 50
    assert stats.overruns > 20
    assert stats.produced["current"] + stats.overruns == 50
    # No burst to catch up: the run ends about when its duration does.
    assert stats.elapsed < 0.5 + 4 * 3 * 0.04


def test_large_catch_up_sends_every_sample_late(mdb: MotorDatabase, channel: str) -> None:
    # The same slow sends, with catch-up allowed past the whole run: nothing is skipped.
    tx = can.Bus(interface="virtual", channel=channel)
    stuck = can.Bus(interface="virtual", channel=channel, rx_queue_size=1)
    try:
        ecu = VirtualECU(tx, mdb, 0, load_scenario("healthy"), send_timeout=0.02,
                         max_catch_up=1000)
        stats = ecu.run(0.2)
    finally:
        tx.shutdown()
        stuck.shutdown()
    assert stats.overruns == 0
    assert stats.produced["current"] == stats.samples == 20


@pytest.mark.parametrize("value", ["0", "-3", "two"])
def test_cli_bad_max_catch_up_is_one_line(capsys: pytest.CaptureFixture[str], value: str) -> None:
    rc = main(["--interface", "virtual", "--channel", "x", "--node", "0",
               "--scenario", "healthy", "--max-catch-up", value])
    err = capsys.readouterr().err
    assert rc == 2
    lines = err.splitlines()
    assert len(lines) == 1 and "--max-catch-up" in lines[0], err


# ----------------------------------------------------------------------------- CLI


def _env(**extra: str) -> dict[str, str]:
    """The test environment without python-can configuration variables."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAN_")}
    env.update(extra)
    return env


def _cli(*args: str, env: dict[str, str] | None = None,
         timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "sim_ecu", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=_env() if env is None else env,
        cwd=ROOT,
    )


def test_cli_runs_and_prints_a_summary() -> None:
    res = _cli("--interface", "virtual", "--channel", "x", "--node", "3",
               "--scenario", "fault-outage-recovery", "--duration", "1")
    assert res.returncode == 0, res.stderr
    lines = res.stderr.splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("sim-ecu: done: node 3, scenario fault-outage-recovery: 100 ")
    assert "current=100 voltage=20 truth=100" in lines[0]


def test_cli_takes_interface_and_channel_from_python_can_config() -> None:
    env = _env(CAN_INTERFACE="virtual", CAN_CHANNEL="from-env")
    res = _cli("--node", "0", "--scenario", "healthy", "--duration", "0.2", "-v", env=env)
    assert res.returncode == 0, res.stderr
    assert "opened interface 'virtual' channel 'from-env'" in res.stderr


def test_cli_in_process_frames_reach_a_receiver(
    mdb: MotorDatabase, channel: str, capsys: pytest.CaptureFixture[str]
) -> None:
    rx = can.Bus(interface="virtual", channel=channel)
    try:
        rc = main(["--interface", "virtual", "--channel", channel, "--node", "7",
                   "--scenario", "healthy", "--duration", "0.2", "--no-truth", "--seed", "9"])
        received = decode_all(mdb, _drain(rx))
    finally:
        rx.shutdown()
    assert rc == 0
    assert {d.kind for d in received} == {"current", "voltage"}
    assert len(_by_kind(received, "current")) == 20
    assert all(d.node == 7 for d in received)
    assert "sim-ecu: done:" in capsys.readouterr().err
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL  # handlers restored


def _key_file(path: Path, content: bytes, mode: int) -> Path:
    path.write_bytes(content)
    path.chmod(mode)
    return path


SECOC_KEY = bytes(range(0x40, 0x50))


def test_cli_with_a_key_sends_signed_frames(
    channel: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    key = _key_file(tmp_path / "ecu.key", SECOC_KEY.hex().encode() + b"\n", 0o600)
    rx = can.Bus(interface="virtual", channel=channel)
    try:
        rc = main(["--interface", "virtual", "--channel", channel, "--node", "4",
                   "--scenario", "healthy", "--duration", "0.2", "--seed", "9",
                   "--key", str(key)])
        frames = _drain(rx)
    finally:
        rx.shutdown()
    assert rc == 0, capsys.readouterr().err
    keyed = load_database(secoc_key=SECOC_KEY)
    decoded = decode_all(keyed, frames)  # every frame verifies: authentic and fresh
    assert {d.kind for d in decoded} == {"current", "voltage", "truth", "sync"}
    # one sync per stream before the first data frame (the run is shorter than a second)
    assert [(d.kind, d.raw.get("SyncKind"), d.value) for d in decoded[:2]] == [
        ("sync", 0, 0.0), ("sync", 1, 0.0)]
    assert len(_by_kind(decoded, "sync")) == 2
    signed = [d for d in decoded if d.kind in ("current", "voltage")]
    assert signed and all(d.raw["FreshnessValue"] == (i + 1) % (256 if d.kind == "current" else 16)
                          for kind in ("current", "voltage")
                          for i, d in enumerate(_by_kind(signed, kind)))
    wrong = load_database(secoc_key=bytes(16))
    reasons = {(m.arbitration_id, getattr(wrong.decode_can(m), "reason", None)) for m in frames
               if m.arbitration_id != 0x7E4}
    # the syncs do not verify under another key, so its streams are never synchronised
    assert reasons == {(0x1F4, "bad_mac"), (0x114, "unsynced"), (0x124, "unsynced")}
    err = capsys.readouterr().err
    assert "sim-ecu: done:" in err and "sync=2" in err


@pytest.mark.parametrize(
    ("content", "mode", "needle"),
    [
        (SECOC_KEY.hex().encode(), 0o644, "chmod 600"),
        (SECOC_KEY.hex().encode(), 0o640, "group or others"),
        (b"0123", 0o600, "not an AES key"),
        (None, 0o600, "key file not found"),
    ],
    ids=["world-readable", "group-readable", "wrong-length", "missing"],
)
def test_cli_key_file_errors_are_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: bytes | None, mode: int,
    needle: str,
) -> None:
    path = tmp_path / "ecu.key"
    if content is not None:
        _key_file(path, content, mode)
    rc = main(["--interface", "virtual", "--channel", "x", "--node", "0",
               "--scenario", "healthy", "--key", str(path)])
    err = capsys.readouterr().err
    assert rc == 2
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("sim-ecu: error: ") and needle in lines[0]
    assert str(path) in lines[0] and SECOC_KEY.hex() not in err


def _cli_run(channel: str, *extra: str) -> list[can.Message]:
    """One in-process sim-ecu run of node 4 (0.3 s, no truth); the frames it sent."""
    rx = can.Bus(interface="virtual", channel=channel)
    try:
        rc = main(["--interface", "virtual", "--channel", channel, "--node", "4",
                   "--scenario", "healthy", "--duration", "0.3", "--no-truth", *extra])
        frames = _drain(rx)
    finally:
        rx.shutdown()
    assert rc == 0
    return frames


def test_cli_secoc_state_keeps_the_counters_across_runs(
    channel: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    key = _key_file(tmp_path / "ecu.key", SECOC_KEY.hex().encode(), 0o600)
    state = tmp_path / "ecu.state"
    monitor = load_database(secoc_key=SECOC_KEY)  # one monitor sees every run
    assert monitor.secoc is not None
    args = ("--key", str(key), "--secoc-state", str(state))
    first = decode_all(monitor, _cli_run(channel, *args))
    assert first[0].kind == "sync" and first[0].value == 0
    assert stat_mode(state) == 0o600
    # the freshness counts the frames sent (30 and 6 unless a loaded machine skipped some)
    current, voltage = len(_by_kind(first, "current")), len(_by_kind(first, "voltage"))
    assert current >= 15 and voltage >= 3
    saved = json.loads(state.read_text())["freshness"]
    assert saved == {"tx/current/4": current, "tx/voltage/4": voltage}
    # a second run continues a minute of frames ahead (it might have crashed after a
    # save), says so in its first sync, and the monitor goes on without a rejection
    second = decode_all(monitor, _cli_run(channel, *args))
    margin = 60 * 100
    assert [(d.kind, d.value) for d in second[:2]] == [("sync", current + margin),
                                                       ("sync", voltage + margin)]
    current += margin + len(_by_kind(second, "current"))
    assert monitor.secoc.rx_freshness(("current", 4)) == current
    assert json.loads(state.read_text())["freshness"]["tx/current/4"] == current
    # without the state a run restarts at 0: the monitor takes it for a replay
    third = [monitor.decode_can(m) for m in _cli_run(channel, "--key", str(key))]
    reasons = {getattr(d, "reason", None) for d in third}
    assert reasons <= {"stale_freshness", "bad_mac"} and "stale_freshness" in reasons
    capsys.readouterr()


@pytest.mark.parametrize(
    ("args", "content", "needle"),
    [
        (["--secoc-state", "{state}"], None, "--secoc-state needs --key"),
        (["--key", "{key}", "--secoc-state", "{state}"], b"{}", "not a SecOC state file"),
        (["--key", "{key}", "--secoc-state", "{tmp}"], None, "not a regular file"),
    ],
)
def test_cli_secoc_state_errors_are_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str],
    content: bytes | None, needle: str,
) -> None:
    key = _key_file(tmp_path / "ecu.key", SECOC_KEY.hex().encode(), 0o600)
    state = tmp_path / "ecu.state"
    if content is not None:
        _key_file(state, content, 0o600)
    argv = [a.format(key=key, state=state, tmp=tmp_path) for a in args]
    rc = main(["--interface", "virtual", "--channel", "x", "--node", "0",
               "--scenario", "healthy", *argv])
    err = capsys.readouterr().err
    assert rc == 2
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("sim-ecu: error: ") and needle in lines[0]


def stat_mode(path: Path) -> int:
    return path.stat().st_mode & 0o777


class _StderrLines:
    """Collects a subprocess's stderr lines in a thread (no select on a buffered pipe)."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stderr is not None
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.seen: list[str] = []
        self._thread = threading.Thread(target=self._pump, args=(proc.stderr,), daemon=True)
        self._thread.start()

    def _pump(self, stream: IO[str]) -> None:
        for line in stream:
            self.lines.put(line)
        self.lines.put(None)

    def wait_for(self, needle: str, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            try:
                line = self.lines.get(timeout=left)
            except queue.Empty:
                break
            if line is None:
                break
            self.seen.append(line)
            if needle in line:
                return
        raise AssertionError(f"{needle!r} not seen on stderr: {self.seen}")

    def rest(self, timeout: float = 5.0) -> str:
        self._thread.join(timeout)
        while not self.lines.empty():
            line = self.lines.get()
            if line is not None:
                self.seen.append(line)
        return "".join(self.seen)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_cli_exits_cleanly_on_signal(sig: signal.Signals) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "sim_ecu", "--interface", "virtual", "--channel", "x",
         "--node", "1", "--scenario", "healthy", "--duration", "600", "-v"],
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
        env=_env(),
        cwd=ROOT,
    )
    stderr = _StderrLines(proc)
    try:
        stderr.wait_for("running node 1", timeout=60.0)
        time.sleep(0.3)
        t0 = time.monotonic()
        proc.send_signal(sig)
        proc.wait(timeout=2.0)
        assert time.monotonic() - t0 < 2.0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    err = stderr.rest()
    assert proc.returncode == 0, err
    summary = [line for line in err.splitlines() if line.startswith("sim-ecu: stopped by")]
    assert len(summary) == 1 and sig.name in summary[0], err
    assert "Traceback" not in err


BAD_TOML = 'name = "broken"\nduration = [\n'
BAD_MOTOR = 'duration = 2.0\n[motor]\nRa = -2.0\n'


@pytest.mark.parametrize(
    ("args", "files", "needle"),
    [
        (["--scenario", "no-such-scenario"], {}, "unknown scenario"),
        (["--scenario", "{tmp}/bad.toml"], {"bad.toml": BAD_TOML}, "not valid TOML"),
        (["--scenario", "{tmp}/motor.toml"], {"motor.toml": BAD_MOTOR}, "Ra"),
        (["--scenario", "healthy", "--node", "16"], {}, "--node"),
        (["--scenario", "healthy", "--rate", "0"], {}, "--rate"),
        (["--scenario", "healthy", "--voltage-rate", "-5"], {}, "--voltage-rate"),
        (["--scenario", "healthy", "--duration", "-1"], {}, "--duration"),
        (["--scenario", "healthy", "--node", "one"], {}, "--node"),
        (["--scenario", "healthy", "--dbc", "{tmp}/missing.dbc"], {}, "missing.dbc"),
        (["--scenario", "healthy", "--interface", "socketcan", "--channel", "doesnotexist0"],
         {}, "doesnotexist0"),
        (["--scenario", "healthy", "--interface", "no-such-interface"], {}, "unknown CAN"),
        (["--scenario", "healthy", "--interface", "", "--channel", "x"], {}, "interface"),
    ],
    ids=["scenario", "toml", "motor", "node", "rate", "vrate", "duration", "node-type", "dbc",
         "socketcan", "interface", "no-interface"],
)
def test_cli_configuration_errors_are_one_line(
    tmp_path: Path, args: list[str], files: dict[str, str], needle: str
) -> None:
    for name, text in files.items():
        (tmp_path / name).write_text(text, encoding="utf-8")
    argv = [a.replace("{tmp}", str(tmp_path)) for a in args]
    if "--interface" not in argv:
        argv += ["--interface", "virtual", "--channel", "x"]
    if "--node" not in argv:
        argv += ["--node", "0"]
    res = _cli(*argv)
    assert res.returncode == 2, (res.returncode, res.stderr)
    lines = res.stderr.splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("sim-ecu: error: ")
    assert needle in lines[0]
    assert "Traceback" not in res.stderr
    assert res.stdout == ""


def test_cli_help_exits_zero(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--help"]) == 0
    assert "--voltage-rate" in capsys.readouterr().out


# ----------------------------------------------------------------------------- vcan

@pytest.mark.vcan
def test_cli_on_real_socketcan(
    vcan: RunOnVcan, mdb: MotorDatabase, tmp_path: Path
) -> None:
    res = run_script(vcan, "sim_ecu_cli.sh", env={"OUT": str(tmp_path)}, timeout=180)
    assert res.returncode == 0, (res.stdout, res.stderr)
    values = script_values(res.stdout)
    assert values["dump_rc"] == "0", (tmp_path / "candump.err").read_text()
    ecu_err = (tmp_path / "ecu.err").read_text()
    assert values["ecu_rc"] == "0", ecu_err
    assert "current=100 voltage=20 truth=100, send errors 0" in ecu_err
    with can.CanutilsLogReader(tmp_path / "cap.log") as reader:
        frames = list(reader)
    decoded = decode_all(mdb, frames)
    assert [len(_by_kind(decoded, k)) for k in ("current", "voltage", "truth")] == [100, 20, 100]
    offline = VirtualECU(None, mdb, 2, load_scenario("fault-outage-recovery"), seed=5)
    assert [bytes(m.data) for m in frames] == [bytes(m.data) for m in offline.frames(1.0)]
    # A missing interface on a kernel with SocketCAN: python-can logs an error itself
    # before raising; the CLI still prints exactly one line.
    bad = (tmp_path / "bad.err").read_text().splitlines()
    assert values["bad_rc"] == "2"
    assert len(bad) == 1 and bad[0].startswith("sim-ecu: error: ") and "doesnotexist0" in bad[0]
    # Interface down: every send fails, one warning for the burst, the run goes on.
    down = (tmp_path / "down.err").read_text()
    assert values["down_rc"] == "0", down
    assert down.count("send failed") == 1, down
    assert "send errors 66" in down, down  # 30 current + 6 voltage + 30 truth
