"""A rig file is read whole, whatever bus it describes: our own bus goes through the same
checks as any other (units, protection, truth: the refusals are cases of mistakes.toml),
`MotorDatabase` serves only a rig that says exactly what it implements and the rig codec any
other; units parse, convert and suit the model; a DBC with two messages on one frame ID, or
two files that clash, is refused in one line."""

from __future__ import annotations

import argparse
import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from monitor.app.options import monitor_config
from monitor.bus.codec import CodecError, MotorDatabase, load_database, load_dbcs
from monitor.bus.rigcodec import RigCodec
from monitor.columnar.replay import replay_file
from monitor.rig import RigError, build_decoder, build_model, builtin_rig, load_rig
from tests.archive.logs import ecu_frames, write_log
from tests.support import motor_monitor
from tests.support.dbc import REPO_DBC
from tests.support.paths import ROOT, TEST_RIGS
from tests.support.pipeline import Recorder
from tests.support.rig_files import written_rig

MOTOR_TEXT = (ROOT / "rigs" / "motor.toml").read_text().replace('"../dbc/motor.dbc"',
                                                               f'"{REPO_DBC}"')
CURRENT_LINE = ('outputs = [{ message = "MotorCurrent", signal = "ArmatureCurrent", '
                'unit = "A" }]')
TRUTH_LINE = 'truth = { message = "SimTruth", signal = "TrueGamma" }'
CURRENT_E2E = ('MotorCurrent = { kind = "e2e_profile2", counter = "Counter", crc = "CRC", '
               'data_id = "id_low_byte" }')
TRUTH_CURRENT = MOTOR_TEXT.replace(CURRENT_E2E, "")  # the output below is not MotorCurrent
NO_OVERRIDES = argparse.Namespace(nodes=None, rate=None, thresholds=None)


def _matrix(a: np.ndarray) -> str:
    return "[" + ", ".join("[" + ", ".join(repr(float(v)) for v in row) + "]"
                           for row in np.atleast_2d(a)) + "]"


def _milliamp_rig(tmp_path: Path) -> Path:
    """Our bus as rigs/motor.toml describes it, but the model takes the current in mA: the
    paper's motor as matrices whose output row and sensor variance are in mA."""
    m = build_model(builtin_rig())
    head, tail = MOTOR_TEXT.replace('unit = "A"', 'unit = "mA"').split("[model]")
    model = (f'[model]\nkind = "state_space"\nrate = 100.0\nE = {_matrix(m.E)}\n'
             f"A = {_matrix(m.A)}\nB = {_matrix(m.B)}\nC = {_matrix(1000.0 * m.C)}\n"
             f"Q = {_matrix(m.Qc)}\nR = {_matrix(1e6 * m.R)}\n\n")
    return written_rig(tmp_path, head + model + tail[tail.index("[diagnosis]"):],
                       name="milliamp.toml")


# ----------------------------------------------------------------- which decoder reads it


def test_our_bus_in_milliamps_is_read_by_the_rig_codec_with_the_same_gamma(
        tmp_path: Path) -> None:
    """A capture of our bus replayed through the built-in rig (`MotorDatabase`) and
    through a rig that wants the current in mA (the rig codec): the same gamma^ and
    diagnosis, the current 1000 times larger."""
    capture = write_log(tmp_path / "cap.log", ecu_frames(["fault-outage-recovery"]))
    ours, mine = Recorder(), Recorder()
    db = build_decoder(builtin_rig())
    assert isinstance(db, MotorDatabase)
    a = replay_file(capture, db, monitor_config(NO_OVERRIDES, builtin_rig()), ours)
    rig = load_rig(_milliamp_rig(tmp_path))
    codec = build_decoder(rig)
    assert isinstance(codec, RigCodec)
    b = replay_file(capture, codec, monitor_config(NO_OVERRIDES, rig), mine)
    assert a.columnar and b.columnar
    assert len(ours.samples) == len(mine.samples) > 1000
    gamma_a = np.array([s.gamma for s in ours.samples])
    gamma_b = np.array([s.gamma for s in mine.samples])
    np.testing.assert_allclose(gamma_b, gamma_a, rtol=0, atol=1e-9)
    assert gamma_a.max() > 0.9  # the scenario's outage: gamma^ went somewhere
    np.testing.assert_allclose([s.measured for s in mine.samples],
                               [1000.0 * s.measured for s in ours.samples], rtol=1e-12)
    assert ([(e.t, e.state) for e in mine.transitions]
            == [(e.t, e.state) for e in ours.transitions])
    assert [e.state for e in ours.transitions] == ["fault_free", "fault", "outage", "fault",
                                                   "fault_free"]
    assert a.counters == b.counters


