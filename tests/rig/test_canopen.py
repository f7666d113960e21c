"""CANopen CiA 402 rigs: the bus description built from public EDS and DCF files
(tests/data/eds), one line per bad file, both engines on the CiA 402 twin's frames, and the
twin read by the `canopen` library's own `Network` as a master reads a drive (python-can's
``virtual`` interface; the vcan run is tests/integration/test_canopen_vcan.py)."""

from __future__ import annotations

import argparse
import json
import threading
from dataclasses import replace
from pathlib import Path

import can
import canopen
import pytest

from monitor.app.identify import collect
from monitor.app.options import monitor_config
from monitor.bus.cia402 import DriveReport, DriveWatch, cia402_state, emcy_name
from monitor.bus.codec import Decoded
from monitor.bus.logfile import read_log
from monitor.bus.rigcodec import RigCodec
from monitor.columnar.replay import ReplayResult, replay_file
from monitor.pipeline import MonitorPipeline
from monitor.pipeline.events import BusEvent, DiagnosisEvent
from monitor.pipeline.feed import feed_log
from monitor.rig import Rig, RigError, build_decoder, load_rig
from monitor.runtime.paths import is_own_file
from monitor.sinks.base import Sink
from sim_ecu.cia402 import EMCY_OUTAGE, STATUS_FAULT, STATUS_OPERATION_ENABLED, Cia402ECU
from sim_ecu.scenario import scenario_from_dict
from tests.support import motor_monitor
from tests.support.cli_cases import CliCase, run_cli_case
from tests.support.dbc import REPO_DBC
from tests.support.paths import ROOT, TEST_DATA
from tests.support.rig_files import rig_refusal

EDS = TEST_DATA / "eds"
EXAMPLE = ROOT / "rigs" / "cia402-example.toml"
NO_OVERRIDES = argparse.Namespace(nodes=None, rate=None, thresholds=None)
RPM = 2 * 3.141592653589793 / 60

#: 6 s: healthy, a 40 % loss from 2 s, an outage 3.5-4.5 s, healthy again.
SCENARIO = {"name": "cia402-fault-outage", "duration": 6.0,
            "fault": [{"start": 2.0, "end": 3.5, "gamma": 0.4},
                      {"start": 3.5, "end": 4.5, "gamma": 1.0}]}

#: What the twin's drive says during `SCENARIO`: (s from the start, report kind, event
#: level, text), as the drive watch reports it and the engines' bus events say it.
TWIN_REPORTS = [
    (0.0, "nmt", "INFO", "NMT BOOT-UP"),
    (0.0, "nmt", "INFO", "NMT OPERATIONAL"),
    (0.0, "cia402", "INFO", "CiA 402 OPERATION ENABLED (statusword 0x0027)"),
    (3.5, "emcy", "WARN", "EMCY 0x5000 device hardware (error register 0x01: generic)"),
    (3.5, "cia402", "WARN", "CiA 402 FAULT (statusword 0x0008)"),
    (4.5, "emcy", "INFO", "EMCY 0x0000 error reset (error register 0x00: none)"),
    (4.5, "cia402", "INFO", "CiA 402 OPERATION ENABLED (statusword 0x0027)"),
]


def _codec(rig: Rig) -> RigCodec:
    codec = build_decoder(rig)
    assert isinstance(codec, RigCodec)
    return codec


def _rig_text(tmp_path: Path, bus: str, signals: str) -> Path:
    path = tmp_path / "rig.toml"
    path.write_text(f"""[bus]
protocol = "canopen"
{bus}

[signals]
{signals}

[model]
kind = "state_space"
rate = 100.0
A = [[-20.0]]
B = [[20.0]]
C = [[1.0]]
Q = [[0.05]]
R = [[0.0004]]
""")
    return path


