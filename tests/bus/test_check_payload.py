"""`check_payload`, the one order of checks of a routed frame: our bus's codec
(`MotorDatabase`) and a rig's (`RigCodec`, here reading our own DBC) give the same bad
payload of the same message the same reason and detail; a limit fails NaN and inf whether
the DBC gives the signal a range or not, and passes the largest finite value of a signal
without one."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import cast

import pytest
from cantools.autosar.end_to_end import apply_profile2_crc
from cantools.database.can import Message

from monitor.bus.codec import Decoded, MotorDatabase, Rejected, load_database
from monitor.bus.rigcodec import RigCodec, RigMessage, load_rig_dbcs
from monitor.rig import build_decoder, load_rig
from tests.support.paths import ROOT

NODE = 3
MOTOR_TEXT = (ROOT / "rigs" / "motor.toml").read_text().replace(
    '"../dbc/motor.dbc"', f'"{ROOT / "dbc" / "motor.dbc"}"')
TRUTH_LINE = 'truth = { message = "SimTruth", signal = "TrueGamma" }'


def _rig_codec_on_our_dbc(tmp_path: Path) -> RigCodec:
    """Our bus as rigs/motor.toml describes it but without the truth: read by the rig codec
    (same E2E data IDs: the frame ID's low byte)."""
    assert TRUTH_LINE in MOTOR_TEXT
    path = tmp_path / "rig.toml"
    path.write_text(MOTOR_TEXT.replace(TRUTH_LINE, ""))
    codec = build_decoder(load_rig(path))
    assert isinstance(codec, RigCodec)
    return codec


def _current_beyond_range(mdb: MotorDatabase, counter: int) -> bytes:
    """A MotorCurrent payload with a valid E2E CRC whose current lies beyond the DBC's
    range (encoded by cantools, not strict)."""
    msg = mdb.message("current", NODE)
    sig = msg.get_signal_by_name("ArmatureCurrent")
    assert sig.maximum is not None
    values: dict[str, float] = {s.name: 0 for s in msg.signals}
    values.update(ArmatureCurrent=float(sig.maximum) + 10.0 * float(sig.scale), Counter=counter)
    protected = apply_profile2_crc(msg.encode(values, scaling=True, padding=False, strict=False),
                                   msg)
    assert protected is not None
    return bytes(protected)


def test_both_codecs_give_a_bad_payload_the_same_reason_and_detail(tmp_path: Path) -> None:
    mdb, rig = load_database(), _rig_codec_on_our_dbc(tmp_path)
    fid = mdb.frame_id("current", NODE)
    assert rig.frame_id("MotorCurrent", NODE) == fid
    good = mdb.encode_current(NODE, 12.5, counter=5)
    flipped = good[:2] + bytes([good[2] ^ 0x01]) + good[3:]
    cases: list[tuple[str, object, bool, str, str]] = [
        ("FD frame", good, True, "fd_frame",
         "CAN FD frame of 8 bytes; MotorCurrent_N3 is a classic CAN message"),
        ("short", good[:4], False, "wrong_length", "4 bytes, expected 8"),
        ("long", good + b"\0", False, "wrong_length", "9 bytes, expected 8"),
        ("one bit flipped", flipped, False, "bad_crc", f"crc 0x{good[0]:02X}, counter 5"),
        ("beyond the range", _current_beyond_range(mdb, 5), False, "out_of_range",
         "ArmatureCurrent=300.1 not in [-300.0, 300.0]"),
        ("not bytes", 2.5, False, "malformed", "payload is TypeError"),
    ]
    for name, data, is_fd, reason, detail in cases:
        for codec in (mdb, rig):
            r = codec.decode(fid, cast("bytes", data), False, False, False, 7.0, is_fd)
            assert isinstance(r, Rejected), (name, type(codec).__name__, r)
            assert (r.reason, r.detail, r.node, r.timestamp) == (reason, detail, NODE, 7.0), \
                (name, type(codec).__name__)
    for codec in (mdb, rig):  # the same payload, whole, classic, any bytes-like: a sample
        d = codec.decode(fid, cast("bytes", bytearray(good)), False, False, False, 7.0)
        assert isinstance(d, Decoded) and d.outputs == (12.5,), type(codec).__name__


FLOAT_DBC = """VERSION ""
NS_ :
BS_:
BU_: Drive Monitor
BO_ 1553 Fb_N1: 8 Drive
 SG_ Ranged : 0|32@1- (1,0) [-50|50] "A" Monitor
 SG_ Free : 32|32@1- (1,0) [0|0] "A" Monitor
BO_ 1554 Wide_N1: 8 Drive
 SG_ Huge : 0|64@1- (1,0) [0|0] "" Monitor
SIG_VALTYPE_ 1553 Ranged : 1;
SIG_VALTYPE_ 1553 Free : 1;
SIG_VALTYPE_ 1554 Huge : 2;
"""


def _float_codec(tmp_path: Path) -> RigCodec:
    """A rig codec over float32 signals with and without a range ([0|0]: none) and a
    float64 one without."""
    path = tmp_path / "floats.dbc"
    path.write_text(FLOAT_DBC)
    db = load_rig_dbcs([path])

    def resolve(name: str, node: int) -> tuple[Message, int] | None:
        msg = db.get_message_by_name(f"{name}_N{node}")
        return msg, msg.frame_id

    messages = [RigMessage("Fb", outputs=(("Ranged", 1.0), ("Free", 1.0))),
                RigMessage("Wide", truth="Huge")]
    return RigCodec(db, str(path), messages, resolve, [1])


@pytest.mark.parametrize(("message", "values", "detail"), [
    ("Fb", {"Ranged": math.inf, "Free": 0.0}, "Ranged=inf not in [-50.0, 50.0]"),
    ("Fb", {"Ranged": -math.inf, "Free": 0.0}, "Ranged=-inf not in [-50.0, 50.0]"),
    ("Fb", {"Ranged": math.nan, "Free": 0.0}, "Ranged=nan not in [-50.0, 50.0]"),
    ("Fb", {"Ranged": 50.0, "Free": math.inf}, "Free=inf not in [-inf, inf]"),
    ("Fb", {"Ranged": 0.0, "Free": -math.inf}, "Free=-inf not in [-inf, inf]"),
    ("Fb", {"Ranged": 0.0, "Free": math.nan}, "Free=nan not in [-inf, inf]"),
    ("Fb", {"Ranged": math.nan, "Free": math.nan}, "Ranged=nan not in [-50.0, 50.0]"),
    ("Wide", {"Huge": math.inf}, "Huge=inf not in [-inf, inf]"),
    ("Wide", {"Huge": -math.inf}, "Huge=-inf not in [-inf, inf]"),
    ("Fb", {"Ranged": -50.0, "Free": 2.0 ** 127}, None),  # float32: exact
    ("Wide", {"Huge": sys.float_info.max}, None),
    ("Wide", {"Huge": -sys.float_info.max}, None),
])
def test_a_limit_fails_nan_and_inf_with_or_without_a_range(
        tmp_path: Path, message: str, values: dict[str, float], detail: str | None) -> None:
    codec = _float_codec(tmp_path)
    msg = codec.message(message, 1)
    payload = msg.encode(values, scaling=True, padding=False, strict=False)
    r = codec.decode(msg.frame_id, payload, False, False, False, 1.0)
    if detail is None:
        assert isinstance(r, Decoded), r
        assert [r.raw[k] for k in values] == list(values.values())
    else:
        assert isinstance(r, Rejected), r
        assert (r.reason, r.detail) == ("out_of_range", detail)