def test_the_builtin_rig_and_its_equivalents_are_our_bus(tmp_path: Path) -> None:
    assert isinstance(build_decoder(builtin_rig()), MotorDatabase)
    # the same units spelt otherwise, the default protection written out: the same rig
    same = (MOTOR_TEXT.replace('unit = "A"', 'unit = "ampere"')
            .replace("[protection]\n", '[protection]\nSimTruth = { kind = "none" }\n'))
    assert isinstance(build_decoder(load_rig(written_rig(tmp_path, same))), MotorDatabase)


@pytest.mark.parametrize(("what", "text", "differs"), [
    ("no truth", MOTOR_TEXT.replace(TRUTH_LINE, ""), "signals.truth"),
    ("the current unprotected", MOTOR_TEXT.replace(CURRENT_E2E, ""),
     "protection.MotorCurrent"),
    ("another data ID", MOTOR_TEXT.replace('crc = "CRC", data_id = "id_low_byte" }\n\n',
                                           'crc = "CRC", data_id = 7 }\n\n'),
     "protection.MotorCurrent"),
    ("the truth's current as the output", TRUTH_CURRENT.replace(
        CURRENT_LINE, 'outputs = [{ message = "SimTruth", signal = "TrueCurrent" }]'),
     "signals.outputs[0].message"),
])
def test_any_other_rig_on_our_dbc_is_read_by_the_rig_codec(
        tmp_path: Path, caplog: pytest.LogCaptureFixture, what: str, text: str,
        differs: str) -> None:
    """What `MotorDatabase` would not do as the rig says goes to the rig codec, which reads
    every key; that our SecOC and MonitorDiagnosis frames are then not served is logged
    once, and asking for our SecOC with --key is one line naming the key that differs."""
    path = written_rig(tmp_path, text)
    with caplog.at_level(logging.INFO, logger="monitor.rig.check"):
        rig = load_rig(path)
        codec = build_decoder(rig)
    assert isinstance(codec, RigCodec), what
    told = [r.getMessage() for r in caplog.records if "MonitorDiagnosis" in r.getMessage()]
    assert told == [f"rig file {path}: not our bus as the built-in rig describes it "
                    f"({differs}): read by the rig codec, so the monitor sends no "
                    "MonitorDiagnosis frames; our bus's SecOC is not verified"]
    with pytest.raises(RigError) as info:
        build_decoder(rig, secoc_key=bytes(16))
    assert str(info.value).startswith(f"rig file {path}: secoc: a SecOC key (--key) was "
                                      "given, but no message of the rig has SecOC")
    assert str(info.value).endswith("; our bus's own SecOC needs the bus described as the "
                                    "built-in rig (rigs/motor.toml) does, and this rig "
                                    f"differs at {differs}")


def test_a_rig_on_our_dbc_reads_what_it_says(tmp_path: Path) -> None:
    """The rig codec on our DBC: E2E with the rig's data ID (ours fails its CRC), the
    truth's current as a model output in A, the voltage in the model's unit."""
    mdb = load_database()
    fid = mdb.frame_id("current", 3)
    frame = mdb.encode_current(3, 1.25, counter=5)
    rig = load_rig(written_rig(tmp_path, MOTOR_TEXT.replace(
        'crc = "CRC", data_id = "id_low_byte" }\n\n', 'crc = "CRC", data_id = 7 }\n\n')))
    codec = build_decoder(rig)
    assert isinstance(codec, RigCodec)
    assert getattr(codec.decode(fid, frame, False, False, False, 1.0), "reason", None) \
        == "bad_crc"
    frame = mdb.encode_truth(3, 0.5, current=2.5, speed=10.0)
    rig = load_rig(written_rig(tmp_path, TRUTH_CURRENT.replace(
        CURRENT_LINE, 'outputs = [{ message = "SimTruth", signal = "TrueCurrent", '
                      'unit = "A" }]')))
    codec = build_decoder(rig)
    assert isinstance(codec, RigCodec)
    d = codec.decode(mdb.frame_id("truth", 3), frame, False, False, False, 1.0)
    assert getattr(d, "outputs", None) == pytest.approx((2.5,))
    assert getattr(d, "truth", None) == pytest.approx(0.5)