def test_the_example_rig_reads_the_pdos_the_canopen_library_writes() -> None:
    rig = load_rig(EXAMPLE)
    assert [(r.message, r.signal) for r in rig.inputs] == [("RPDO4", "Target Velocity 1")]
    assert [(r.message, r.signal) for r in rig.outputs] == [("TPDO4", "Velocity Actual Value 1")]
    codec = build_decoder(rig)
    # the library encodes the drive's TPDO4 as a drive would send it
    network = canopen.Network()
    node = canopen.RemoteNode(1, str(EDS / "cia402_slave.eds"))
    network.add_node(node)
    node.tpdo.read(from_od=True)
    tpdo = node.tpdo[4]
    tpdo["Statusword 1"].raw = 0x0027
    tpdo["Velocity Actual Value 1"].raw = -1_234_567  # 0.001 rpm
    got = codec.decode(tpdo.cob_id, bytes(tpdo.data), False, False, False, 5.0)
    assert isinstance(got, Decoded)
    assert got.kind == "TPDO4" and got.node == 1
    assert got.outputs[0] == pytest.approx(-1234.567 * RPM)


def test_an_object_in_two_pdos_needs_its_message(tmp_path: Path) -> None:
    bus = 'dcf = "' + str(EDS / "prbt_0_1.dcf") + '"\nnodes = [3]'
    rig = _rig_text(tmp_path, bus, 'inputs = [{ signal = "0x6042" }]\n'
                    'outputs = [{ signal = "velocity_actual_value" }]')
    with pytest.raises(RigError, match=r"signals\.outputs\[0\]\.signal: velocity_actual_value "
                                       r"is mapped by TPDO2, TPDO3: give message"):
        load_rig(rig)
    rig = _rig_text(tmp_path, bus, 'inputs = [{ signal = "0x6042" }]\n'
                    'outputs = [{ message = "TPDO3", signal = "0x606C" }]')
    loaded = load_rig(rig)
    codec = _codec(loaded)
    assert codec.frame_id("TPDO3", 3) == 0x383 and codec.frame_id("RPDO1", 3) == 0x203
    assert loaded.outputs[0].signal == "velocity_actual_value"


def test_a_rated_current_scales_the_per_mille_current(tmp_path: Path) -> None:
    eds = (EDS / "cia402_slave.eds").read_text()
    eds += ("\n[6075]\nParameterName=Motor rated current\nObjectType=0x7\nDataType=0x0007\n"
            "AccessType=rw\nDefaultValue=2500\nPDOMapping=0\n"
            "\n[6078]\nParameterName=Current actual value\nObjectType=0x7\nDataType=0x0003\n"
            "AccessType=ro\nDefaultValue=0\nPDOMapping=1\n")
    (tmp_path / "drive.eds").write_text(eds)
    rig = _rig_text(tmp_path, 'eds = "drive.eds"\nnodes = [2]\n'
                    '[bus.pdo.TPDO1]\nobjects = ["0x6041", "0x6078"]\n'
                    '[bus.pdo.RPDO4]\nenabled = true',
                    'inputs = [{ signal = "0x60FF" }]\n'
                    'outputs = [{ signal = "0x6078", unit = "mA" }]')
    codec = build_decoder(load_rig(rig))
    # 400 per mille of 2500 mA
    got = codec.decode(0x182, bytes([0x27, 0, 400 & 0xFF, 400 >> 8]), False, False, False, 1.0)
    assert isinstance(got, Decoded)
    assert got.outputs[0] == pytest.approx(1000.0)


@pytest.mark.parametrize(("content", "wrong"), [
    ("not an ini file at all\n", "not a valid EDS file"),
    ("[1800]\nParameterName=TPDO\nObjectType=0x9\nSubNumber=2\n[1800sub1]\nParameterName=COB\n"
     "DataType=0x0007\nDefaultValue=$NODEID+0x180\n[1800sub1]\nParameterName=dup\n",
     "not a valid EDS file"),
    (None, "TPDO4 maps 2 object(s), of which 1 the file does not define"),
])
def test_a_bad_eds_is_one_line_naming_the_file(tmp_path: Path, content: str | None,
                                               wrong: str) -> None:
    if content is None:  # the real file with the velocity object removed
        text = (EDS / "cia402_slave.eds").read_text()
        start = text.index("[606C]")
        content = text[:start] + text[text.index("\n[", start + 1) + 1:]
    (tmp_path / "bad.eds").write_text(content)
    rig = _rig_text(tmp_path, 'eds = "bad.eds"\nnodes = [1]',
                    'inputs = [{ signal = "0x60FF" }]\noutputs = [{ signal = "0x606C" }]')
    line = rig_refusal(rig)
    assert line.startswith(f"rig file {rig}: bus.eds: "), line
    assert "bad.eds" in line and wrong in line


