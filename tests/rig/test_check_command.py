"""`motor-monitor check`: the rig as the monitor reads it, held against captures written by
python-can's writers (the CiA 402 twin's frames, our bus's virtual ECUs), read back from
the command's output and exit status."""

from __future__ import annotations

import subprocess
from pathlib import Path

import can

from monitor.bus.rigcodec import RigCodec
from monitor.rig import build_decoder, load_rig
from monitor.rig.survey import cob_id_name
from sim_ecu.cia402 import Cia402ECU
from sim_ecu.scenario import scenario_from_dict
from tests.archive.logs import ecu_frames, write_log
from tests.support import BIN
from tests.support.paths import ROOT

EXAMPLE = ROOT / "rigs" / "cia402-example.toml"


def _check(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(BIN / "motor-monitor"), "check", *args], capture_output=True,
                          text=True, timeout=300, cwd=cwd)


def _twin_capture(path: Path, *, cut_tpdo: bool = False) -> Path:
    rig = load_rig(EXAMPLE)
    codec = build_decoder(rig)
    assert isinstance(codec, RigCodec)
    ecu = Cia402ECU(None, codec, rig, 1, scenario_from_dict({"name": "h", "duration": 2.0}),
                    seed=1)
    with can.Logger(str(path)) as log:
        for m in ecu.frames(start_time=1000.0):
            if cut_tpdo and m.arbitration_id == 0x481:  # TPDO4, the velocity: 2 bytes short
                m = can.Message(timestamp=m.timestamp, arbitration_id=m.arbitration_id,
                                is_extended_id=False, data=bytes(m.data)[:-2])
            log.on_message_received(m)
    return path


def test_the_twins_capture_matches_its_rig(tmp_path: Path) -> None:
    log = _twin_capture(tmp_path / "twin.log")
    done = _check(str(log), "--rig", str(EXAMPLE), cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    rows = {line.split()[0]: line for line in done.stdout.splitlines()
            if line.strip().startswith("0x")}
    assert "RPDO4 of node 1: read 200" in rows["0x501"]
    assert "TPDO4 of node 1: read 200" in rows["0x481"]
    assert "SYNC: ignored/canopen 200" in rows["0x80"] and " 100.0 " in rows["0x80"]
    assert "every message carrying the model's inputs and outputs is read" in done.stdout


def test_a_wrong_node_names_the_missing_messages_and_the_busy_ids(tmp_path: Path) -> None:
    log = _twin_capture(tmp_path / "twin.log")
    rig = tmp_path / "rig.toml"
    rig.write_text(EXAMPLE.read_text().replace("nodes = [1]", "nodes = [2]"))
    (tmp_path / EXAMPLE.with_suffix(".eds").name).write_bytes(
        EXAMPLE.with_suffix(".eds").read_bytes())
    done = _check(str(log), "--rig", str(rig), cwd=tmp_path)
    assert done.returncode == 1
    said = done.stderr.strip().splitlines()
    assert any("node 2's TPDO4 (ID 0x482" in x and "no frame with this ID" in x for x in said)
    assert any("node 2's RPDO4 (ID 0x502" in x for x in said)
    assert any("its busiest IDs: " in x and "of node 1, 200 frames, 100 Hz)" in x for x in said)


def test_frames_of_the_wrong_length_say_so(tmp_path: Path) -> None:
    log = _twin_capture(tmp_path / "cut.log", cut_tpdo=True)
    done = _check(str(log), "--rig", str(EXAMPLE), cwd=tmp_path)
    assert done.returncode == 1
    line = next(x for x in done.stderr.splitlines() if "TPDO4" in x)
    assert "200 frames, none read (200 rejected/wrong_length" in line, line
    assert "the rig expects" in line


def test_our_bus_without_a_rig_file(tmp_path: Path) -> None:
    log = write_log(tmp_path / "ours.log", ecu_frames(["healthy", "healthy"], duration=1.0))
    done = _check(str(log), cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "the built-in rig" in done.stdout
    read = [x.split(":")[0].split()[-4:] for x in done.stdout.splitlines() if ": read " in x]
    assert {(kind, node) for kind, _, _, node in read} >= {
        ("current", "0"), ("voltage", "0"), ("current", "1"), ("voltage", "1")}, read


def test_the_rig_alone_lists_what_is_read(tmp_path: Path) -> None:
    done = _check("--rig", str(EXAMPLE), cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert any(x.split()[:3] == ["1", "TPDO4", "0x481"] for x in done.stdout.splitlines()), \
        done.stdout


def test_cob_id_names() -> None:
    assert [cob_id_name(i) for i in (0x000, 0x080, 0x081, 0x383, 0x203, 0x703, 0x7E5)] == [
        "NMT", "SYNC", "EMCY of node 1", "TPDO3 of node 3", "RPDO1 of node 3",
        "heartbeat of node 3", "COB-ID 0x7E5"]