def test_our_dbc_in_milliamps_is_scaled_not_taken_as_amps(tmp_path: Path) -> None:
    """The built-in rig on a DBC of our bus that gives the current in mA: `MotorDatabase`
    would hand the estimator mA as A; the rig codec converts."""
    dbc = tmp_path / "motor_ma.dbc"
    text = REPO_DBC.read_text(encoding="cp1252")
    old = 'ArmatureCurrent : 16|16@1- (0.01,0) [-300|300] "A"'
    assert old in text
    dbc.write_text(text.replace(old, 'ArmatureCurrent : 16|16@1- (10,0) [-300000|300000] '
                                '"mA"'), encoding="cp1252")
    codec = build_decoder(replace(builtin_rig(), dbc=(dbc,)))
    assert isinstance(codec, RigCodec)
    mdb = load_database()
    d = codec.decode(mdb.frame_id("current", 2), mdb.encode_current(2, -1.5, counter=1),
                     False, False, False, 1.0)
    assert getattr(d, "outputs", None) == pytest.approx((-1.5,))
    with pytest.raises(RigError, match=r"^rig file <built-in rig>: secoc: .* this rig differs "
                                       r"at signals\.outputs\[0\]\.unit \(the DBC's values "
                                       r"scaled\)$"):
        build_decoder(replace(builtin_rig(), dbc=(dbc,)), secoc_key=bytes(16))


# ----------------------------------------------------------------- units


def _twin(tmp_path: Path, rig_text: str, dbc_text: str | None = None) -> Path:
    (tmp_path / "twin.dbc").write_text(dbc_text or (TEST_RIGS / "twin.dbc").read_text())
    return written_rig(tmp_path, rig_text)


TWIN = (TEST_RIGS / "twin.toml").read_text()
TWIN_Y1 = '{ message = "TwinSense", signal = "Y1" }'
SERVO = (TEST_RIGS / "servo.toml").read_text()


def _servo(tmp_path: Path, rig_text: str, voltage_unit: str = "V") -> Path:
    dbc = (TEST_RIGS / "servo.dbc").read_text()
    old = 'VoltageCmd : 0|32@1- (1,0) [-50|50] "V"'
    assert old in dbc
    (tmp_path / "servo.dbc").write_text(dbc.replace(
        old, f'VoltageCmd : 0|32@1- (1,0) [-50|50] "{voltage_unit}"'))
    return written_rig(tmp_path, rig_text)