@pytest.mark.parametrize(("bus", "key", "wrong"), [
    ('nodes = [1]', "bus.eds", "a CANopen rig names its drive's file"),
    ('eds = "missing.eds"\nnodes = [1]', "bus.eds", "missing.eds"),
    (f'eds = "{EDS / "cia402_slave.eds"}"\nnodes = [0]', "bus.nodes", "1..127"),
    (f'eds = "{EDS / "cia402_slave.eds"}"\nnodes = [1]\n[bus.pdo.XPDO1]\nenabled = true',
     "bus.pdo.XPDO1", "not a PDO name"),
    (f'eds = "{EDS / "cia402_slave.eds"}"\nnodes = [1]\n[bus.pdo.TPDO4]\nobjects = ["0x7777"]',
     "bus.eds", "TPDO4 maps 0x7777:0, which the file does not define"),
])
def test_a_bad_canopen_key_is_one_line(tmp_path: Path, bus: str, key: str, wrong: str) -> None:
    rig = _rig_text(tmp_path, bus,
                    'inputs = [{ signal = "0x60FF" }]\noutputs = [{ signal = "0x606C" }]')
    line = rig_refusal(rig)
    assert line.startswith(f"rig file {rig}: {key}: "), line
    assert wrong in line


def test_an_unmapped_object_says_what_is_mapped(tmp_path: Path) -> None:
    rig = _rig_text(tmp_path, f'eds = "{EDS / "cia402_slave.eds"}"\nnodes = [1]',
                    'inputs = [{ signal = "0x60FF" }]\noutputs = [{ signal = "0x606C" }]')
    with pytest.raises(RigError, match=r"signals\.inputs\[0\]\.signal: no enabled PDO maps "
                                       r"0x60FF \(mapped: 0x6040 Controlword 1"):
        load_rig(rig)


def _twin_frames() -> tuple[list[can.Message], Cia402ECU]:
    rig = load_rig(EXAMPLE)
    ecu = Cia402ECU(None, _codec(rig), rig, 1, scenario_from_dict(SCENARIO), seed=3)
    return list(ecu.frames(start_time=1000.0)), ecu


def test_the_twin_speaks_cia402() -> None:
    frames, ecu = _twin_frames()
    assert (frames[0].arbitration_id, bytes(frames[0].data)) == (0x701, b"\x00")  # boot-up
    assert (frames[1].arbitration_id, bytes(frames[1].data)) == (0x000, b"\x01\x01")
    emcy = [(round(m.timestamp - 1000.0, 2), bytes(m.data)) for m in frames
            if m.arbitration_id == 0x81]
    assert emcy == [(3.5, bytes([0x00, 0x50, 0x01, 0, 0, 0, 0, 0])), (4.5, bytes(8))]
    status = {round(m.timestamp - 1000.0, 2): int.from_bytes(m.data[:2], "little")
              for m in frames if m.arbitration_id == 0x481}
    assert status[3.49] == STATUS_OPERATION_ENABLED and status[3.5] == STATUS_FAULT
    assert status[4.5] == STATUS_OPERATION_ENABLED
    beats = [m.timestamp for m in frames if m.arbitration_id == 0x701 and m.data[0] == 5]
    assert len(beats) == 60  # 100 ms: the file's 0x1017 is 0
    # synchronous TPDOs follow the SYNC they answer
    ids = [m.arbitration_id for m in frames[:20]]
    assert ids.index(0x080) < ids.index(0x481) and ids.index(0x501) < ids.index(0x080)
    assert ecu.stats.produced["TPDO4"] == ecu.stats.produced["sync"] == 600


