"""The CiA 402 twin as the drive only (``sim-ecu --rig R --host external``), driven by a
master nobody here wrote: the `canopen` library's `Network` on python-can's in-process
``virtual`` interface loads the rig's EDS, starts the node, runs SYNC, sends the target
velocity and the controlword in RPDO4 and reads the twin's TPDO4, heartbeat and EMCY."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import can
import canopen
import pytest

from monitor.bus.rigcodec import RigCodec
from monitor.rig import build_decoder, load_rig
from sim_ecu.cia402 import EMCY_OUTAGE, Cia402ECU, next_state
from sim_ecu.cli import main
from sim_ecu.ecu import ECUError
from sim_ecu.scenario import scenario_from_dict
from tests.support.paths import ROOT

EXAMPLE = ROOT / "rigs" / "cia402-example.toml"
TIMEOUT = 30.0  # generous: a loaded 2-core machine; every wait ends as soon as it holds
SYNC_PERIOD = 0.01  # the rig's rate, 100 Hz
TARGET = 600_000  # 600 rpm in the drive's unit, 0.001 rpm
TPDOS = (0x181, 0x281, 0x381, 0x481)
#: statusword values (CiA 402) the master waits for
SOD, RTSO, SO, OE, FAULT = 0x40, 0x21, 0x23, 0x27, 0x08
STATUS_MASK = 0x6F


def wait_until(condition: Callable[[], bool], what: str) -> None:
    end = time.monotonic() + TIMEOUT
    while not condition():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.005)


@dataclass
class Bench:
    """The master's side: its network, the node and what it heard."""

    network: canopen.Network
    node: canopen.RemoteNode
    ecu: Cia402ECU
    beats: list[int] = field(default_factory=list)
    tpdo_ids: list[int] = field(default_factory=list)  # every TPDO frame of the drive
    seen: list[tuple[int, int]] = field(default_factory=list)  # TPDO4: statusword, velocity

    def beats_after(self, state: int, count: int) -> None:
        """Wait for `count` heartbeats in NMT `state` from now."""
        start = len(self.beats)
        wait_until(lambda: self.beats[start:].count(state) >= count,
                   f"{count} heartbeats in state {state}")

    def status(self, want: int) -> None:
        start = len(self.seen)
        wait_until(lambda: any(s & STATUS_MASK == want for s, _ in self.seen[start:]),
                   f"statusword 0x{want:04X}")

    def control(self, word: int, target: int = TARGET) -> None:
        rpdo = self.node.rpdo[4]
        rpdo["Controlword 1"].raw = word
        rpdo["Target Velocity 1"].raw = target  # set_data updates the periodic task


@pytest.fixture
def bench() -> Iterator[Bench]:
    channel = f"cia402-drive-{id(object())}"
    rig = load_rig(EXAMPLE)
    assert rig.canopen is not None
    codec = build_decoder(rig)
    assert isinstance(codec, RigCodec)
    # healthy, then an outage from 2 s of the model's time (the 200th SYNC) to 2.3 s
    scenario = scenario_from_dict({"name": "outage", "duration": 10.0,
                                   "fault": [{"start": 2.0, "end": 2.3, "gamma": 1.0}]})
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel, receive_own_messages=False)
    bus = can.Bus(interface="virtual", channel=channel)
    stop = threading.Event()
    worker: threading.Thread | None = None
    try:
        node = canopen.RemoteNode(1, str(rig.canopen.file))  # the rig's EDS
        network.add_node(node)
        node.tpdo.read(from_od=True)
        node.rpdo.read(from_od=True)
        for pdo in (node.tpdo[4], node.rpdo[4]):  # as the rig file sets them
            pdo.enabled = True
            pdo.trans_type = 1
        node.tpdo[4].subscribe()
        ecu = Cia402ECU(bus, codec, rig, 1, scenario, seed=1, host="external")
        b = Bench(network, node, ecu)
        node.tpdo[4].add_callback(lambda m: b.seen.append(
            (m["Statusword 1"].raw, m["Velocity Actual Value 1"].raw)))
        node.nmt.add_heartbeat_callback(b.beats.append)
        for cob_id in TPDOS:
            network.subscribe(cob_id, lambda can_id, data, ts: b.tpdo_ids.append(can_id))
        worker = threading.Thread(target=ecu.run, args=(math.inf, stop))
        worker.start()
        wait_until(lambda: b.beats[:1] == [0], "the boot-up")
        yield b
    finally:
        stop.set()
        if worker is not None:
            worker.join(TIMEOUT)
        network.sync.stop()
        if "node" in locals():
            node.rpdo[4].stop()
        network.disconnect()
        bus.shutdown()


