"""A CANopen CiA 402 rig end to end on real vcan: `sim-ecu --rig rigs/cia402-example.toml`
(the CiA 402 twin: boot-up, heartbeat, SYNC, RPDOs and TPDOs, EMCY on an outage) and
`motor-monitor run --rig` as separate processes, with the `canopen` library's own `Network`
as an independent master in a third: it must hear the drive boot and beat, read its TPDO4
(statusword, velocity) and its EMCYs as a master would. candump records the bus; the live
events must follow the scenario and equal the capture replayed through the same rig."""

from __future__ import annotations

import itertools
import json
import re
from pathlib import Path

import pytest

from monitor.pipeline.feed import TICK_S
from monitor.rig import load_rig
from tests.support import motor_monitor
from tests.support.paths import ROOT
from tests.support.vcan_scripts import RunOnVcan, logs_tail, run_ready

RIG = ROOT / "rigs" / "cia402-example.toml"
EDS = ROOT / "rigs" / "cia402-example.eds"

SCENARIO = """name = "cia402-vcan"
duration = 8.0
[[fault]]
start = 2.0
end = 4.0
gamma = 0.4
[[fault]]
start = 4.0
end = 6.0
gamma = 1.0
"""
SILENCE_S = load_rig(RIG).diagnosis.silence_timeout_s
TICK_SLACK_S = 2 * TICK_S  # a silence is told at one of the daemon's next ticks


@pytest.mark.vcan
def test_cia402_twin_monitor_and_a_canopen_master_on_vcan(vcan: RunOnVcan,
                                                         tmp_path: Path) -> None:
    (tmp_path / "scenario.toml").write_text(SCENARIO)
    values = run_ready(vcan, "canopen.sh", tmp_path, env={"RIG": str(RIG), "EDS": str(EDS)},
                       timeout=300.0)
    for key in ("ecu_rc", "master_rc", "mon_rc"):
        assert values.get(key) == "0", f"{key}\n{values}\n{logs_tail(tmp_path)}"
    ecu_err = (tmp_path / "ecu.err").read_text()
    sent = {k: int(v) for k, v in re.findall(r"\b(TPDO4|RPDO4|sync|emcy)=(\d+)", ecu_err)}
    assert sent["TPDO4"] == sent["sync"] == 800 and sent["emcy"] == 2, ecu_err

    # The master heard the drive as a drive: boot-up, heartbeats, every TPDO4, the EMCYs.
    master = json.loads((tmp_path / "master.json").read_text())
    assert master["beats"][0] == 0 and set(master["beats"][1:]) == {5}, master["beats"][:5]
    assert master["state"] == "OPERATIONAL"
    assert master["emcy"] == [[0x5000, 1, "Device Hardware"], [0, 0, "Error Reset / No Error"]]
    statuses = [s for s, _ in master["pdos"]]
    assert len(statuses) >= 0.98 * sent["TPDO4"], len(statuses)
    assert statuses.count(0x0008) >= 190 and statuses[0] == statuses[-1] == 0x0027

    # The monitor diagnosed the drive live: the 40 % loss from 2 s by its estimate; the
    # outage of 4-6 s the drive reports itself (Fault, EMCY), so its frames are not read
    # then (the node falls silent) and its estimate starts afresh once it is operational.
    events = [json.loads(x) for x in (tmp_path / "ev.jsonl").read_text().splitlines()]
    live = [e for e in events if e["kind"] == "health"]
    # Sample k is the k-th TPDO4 of the capture (kernel time, as the monitor's): on a busy
    # one-CPU guest the twin sends late, so the changes are timed from their samples (200:
    # the loss, 400: the outage, 600: operational again).
    tpdo4 = [float(t) for t in re.findall(r"^\((\d+\.\d+)\) vcan0 481#",
                                          (tmp_path / "cap.log").read_text(), re.MULTILINE)]
    assert len(tpdo4) == sent["TPDO4"]
    # A twin starved for the silence timeout (a stall of the busy guest, seen in the
    # capture as a gap between two TPDO4s outside the outage) is a silent node, rightly
    # reported: such a silence, timed inside its gap, is taken out with the repeat of the
    # state it interrupted; any other silence is the monitor's own.
    stalls = [(tpdo4[i - 1], tpdo4[i]) for i in range(1, len(tpdo4))
              if tpdo4[i] - tpdo4[i - 1] >= SILENCE_S and not 400 <= i <= 600]
    states: list[tuple[str, str, float]] = []
    for e in live:
        if e["state"] == "no_data" and any(a + SILENCE_S <= e["t"] <= b + TICK_SLACK_S
                                           for a, b in stalls):
            continue
        if not states or states[-1][0] != e["state"]:
            states.append((e["state"], e["cause"], round(e["t"], 6)))
    gap = max(b - a for a, b in itertools.pairwise(tpdo4))
    assert [(s, c) for s, c, _ in states] == [
        ("fault_free", "estimate"), ("fault", "estimate"), ("no_data", "silence"),
        ("fault_free", "estimate"), ("no_data", "silence")], (states, stalls, gap)
    assert 0.0 <= states[1][2] - tpdo4[200] <= 0.5, (states, tpdo4[200])
    assert 0.5 <= states[2][2] - tpdo4[399] <= 1.0, (states, tpdo4[399])
    assert 0.0 <= states[3][2] - tpdo4[600] <= 0.5, (states, tpdo4[600])

    # ... and replaying the capture through the same rig gives the same transitions (but
    # the last: the live run's clock after the bus fell silent).
    rep = motor_monitor("replay", str(tmp_path / "cap.log"), "--rig", str(RIG), "--nodes", "1")
    assert rep.returncode == 0, rep.stderr
    again = [e for e in map(json.loads, rep.stdout.splitlines()) if e["kind"] == "health"]
    assert [(e["state"], e["previous"], e["cause"]) for e in again] == [
        (e["state"], e["previous"], e["cause"]) for e in live[:-1]]