class _BusEvents(Sink):
    def __init__(self) -> None:
        self.bus: list[BusEvent] = []
        self.transitions: list[DiagnosisEvent] = []

    def on_bus_event(self, event: BusEvent) -> None:
        self.bus.append(event)

    def on_transition(self, event: DiagnosisEvent) -> None:
        self.transitions.append(event)


def _both_engines(rig: Rig, frames: list[can.Message], path: Path, chunk: int
                  ) -> tuple[ReplayResult, _BusEvents]:
    """Both engines over `frames` (written to `path`): the same counters, transitions and
    bus events; the columnar engine's result and bus events."""
    with can.Logger(str(path)) as lg:
        for m in frames:
            lg.on_message_received(m)
    cfg = monitor_config(NO_OVERRIDES, rig)
    per_frame = _BusEvents()
    pipe = MonitorPipeline(build_decoder(rig), cfg, sink=per_frame)
    n = feed_log(pipe, read_log(path))
    columnar = _BusEvents()
    res = replay_file(path, build_decoder(rig), cfg, columnar, chunk_frames=chunk)
    assert res.frames == n and res.columnar
    assert res.counters == dict(pipe.counters)
    assert res.events == per_frame.transitions
    assert columnar.bus == per_frame.bus
    return res, columnar


def test_frames_of_another_node_are_unknown_not_protocol(tmp_path: Path) -> None:
    """The rig's drive is node 1: node 5's TPDO, node 5's heartbeat and an extended frame
    are no traffic of this rig's protocol (a wrong node ID in the rig shows as unknown_id),
    while node 1's SDO reply is; both engines count them alike (`_both_engines`)."""
    frames, _ = _twin_frames()
    t = frames[-1].timestamp
    foreign = [can.Message(timestamp=t + 0.001 * k, arbitration_id=i, is_extended_id=x,
                           data=bytes(8)) for k, (i, x) in
               enumerate([(0x185, False), (0x705, False), (0x181, True), (0x581, False)])]
    plain, _ = _both_engines(load_rig(EXAMPLE), frames, tmp_path / "plain.log", 997)
    res, _ = _both_engines(load_rig(EXAMPLE), frames + foreign, tmp_path / "more.log", 997)
    assert res.counters["rejected/unknown_id"] == 3
    assert res.counters["ignored/canopen"] == plain.counters["ignored/canopen"] + 1


@pytest.mark.parametrize("chunk", [61, 997, 262_144])
def test_both_engines_diagnose_the_twin_alike(tmp_path: Path, chunk: int) -> None:
    frames, _ = _twin_frames()
    res, columnar = _both_engines(load_rig(EXAMPLE), frames, tmp_path / "cia402.log", chunk)
    states = [(e.state, e.cause, round(e.t - 1000.0, 2)) for e in res.events
              if e.kind == "health"]
    # the 40 % loss is the estimator's to find; the outage the drive reports itself (Fault,
    # EMCY): its frames are not read (the node falls silent) until it is operational again,
    # and the estimate starts afresh then
    assert [(s, c) for s, c, _ in states] == [
        ("fault_free", "estimate"), ("fault", "estimate"), ("no_data", "silence"),
        ("fault_free", "estimate")], states
    assert 2.0 <= states[1][2] <= 2.3 and states[2][2] == 4.0, states
    assert 4.5 <= states[3][2] <= 4.6, states
    # TPDO4 and RPDO4 of 3.5-4.5 s, and the RPDO4 at 4.5 s: the host's command goes out
    # before the SYNC whose TPDO1 says Operation enabled again
    assert res.counters["ignored/drive_not_operational"] == 201
    assert res.counters["estimator/restarts"] == 1
    assert res.counters["samples/estimated"] == 500
    # NMT, SYNC, heartbeat, EMCY and the PDOs the rig does not read are the protocol's own
    # traffic, not frames the monitor does not know
    assert res.counters["ignored/canopen"] > 0
    assert "rejected/unknown_id" not in res.counters
    # what the drive said, the same in both: in the bus events and the counters
    said = [(round(e.t - 1000.0, 2), e.level, e.text) for e in columnar.bus]
    assert said == [(t, level, f"node 1: {text}") for t, _, level, text in TWIN_REPORTS]
    assert {k: v for k, v in res.counters.items() if k.startswith("drive/")} == {
        "drive/nmt": 2, "drive/cia402": 3, "drive/emcy": 2}