def test_a_unit_only_the_rig_gives_is_taken_and_said_once(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = _twin(tmp_path, TWIN.replace(
        TWIN_Y1, '{ message = "TwinSense", signal = "Y1", unit = "rad/s" }'))
    with caplog.at_level(logging.INFO, logger="monitor.rig.check"):
        rig = load_rig(path)
        codec = build_decoder(rig)
        build_decoder(rig)
    assert isinstance(codec, RigCodec)
    told = [r.getMessage() for r in caplog.records if r.name == "monitor.rig.check"]
    assert told == [f"rig file {path}: signals.outputs[0]: TwinSense_N1.Y1 has no unit in "
                    "the DBC; taken as the rig's 'rad/s'"]
    fid, ext, data = codec.encode_sample("TwinSense", 1, [0.0, 0.0], [1.5, -2.0])
    assert getattr(codec.decode(fid, data, ext, False, False, 1.0), "outputs", None) \
        == pytest.approx((1.5, -2.0))


def test_units_convert_and_any_unit_suits_a_state_space_model(tmp_path: Path) -> None:
    """The twin's inputs are V in its DBC: a state-space model may take them in mV
    (scaled), and its unit-less outputs in anything pint knows."""
    path = _twin(tmp_path, TWIN.replace(
        '{ message = "TwinCommand", signal = "U1" }',
        '{ message = "TwinCommand", signal = "U1", unit = "mV" }').replace(
        TWIN_Y1, '{ message = "TwinSense", signal = "Y1", unit = "furlong" }'))
    codec = build_decoder(load_rig(path))
    assert isinstance(codec, RigCodec)
    assert [(i, s) for i, s, _ in codec.specs["TwinCommand"].inputs] == [(0, "U1"), (1, "U2")]
    assert [f for _, _, f in codec.specs["TwinCommand"].inputs] == pytest.approx([1000.0, 1.0])
    fid, ext, data = codec.encode_sample("TwinCommand", 1, [2500.0, -1.25], [])
    d = codec.decode(fid, data, ext, False, False, 1.0)
    assert [i for i, _ in getattr(d, "inputs", ())] == [0, 1]
    assert [v for _, v in getattr(d, "inputs", ())] == pytest.approx([2500.0, -1.25])


def test_a_dc_motor_takes_the_dbc_units_where_the_rig_gives_none(tmp_path: Path) -> None:
    path = _servo(tmp_path, SERVO.replace(', unit = "V" }', " }").replace(
        ', unit = "A" }', " }"))
    with pytest.raises(RigError, match=r"outputs\[0\]\.unit: a dc_motor model's output is a "
                                       r"current in A .*, not 'mA' \(the DBC's\): give unit = "
                                       r"\"A\" \(the DBC's 'mA' are converted\)"):
        load_rig(path)
    path = _servo(tmp_path, SERVO.replace(', unit = "V" }', " }"))
    assert isinstance(build_decoder(load_rig(path)), RigCodec)


# ----------------------------------------------------------------- DBCs cantools only warns about


DBC_HEAD = 'VERSION ""\n\nBU_: A\n\n'


def _dbc(tmp_path: Path, name: str, *messages: tuple[int, str]) -> Path:
    p = tmp_path / name
    p.write_text(DBC_HEAD + "".join(
        f'BO_ {fid} {msg}: 8 A\n SG_ S{i} : 0|8@1+ (1,0) [0|255] "" A\n\n'
        for i, (fid, msg) in enumerate(messages)))
    return p


def test_two_messages_on_one_id_are_refused(tmp_path: Path,
                                            caplog: pytest.LogCaptureFixture) -> None:
    one = _dbc(tmp_path, "one.dbc", (0x110, "Foo"), (0x110, "Bar"))
    with caplog.at_level(logging.DEBUG), pytest.raises(CodecError) as info:
        load_dbcs([one])
    assert str(info.value) == (f"{one}: messages Foo and Bar have the same 11-bit frame ID "
                               "0x110")
    assert not [r for r in caplog.records if r.name.startswith("cantools")]
    ext = _dbc(tmp_path, "ext.dbc", (0x80000123, "Foo"), (0x80000123, "Bar"), (0x123, "Baz"))
    with pytest.raises(CodecError, match=r"have the same 29-bit frame ID 0x123$"):
        load_dbcs([ext])
    named = _dbc(tmp_path, "named.dbc", (0x110, "Foo"), (0x111, "Foo"))
    with pytest.raises(CodecError) as info:
        load_dbcs([named])
    assert str(info.value) == (f"{named}: messages Foo (0x110) and Foo (0x111) have the "
                               "same name")


def test_two_files_that_clash_are_refused_naming_both(tmp_path: Path) -> None:
    a = _dbc(tmp_path, "a.dbc", (0x100, "Alpha"), (0x101, "Beta"))
    b = _dbc(tmp_path, "b.dbc", (0x102, "Gamma"), (0x101, "Delta"))
    with pytest.raises(CodecError) as info:
        load_dbcs([a, b])
    assert str(info.value) == (f"messages Beta (in {a}) and Delta (in {b}) have the same "
                               "11-bit frame ID 0x101")
    c = _dbc(tmp_path, "c.dbc", (0x103, "Alpha"))
    with pytest.raises(CodecError) as info:
        load_dbcs([a, c])
    assert str(info.value) == (f"messages Alpha (0x100 in {a}) and Alpha (0x103 in {c}) have "
                               "the same name")
    link = tmp_path / "link.dbc"
    link.symlink_to(a)
    with pytest.raises(CodecError) as info:
        load_dbcs([a, link])
    assert str(info.value) == f"{link}: listed twice (as {a} too)"
    with pytest.raises(CodecError) as info:
        load_dbcs([a, c, a])
    assert str(info.value) == f"{a}: listed twice"


def test_a_clashing_dbc_is_one_line_on_the_command_line(tmp_path: Path) -> None:
    """cantools' own warnings do not reach the terminal: one error line, exit 2."""
    (tmp_path / "twin.dbc").write_text((TEST_RIGS / "twin.dbc").read_text().replace("1553", "1537"))
    path = written_rig(tmp_path, TWIN)
    (tmp_path / "x.log").write_text("")
    res = motor_monitor("replay", "x.log", "--rig", str(path), cwd=tmp_path, timeout=120)
    assert res.returncode == 2, res.stderr
    assert res.stderr.splitlines() == [
        f"motor-monitor: error: rig file {path}: bus.dbc: {tmp_path / 'twin.dbc'}: messages "
        "TwinCommand_N1 and TwinSense_N1 have the same 11-bit frame ID 0x601"], res.stderr


# ----------------------------------------------------------------- the example rigs


@pytest.mark.parametrize("name", ["servo.toml", "press.toml", "twin.toml",
                                  "secure_drive.toml", "fd_servo.toml"])
def test_the_example_rigs_load_as_before(name: str, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.INFO, logger="monitor.rig.check"):
        assert isinstance(build_decoder(load_rig(TEST_RIGS / name)), RigCodec)
    # their DBCs give every unit they use: nothing taken from the rig, nothing to say
    assert not [r for r in caplog.records if r.name == "monitor.rig.check"], caplog.text