def test_a_canopen_master_drives_the_twin(bench: Bench) -> None:
    node, network = bench.node, bench.network
    # pre-operational: SYNC and an RPDO that enables the drive; no PDO, the RPDO unread
    bench.control(0x000F)
    network.sync.start(SYNC_PERIOD)
    node.rpdo[4].start(SYNC_PERIOD)
    bench.beats_after(127, 3)
    assert bench.tpdo_ids == []
    network.sync.stop()
    node.rpdo[4].stop()
    # operational without SYNC: still no synchronous TPDO
    node.nmt.state = "OPERATIONAL"
    bench.beats_after(5, 3)
    assert bench.tpdo_ids == []
    assert bench.ecu.received["nmt"] == 1
    # SYNC: the TPDOs answer; the controlword walks the CiA 402 state machine
    bench.control(0x0006)
    node.rpdo[4].start(SYNC_PERIOD)
    network.sync.start(SYNC_PERIOD)
    bench.status(RTSO)
    assert set(bench.tpdo_ids) == set(TPDOS)  # TPDO1..4, all synchronous (type 1)
    bench.control(0x0007)
    bench.status(SO)
    # not enabled, the power stage is off: the motor stays at rest whatever the target
    assert all(abs(v) < 1_000 for s, v in bench.seen if s & STATUS_MASK != OE)
    bench.control(0x000F)
    bench.status(OE)
    # the velocity follows the master's target by the rig's first-order lag
    wait_until(lambda: bench.seen[-1][0] & STATUS_MASK == OE
               and abs(bench.seen[-1][1] - TARGET) < 0.01 * TARGET, "the target velocity")
    assert node.emcy.log == []  # the outage is 2 s of SYNCs away
    # the scenario's outage: EMCY, Fault, the error reset at its end, Fault until reset
    wait_until(lambda: len(node.emcy.log) >= 2, "the EMCY and its reset")
    assert [e.code for e in node.emcy.log] == [EMCY_OUTAGE, 0]
    assert node.emcy.log[0].register == 0x01
    assert any(s & STATUS_MASK == FAULT for s, _ in bench.seen)
    bench.status(FAULT)
    bench.control(0x0080)  # fault reset
    bench.status(SOD)
    for word, state in ((0x0006, RTSO), (0x000F, OE)):  # 3 and 4 in one from RTSO
        bench.control(word)
        bench.status(state)
    # NMT stop: heartbeat 4 and no PDO though SYNC runs
    node.nmt.state = "STOPPED"
    bench.beats_after(4, 1)
    sent = len(bench.tpdo_ids)
    bench.beats_after(4, 3)
    assert len(bench.tpdo_ids) == sent
    assert bench.beats[:2] == [0, 127]
    assert bench.ecu.received["rejected"] == 0 and bench.ecu.received["rpdo"] > 0


def test_nmt_to_all_nodes_and_reset(bench: Bench) -> None:
    """NMT for all nodes (node 0) starts the drive; reset node boots it again into
    pre-operational, where SYNC gets no answer."""
    bench.network.nmt.state = "OPERATIONAL"  # the library's broadcast master
    bench.beats_after(5, 1)
    bench.network.sync.start(SYNC_PERIOD)
    wait_until(lambda: len(bench.tpdo_ids) >= 8, "TPDOs")
    bench.node.nmt.state = "RESET"
    wait_until(lambda: 0 in bench.beats[1:], "the second boot-up")
    bench.beats_after(127, 1)
    sent = len(bench.tpdo_ids)
    bench.beats_after(127, 2)
    assert len(bench.tpdo_ids) == sent


@pytest.mark.parametrize(("state", "word", "after"), [
    ("SWITCH ON DISABLED", 0x000F, "SWITCH ON DISABLED"),  # enable needs shutdown first
    ("SWITCH ON DISABLED", 0x0006, "READY TO SWITCH ON"),
    ("OPERATION ENABLED", 0x0007, "SWITCHED ON"),  # disable operation
    ("OPERATION ENABLED", 0x0002, "QUICK STOP ACTIVE"),
    ("QUICK STOP ACTIVE", 0x000F, "OPERATION ENABLED"),
    ("SWITCHED ON", 0x0000, "SWITCH ON DISABLED"),  # disable voltage
    ("OPERATION ENABLED", 0x0080, "OPERATION ENABLED"),  # fault reset outside Fault
])
def test_the_controlword_moves_the_state_machine(state: str, word: int, after: str) -> None:
    assert next_state(state, word, 0, False) == after


def test_fault_reset_needs_a_rising_bit_7_and_the_outage_over() -> None:
    assert next_state("FAULT", 0x0080, 0x0000, True) == "FAULT"
    assert next_state("FAULT", 0x0080, 0x0080, False) == "FAULT"
    assert next_state("FAULT", 0x0080, 0x000F, False) == "SWITCH ON DISABLED"


def test_an_external_host_needs_a_bus_and_a_canopen_rig(
        capsys: pytest.CaptureFixture[str]) -> None:
    rig = load_rig(EXAMPLE)
    codec = build_decoder(rig)
    assert isinstance(codec, RigCodec)
    ecu = Cia402ECU(None, codec, rig, 1, scenario_from_dict({"name": "ok", "duration": 1.0}),
                    host="external")
    with pytest.raises(ECUError, match="runs on a bus only"):
        next(iter(ecu.frames()))
    assert main(["--node", "0", "--scenario", "healthy", "--host", "external"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["sim-ecu: error: --host external needs a CANopen rig ([bus] protocol = "
                   "\"canopen\" in --rig)"]