def test_the_canopen_librarys_master_reads_the_twin() -> None:
    """The library's `Network` on python-can's virtual bus, as a master: it hears the boot-up
    and the heartbeat, reads TPDO4 (statusword and velocity) and the EMCY of the outage."""
    channel = f"cia402-{id(object())}"
    rig = load_rig(EXAMPLE)
    scenario = scenario_from_dict({"name": "outage", "duration": 1.5,
                                   "fault": [{"start": 0.8, "end": 1.5, "gamma": 1.0}]})
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel, receive_own_messages=False)
    try:
        node = canopen.RemoteNode(1, str(EDS / "cia402_slave.eds"))
        network.add_node(node)
        node.tpdo.read(from_od=True)
        tpdo = node.tpdo[4]
        tpdo.enabled = True
        tpdo.subscribe()
        seen: list[tuple[int, float]] = []
        tpdo.add_callback(lambda m: seen.append((m["Statusword 1"].raw,
                                                 m["Velocity Actual Value 1"].raw)))
        beats: list[int] = []
        node.nmt.add_heartbeat_callback(beats.append)
        bus = can.Bus(interface="virtual", channel=channel)
        ecu = Cia402ECU(bus, _codec(rig), rig, 1, scenario, seed=1)
        worker = threading.Thread(target=ecu.run)
        worker.start()
        worker.join(30.0)
        bus.shutdown()
    finally:
        network.disconnect()
    assert beats[0] == 0 and set(beats[1:]) == {5} and len(beats) >= 10  # boot-up, 100 ms
    assert node.nmt.state == "OPERATIONAL"
    assert [e.code for e in node.emcy.log] == [EMCY_OUTAGE]
    emcy = node.emcy.log[0]
    assert emcy.register == 0x01
    assert emcy.get_desc() == "Device Hardware"
    statuses = [s for s, _ in seen]
    assert statuses[0] == STATUS_OPERATION_ENABLED and statuses[-1] == STATUS_FAULT
    assert len(seen) >= 100
    assert all(v != 0 for _, v in seen)


def test_the_drive_watch_reads_what_the_twin_says() -> None:
    """EMCY, heartbeat and statusword of the twin's run, named and timed, and the rule that
    a drive in Fault, with an active EMCY or a lost heartbeat is not driving its motor."""
    frames, ecu = _twin_frames()
    drive = replace(ecu.drive, heartbeat_ms=100)  # the file says 0; the twin beats at 100 ms
    watch = DriveWatch([drive])
    reports: list[DriveReport] = []
    operational: dict[float, bool] = {}
    for m in frames:
        reports += watch.feed(m.arbitration_id, bytes(m.data), m.timestamp)
        operational[round(m.timestamp - 1000.0, 2)] = watch.operational(1)
    got = [(round(r.t - 1000.0, 2), r.kind, r.text) for r in reports]
    assert got == [(t, kind, text) for t, kind, _, text in TWIN_REPORTS]
    assert operational[3.49] and not operational[3.5] and not operational[4.49]
    assert operational[4.5] and operational[5.99]
    assert watch.counts(1) == {"nmt": 2, "cia402": 3, "emcy": 2}
    # the drive falls silent: its heartbeat is lost after 1.5 periods, once
    last = max(m.timestamp for m in frames if m.arbitration_id == 0x701)
    assert watch.tick(last + 0.14) == []
    lost = watch.tick(last + 0.16)
    assert [r.kind for r in lost] == ["heartbeat_lost"] and not watch.operational(1)
    assert watch.tick(last + 1.0) == []


@pytest.mark.parametrize(("word", "state"), [
    (0x0027, "OPERATION ENABLED"), (0x0637, "OPERATION ENABLED"), (0x0008, "FAULT"),
    (0x0007, "QUICK STOP ACTIVE"), (0x0040, "SWITCH ON DISABLED"), (0x0021, "READY TO SWITCH ON"),
    (0x0023, "SWITCHED ON"), (0x000F, "FAULT REACTION ACTIVE"), (0x0000, "NOT READY TO SWITCH ON"),
])
def test_statusword_states(word: int, state: str) -> None:
    assert cia402_state(word) == state


