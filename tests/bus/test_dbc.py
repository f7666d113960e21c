"""The bus description itself: dbc/motor.dbc as cantools and its command line see it."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import cantools
import pytest
from cantools.database.can import Database

from monitor.bus.codec import HEALTH_STATES, KINDS, N_NODES, e2e_data_id, load_database
from tests.support.dbc import REPO_DBC
from tests.support.paths import ROOT

PACKAGE_DBC = ROOT / "monitor" / "bus" / "motor.dbc"

LAYOUT = {  # kind: (message prefix, base id, sender, cycle time ms, E2E protected)
    "current": ("MotorCurrent", 0x110, "MotorECU", 10, True),
    "voltage": ("MotorVoltage", 0x120, "MotorECU", 50, True),
    "truth": ("SimTruth", 0x7E0, "MotorECU", 10, False),
    "diagnosis": ("MonitorDiagnosis", 0x180, "Monitor", 100, True),
    "sync": ("SecOCSync", 0x1F0, "MotorECU", 1000, False),
}


def _cantools_cli() -> list[str]:
    """The `cantools` console script installed next to the running interpreter."""
    script = Path(sys.executable).with_name("cantools")
    return [str(script)] if script.exists() else [sys.executable, "-m", "cantools"]


@pytest.fixture(scope="module")
def db() -> Database:
    loaded = cantools.database.load_file(REPO_DBC, database_format="dbc", strict=True)
    assert isinstance(loaded, Database)
    return loaded


def test_package_copy_is_byte_identical() -> None:
    # dbc/motor.dbc is the source of truth; the wheel ships monitor/bus/motor.dbc.
    assert PACKAGE_DBC.read_bytes() == REPO_DBC.read_bytes()


def test_one_message_per_kind_and_node(db: Database) -> None:
    assert len(db.messages) == len(LAYOUT) * N_NODES
    assert sorted(LAYOUT) == sorted(KINDS)
    assert {n.name for n in db.nodes} == {"MotorECU", "Monitor"}
    for prefix, base, sender, cycle, _e2e in LAYOUT.values():
        for node in range(N_NODES):
            msg = db.get_message_by_name(f"{prefix}_N{node}")
            assert msg.frame_id == base + node
            assert msg.frame_id & 0xF == node
            assert not msg.is_extended_frame
            assert msg.length == 8
            assert msg.senders == [sender]
            assert msg.cycle_time == cycle
            assert msg.dbc is not None
            assert msg.dbc.attributes["NodeNumber"].value == node
            assert msg.comment and f"node {node}" in msg.comment


def test_signals_little_endian_commented_and_bounded(db: Database) -> None:
    for msg in db.messages:
        for sig in msg.signals:
            assert sig.byte_order == "little_endian", (msg.name, sig.name)
            assert sig.comment, (msg.name, sig.name)
            assert sig.minimum is not None and sig.maximum is not None


def test_e2e_layout_and_data_ids(db: Database) -> None:
    data_ids: list[int] = []
    for prefix, base, _sender, _cycle, e2e in LAYOUT.values():
        for node in range(N_NODES):
            msg = db.get_message_by_name(f"{prefix}_N{node}")
            assert msg.dbc is not None
            if not e2e:
                assert "E2EDataID" not in msg.dbc.attributes
                assert "CRC" not in [s.name for s in msg.signals]
                continue
            crc = msg.get_signal_by_name("CRC")
            counter = msg.get_signal_by_name("Counter")
            assert (crc.start, crc.length, crc.is_signed) == (0, 8, False)
            assert (counter.start, counter.length, counter.is_signed) == (8, 4, False)
            data_id = int(msg.dbc.attributes["E2EDataID"].value)
            assert data_id == e2e_data_id(base + node) == (base + node) & 0xFF
            assert f"0x{data_id:02X}" in (msg.comment or "")
            data_ids.append(data_id)
    assert len(set(data_ids)) == len(data_ids) == 3 * N_NODES  # masquerade -> CRC fails


def test_signal_ranges(db: Database) -> None:
    cur = db.get_message_by_name("MotorCurrent_N0").get_signal_by_name("ArmatureCurrent")
    assert (cur.scale, cur.minimum, cur.maximum, cur.unit) == (0.01, -300, 300, "A")
    assert cur.is_signed
    volt = db.get_message_by_name("MotorVoltage_N0").get_signal_by_name("VoltageCommand")
    assert (volt.scale, volt.minimum, volt.maximum, volt.unit) == (0.01, -400, 400, "V")
    truth = db.get_message_by_name("SimTruth_N0")
    assert truth.get_signal_by_name("TrueGamma").minimum == 0
    assert truth.get_signal_by_name("TrueGamma").maximum == 1
    assert truth.get_signal_by_name("TrueSpeed").unit == "rad/s"
    diag = db.get_message_by_name("MonitorDiagnosis_N0")
    state = diag.get_signal_by_name("HealthState")
    assert state.choices is not None
    assert {int(k): str(v) for k, v in state.choices.items()} == dict(enumerate(HEALTH_STATES))
    assert (state.start, state.length, state.maximum) == (12, 4, 3)
    assert diag.get_signal_by_name("RuleCount").maximum == 255
    # the model-mismatch flag: one bit of the byte no other signal used, so receivers of
    # the older layout decode every signal where it was
    layout = {s.name: (s.start, s.length) for s in diag.signals}
    assert layout == {"CRC": (0, 8), "Counter": (8, 4), "HealthState": (12, 4),
                      "GammaEstimate": (16, 16), "FaultEstimate": (32, 16),
                      "RuleCount": (48, 8), "ModelMismatch": (56, 1)}
    flag = diag.get_signal_by_name("ModelMismatch")
    assert (flag.minimum, flag.maximum, flag.is_signed) == (0, 1, False)


def test_cantools_dump_runs() -> None:
    proc = subprocess.run([*_cantools_cli(), "dump", str(REPO_DBC)],
                          capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    assert "MotorCurrent_N15" in proc.stdout
    assert "MonitorDiagnosis_N0" in proc.stdout


def test_cantools_decode_reads_our_frames() -> None:
    mdb = load_database(REPO_DBC)
    frames = [
        (mdb.frame_id("current", 1), mdb.encode_current(1, 12.34, 5)),
        (mdb.frame_id("voltage", 15), mdb.encode_voltage(15, -230.5, 15)),
        (mdb.frame_id("truth", 3), mdb.encode_truth(3, 0.25, -3.2, 615.5)),
        (mdb.frame_id("diagnosis", 0), mdb.encode_diagnosis(0, "outage", 0.987, -400.0, 12, 0)),
    ]
    log = "".join(
        f"(1700000000.{i:06d}) vcan0 {fid:03X}#{data.hex().upper()}\n"
        for i, (fid, data) in enumerate(frames)
    )
    proc = subprocess.run([*_cantools_cli(), "decode", "--single-line", str(REPO_DBC)],
                          input=log, capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert len(lines) == len(frames)

    def signals(line: str) -> tuple[str, dict[str, str]]:
        m = re.search(r":: (\w+)\((.*)\)$", line)
        assert m, line
        return m[1], dict(kv.split(": ", 1) for kv in m[2].split(", "))

    name, sig = signals(lines[0])
    assert name == "MotorCurrent_N1"
    assert sig["ArmatureCurrent"] == "12.34 A" and sig["Counter"] == "5"
    assert int(sig["CRC"]) == frames[0][1][0]
    name, sig = signals(lines[1])
    assert name == "MotorVoltage_N15"
    assert sig["VoltageCommand"] == "-230.5 V" and sig["Counter"] == "15"
    name, sig = signals(lines[2])
    assert name == "SimTruth_N3"
    assert sig == {"TrueGamma": "0.25", "TrueCurrent": "-3.2 A", "TrueSpeed": "615.5 rad/s"}
    name, sig = signals(lines[3])
    assert name == "MonitorDiagnosis_N0"
    assert sig["HealthState"] == "outage"
    assert sig["GammaEstimate"] == "0.987"
    assert sig["FaultEstimate"] == "-400.0 V"
    assert sig["RuleCount"] == "12" and sig["Counter"] == "0"


SECOC_LAYOUT = {  # kind: ((FreshnessValue start, length), (Authenticator start, length))
    "current": ((32, 8), (40, 24)),
    "voltage": ((12, 4), (40, 24)),
}


def test_secoc_signals_and_attributes(db: Database) -> None:
    for kind, (prefix, base, _sender, _cycle, _e2e) in LAYOUT.items():
        for node in range(N_NODES):
            msg = db.get_message_by_name(f"{prefix}_N{node}")
            assert msg.dbc is not None
            names = {s.name for s in msg.signals}
            if kind not in SECOC_LAYOUT:
                assert not names & {"FreshnessValue", "Authenticator"}
                if kind != "sync":  # the sync frame has its own MAC (test below)
                    assert "SecOCDataID" not in msg.dbc.attributes
                continue
            (fv_start, fv_len), (auth_start, auth_len) = SECOC_LAYOUT[kind]
            fv = msg.get_signal_by_name("FreshnessValue")
            auth = msg.get_signal_by_name("Authenticator")
            assert (fv.start, fv.length, fv.is_signed) == (fv_start, fv_len, False)
            assert (auth.start, auth.length, auth.is_signed) == (auth_start, auth_len, False)
            assert (fv.minimum, fv.maximum) == (0, (1 << fv_len) - 1)
            assert (auth.minimum, auth.maximum) == (0, (1 << auth_len) - 1)
            assert msg.dbc.attributes["SecOCDataID"].value == base + node
            assert msg.dbc.attributes["SecOCFreshnessValueLength"].value == 64
            assert "SecOC" in (msg.comment or "")
            assert "AES-CMAC" in (auth.comment or "")
            assert "CRC" in (auth.comment or "")  # the E2E CRC comes after and covers it


def test_secoc_uses_the_spare_bits_only(db: Database) -> None:
    # Without SecOC the new signals are 0, so an unsigned frame is the old frame: the old
    # signals keep their bits; MotorCurrent keeps 4 reserved bits (12..15), MotorVoltage
    # none.
    for kind, expected_free in (("current", set(range(12, 16))), ("voltage", set())):
        prefix = LAYOUT[kind][0]
        msg = db.get_message_by_name(f"{prefix}_N0")
        used: set[int] = set()
        for sig in msg.signals:
            bits = set(range(sig.start, sig.start + sig.length))
            assert not used & bits, sig.name
            used |= bits
        assert set(range(64)) - used == expected_free
    old = {("current", "ArmatureCurrent"): (16, 16), ("voltage", "VoltageCommand"): (16, 24)}
    for (kind, name), (start, length) in old.items():
        sig = db.get_message_by_name(f"{LAYOUT[kind][0]}_N0").get_signal_by_name(name)
        assert (sig.start, sig.length) == (start, length)


def test_sync_frames_layout(db: Database) -> None:
    # SyncKind 0-3 | reserved 4-7 | SyncFreshness 8-39 | SyncAuthenticator 40-63; no E2E.
    ids = {m.frame_id for m in db.messages}
    sync_ids = set(range(0x1F0, 0x200))
    assert sync_ids <= ids
    assert not sync_ids & {m.frame_id for m in db.messages
                           if not m.name.startswith("SecOCSync_")}  # collides with nothing
    for node in range(N_NODES):
        msg = db.get_message_by_name(f"SecOCSync_N{node}")
        assert msg.dbc is not None
        layout = {s.name: (s.start, s.length, s.is_signed) for s in msg.signals}
        assert layout == {"SyncKind": (0, 4, False), "SyncFreshness": (8, 32, False),
                          "SyncAuthenticator": (40, 24, False)}
        kind = msg.get_signal_by_name("SyncKind")
        assert (kind.minimum, kind.maximum) == (0, 1)
        assert kind.choices is not None
        assert {int(k): str(v) for k, v in kind.choices.items()} == {0: "current", 1: "voltage"}
        assert msg.get_signal_by_name("SyncFreshness").maximum == 2**32 - 1
        assert msg.dbc.attributes["SecOCDataID"].value == 0x1F0 + node
        assert msg.dbc.attributes["SecOCFreshnessValueLength"].value == 64
        assert "E2EDataID" not in msg.dbc.attributes
        assert "AES-CMAC" in (msg.get_signal_by_name("SyncAuthenticator").comment or "")
        assert "497 days" in (msg.get_signal_by_name("SyncFreshness").comment or "")


def test_cantools_decode_reads_a_sync_frame() -> None:
    tx = load_database(REPO_DBC, secoc_key=bytes(range(16)))
    for _ in range(300):
        tx.encode_voltage(5, 1.0, 0)
    data = tx.encode_sync(5, "voltage")
    log = f"(1700000000.000000) vcan0 1F5#{data.hex().upper()}\n"
    proc = subprocess.run([*_cantools_cli(), "decode", "--single-line", str(REPO_DBC)],
                          input=log, capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    assert "SecOCSync_N5(SyncKind: voltage, SyncFreshness: 300, SyncAuthenticator: " \
        in proc.stdout, proc.stdout