def test_emcy_names() -> None:
    assert emcy_name(0x8130) == "life guard or heartbeat error"
    assert emcy_name(0x2311) == "current"  # its class (CiA 301), from the library
    assert emcy_name(0xFF42) == "device specific"


def test_a_drive_whose_heartbeat_stops_is_not_read(tmp_path: Path) -> None:
    """The drive's heartbeat (100 ms here) stops for 1 s while its PDOs go on: both engines
    stop reading it after 150 ms without one, and read it afresh at the next heartbeat."""
    rig = _beating_rig(tmp_path)
    healthy = scenario_from_dict({"name": "healthy", "duration": 4.0})
    ecu = Cia402ECU(None, _codec(rig), rig, 1, healthy, seed=2)
    frames = [m for m in ecu.frames(start_time=1000.0)
              if not (m.arbitration_id == 0x701 and 1.0 < m.timestamp - 1000.0 < 2.05)]
    res, columnar = _both_engines(rig, frames, tmp_path / "silent.log", 997)
    said = [(round(e.t - 1000.0, 2), e.text) for e in columnar.bus]
    assert said[3:] == [(1.16, "node 1: heartbeat lost (none for 0.160 s)"),
                        (2.1, "node 1: NMT OPERATIONAL")], said
    # not read from the first frame after the loss (1.16 s) to the heartbeat at 2.1 s
    assert res.counters["ignored/drive_not_operational"] == 2 * 94
    assert res.counters["estimator/restarts"] == 1
    assert [e.state for e in res.events if e.kind == "health"] == [
        "fault_free", "no_data", "fault_free"]


def _beating_rig(tmp_path: Path) -> Rig:
    """The example rig with a drive that beats every 100 ms (its file says 0: none)."""
    eds = (EDS / "cia402_slave.eds").read_text()
    start = eds.index("[1017]")
    eds = eds[:start] + eds[start:].replace("DefaultValue=0x0", "DefaultValue=100", 1)
    (tmp_path / "cia402-example.eds").write_text(eds)
    (tmp_path / "rig.toml").write_text(EXAMPLE.read_text())
    return load_rig(tmp_path / "rig.toml")


def test_a_heartbeat_lost_while_only_pdos_go_on_is_found_at_a_tick(tmp_path: Path) -> None:
    """From 1 s to 2.05 s the bus carries only the rig's PDOs (no SYNC, no heartbeat, nothing
    the drive watch reads): both engines find the loss at a tick, 150 ms after the last
    heartbeat, not at the next protocol frame a second later."""
    rig = _beating_rig(tmp_path)
    healthy = scenario_from_dict({"name": "healthy", "duration": 4.0})
    ecu = Cia402ECU(None, _codec(rig), rig, 1, healthy, seed=2)
    pdos = {0x481, 0x501}  # TPDO4 and RPDO4 of node 1
    frames = [m for m in ecu.frames(start_time=1000.0)
              if m.arbitration_id in pdos or not 1.0 < m.timestamp - 1000.0 < 2.05]
    res, columnar = _both_engines(rig, frames, tmp_path / "pdos-only.log", 997)
    lost = [e for e in columnar.bus if "heartbeat lost" in e.text]
    assert len(lost) == 1 and 1.15 < lost[0].t - 1000.0 <= 1.21, columnar.bus
    assert res.counters["drive/heartbeat_lost"] == 1


def test_a_heartbeat_lost_on_a_silent_bus_is_said_at_the_live_tick(tmp_path: Path) -> None:
    """The live loop ticks in wall time when no frame comes: a drive gone silent with the
    whole bus is reported once its heartbeat is overdue, without another frame."""
    rig = _beating_rig(tmp_path)
    healthy = scenario_from_dict({"name": "healthy", "duration": 1.0})
    ecu = Cia402ECU(None, _codec(rig), rig, 1, healthy, seed=2)
    sink = _BusEvents()
    pipe = MonitorPipeline(build_decoder(rig), monitor_config(NO_OVERRIDES, rig), sink=sink)
    last = 0.0
    for m in ecu.frames(start_time=1000.0):
        pipe.feed(m)
        last = m.timestamp
    before = len(sink.bus)
    for k in range(1, 11):  # the loop's ticks every 50 ms of wall time, no frame between
        pipe.tick(last + 0.05 * k)
    said = [e.text for e in sink.bus[before:]]
    assert len(said) == 1 and said[0].startswith("node 1: heartbeat lost"), said
    assert pipe.counters["drive/heartbeat_lost"] == 1


def test_a_dbc_for_a_canopen_rig_is_one_line(tmp_path: Path) -> None:
    """--dbc would replace the bus description the EDS gives: refused, not ignored."""
    case = CliCase("dbc_canopen", "--dbc with a CANopen rig", (
        "motor-monitor", "replay", str(tmp_path / "none.log"), "--rig", str(EXAMPLE),
        "--dbc", str(REPO_DBC)), "is a CANopen rig")
    outcome = run_cli_case(case, tmp_path, timeout=60)
    assert outcome.clean, (outcome.returncode, outcome.lines)


def test_identify_reads_a_drive_as_the_monitor_does(tmp_path: Path) -> None:
    """identify's capture of the twin with a drive Fault: the protocol's frames counted as
    the protocol's (not unknown IDs), and the frames of the Fault left out of the plant's
    samples, as many as the monitor leaves out of the same log."""
    frames, _ = _twin_frames()
    log = tmp_path / "twin.log"
    with can.Logger(str(log)) as lg:
        for m in frames:
            lg.on_message_received(m)
    rig = load_rig(EXAMPLE)
    _, counts = collect(argparse.Namespace(rig=str(EXAMPLE), dbc=None, key=None), rig, [log])
    pipe = MonitorPipeline(build_decoder(rig), monitor_config(NO_OVERRIDES, rig))
    feed_log(pipe, read_log(log))
    assert "rejected/unknown_id" not in counts
    for key in ("ignored/canopen", "ignored/drive_not_operational"):
        assert counts[key] == pipe.counters[key] > 0, key


def test_the_events_carry_what_the_drive_says(tmp_path: Path) -> None:
    """`replay --events` of the twin: the drive's reports are lines of kind drive between the
    health transitions (an EMCY explains the node's silence), the same in both engines, and
    the file is still recognised as the monitor's own (so `run --events` appends to it)."""
    frames, _ = _twin_frames()
    log = tmp_path / "cia402.log"
    with can.Logger(str(log)) as lg:
        for m in frames:
            lg.on_message_received(m)
    lines = {}
    for engine in ("columnar", "per-frame"):
        ev = tmp_path / f"{engine}.jsonl"
        done = motor_monitor("replay", str(log), "--rig", str(EXAMPLE), "--engine", engine,
                             "--events", str(ev))
        assert done.returncode == 0, done.stderr
        lines[engine] = [json.loads(x) for x in ev.read_text().splitlines()]
        assert is_own_file(ev, "events")
        # the summary lists the node's silence during the drive's Fault, from the log's start
        silent = [e["t"] - 1000.0 for e in lines[engine]
                  if e["kind"] == "health" and e["state"] == "no_data"]
        stretches = [x for x in done.stderr.splitlines() if x.startswith("  no_data")]
        assert len(stretches) == len(silent) >= 1, done.stderr
        assert f"{silent[0]:9.2f} s ->" in stretches[0], done.stderr
    assert lines["columnar"] == lines["per-frame"]
    kinds = [(e["kind"], e.get("report") or e["state"]) for e in lines["columnar"]]
    emcy = kinds.index(("drive", "emcy"))
    assert ("health", "no_data") in kinds[emcy:]  # the drive said so before the node fell silent
    said = [e for e in lines["columnar"] if e["kind"] == "drive"]
    assert {e["report"] for e in said} >= {"emcy", "nmt", "cia402"}
    assert said[[e["report"] for e in said].index("emcy")]["value"] == EMCY_OUTAGE
