"""monitor.bus.codec: encoding, the never-raising decoder, E2E CRCs and alive counters."""

from __future__ import annotations

import dataclasses
import math
import shutil
from collections.abc import Callable, Iterable
from pathlib import Path

import can
import pytest
from cantools.autosar.end_to_end import apply_profile2_crc, check_profile2_crc
from hypothesis import given, settings
from hypothesis import strategies as st

from monitor.bus.codec import (
    HEALTH_STATES,
    KINDS,
    N_NODES,
    CodecError,
    Decoded,
    Kind,
    MotorDatabase,
    Rejected,
    RejectReason,
    default_dbc_path,
    e2e_data_id,
    frame_id,
    load_database,
)
from monitor.bus.counters import CounterCheck, CounterOutcome, CounterTracker
from tests.support.dbc import REPO_DBC, decode_frame, edited_dbc

E2E_KINDS: tuple[Kind, ...] = ("current", "voltage", "diagnosis")


@pytest.fixture(scope="module")
def mdb() -> MotorDatabase:
    return load_database()


def _valid(mdb: MotorDatabase, kind: Kind, node: int, counter: int = 3) -> bytes:
    if kind == "current":
        return mdb.encode_current(node, 1.5, counter)
    if kind == "voltage":
        return mdb.encode_voltage(node, 24.0, counter)
    if kind == "truth":
        return mdb.encode_truth(node, 0.5, 1.5, 100.0)
    return mdb.encode_diagnosis(node, "fault", 0.5, 12.0, 4, counter)


def _tally(checks: Iterable[CounterCheck]) -> dict[str, int]:
    """Frames per alive-counter outcome (all three keys present)."""
    total = dict.fromkeys((o.value for o in CounterOutcome), 0)
    for check in checks:
        total[check.outcome.value] += 1
    return total


class _Checks:
    """A `CounterTracker` that keeps every `CounterCheck` it returns, per stream."""

    def __init__(self) -> None:
        self.tracker = CounterTracker()
        self.seen: list[tuple[Kind, int, CounterCheck]] = []

    def update(self, kind: Kind, node: int, counter: int) -> CounterCheck:
        check = self.tracker.update(kind, node, counter)
        self.seen.append((kind, node, check))
        return check

    def of(self, kind: Kind | None = None, node: int | None = None) -> list[CounterCheck]:
        """The checks of the streams that match (None: any kind, any node)."""
        return [c for k, n, c in self.seen
                if (kind is None or k == kind) and (node is None or n == node)]

    def counts(self, kind: Kind | None = None, node: int | None = None) -> dict[str, int]:
        return _tally(self.of(kind, node))

    def lost_frames(self, kind: Kind | None = None, node: int | None = None) -> int:
        return sum(c.lost for c in self.of(kind, node))


def _raw_frame(mdb: MotorDatabase, kind: Kind, node: int, raw: dict[str, int]) -> bytes:
    """A frame with arbitrary raw signal values (cantools encodes, cantools adds the CRC).

    SecOC signals not given are 0 (an unsigned frame).
    """
    msg = mdb.message(kind, node)
    names = {s.name for s in msg.signals}
    raw = {**{n: 0 for n in ("FreshnessValue", "Authenticator") if n in names}, **raw}
    payload = msg.encode(raw, scaling=False, strict=False)
    if kind == "truth":
        return payload
    protected = apply_profile2_crc(payload, msg)
    assert protected is not None
    return bytes(protected)


# ----------------------------------------------------------------------------- loading


def test_default_path_is_package_copy_of_repo_dbc(mdb: MotorDatabase) -> None:
    assert default_dbc_path().read_bytes() == REPO_DBC.read_bytes()
    assert mdb.source == str(default_dbc_path())
    assert load_database(REPO_DBC).frame_id("current", 0) == 0x110
    assert load_database(str(REPO_DBC)).frame_id("diagnosis", 15) == 0x18F


def test_missing_dbc_raises_codec_error(tmp_path: Path) -> None:
    missing = tmp_path / "nope.dbc"
    with pytest.raises(CodecError, match=r"nope\.dbc: no such file") as info:
        load_database(missing)
    assert isinstance(info.value, ValueError)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("text", "what"),
    [
        ("", "not a valid DBC"),
        ("BO_ this is not a dbc\n", "not a valid DBC"),
        ('VERSION ""\nBU_: A\nBO_ 1 Foo: 8 A\n SG_ X : 0|8@1+ (1,0) [0|1] "" A\n',
         "unexpected message Foo"),
    ],
)
def test_malformed_dbc_raises_one_line(tmp_path: Path, text: str, what: str) -> None:
    path = tmp_path / "broken.dbc"
    path.write_text(text)
    with pytest.raises(CodecError) as info:
        load_database(path)
    msg = str(info.value)
    assert "broken.dbc" in msg and what in msg and "\n" not in msg


@pytest.mark.parametrize(
    ("old", "new", "what"),
    [
        ('BA_ "E2EDataID" BO_ 273 17;', 'BA_ "E2EDataID" BO_ 273 18;', "E2EDataID must be 17"),
        ("BO_ 287 MotorCurrent_N15: 8", "BO_ 1279 MotorCurrent_N15: 8", "expected standard id"),
        ('3 "no_data"', '3 "gone"', "HealthState VAL_"),
    ],
)
def test_dbc_inconsistent_with_scheme(tmp_path: Path, old: str, new: str, what: str) -> None:
    with pytest.raises(CodecError, match=what):
        load_database(edited_dbc(tmp_path, old, new))


def test_dbc_missing_a_node(tmp_path: Path) -> None:
    lines = REPO_DBC.read_text().splitlines()
    start = lines.index("BO_ 391 MonitorDiagnosis_N7: 8 Monitor")
    end = lines.index("", start)
    kept = [ln for i, ln in enumerate(lines) if not start <= i <= end and " 391 " not in ln]
    path = tmp_path / "motor.dbc"
    path.write_text("\n".join(kept) + "\n")
    with pytest.raises(CodecError, match=r"missing message MonitorDiagnosis_N7 \(0x187"):
        load_database(path)


def test_directory_instead_of_file(tmp_path: Path) -> None:
    with pytest.raises(CodecError, match="is a directory, not a regular file"):
        load_database(tmp_path)


# ----------------------------------------------------------------------------- ids


def test_frame_ids_and_data_ids(mdb: MotorDatabase) -> None:
    bases: dict[Kind, int] = {"current": 0x110, "voltage": 0x120, "truth": 0x7E0,
                              "diagnosis": 0x180, "sync": 0x1F0}
    for kind, base in bases.items():
        for node in range(N_NODES):
            assert frame_id(kind, node) == mdb.frame_id(kind, node) == base + node
    assert e2e_data_id(0x113) == 0x13
    assert e2e_data_id(0x12F) == 0x2F
    assert e2e_data_id(0x180) == 0x80
    with pytest.raises(CodecError, match="node"):
        frame_id("current", 16)
    with pytest.raises(CodecError, match="kind"):
        frame_id("speed", 0)  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- roundtrip


@pytest.mark.parametrize("node", [0, 7, 15])
@pytest.mark.parametrize("counter", range(16))
def test_roundtrip_all_kinds(mdb: MotorDatabase, node: int, counter: int) -> None:
    ts = 1700000000.25
    d = decode_frame(mdb, 0x110 + node, mdb.encode_current(node, -123.45, counter), ts)
    assert isinstance(d, Decoded)
    assert (d.kind, d.node, d.counter, d.timestamp) == ("current", node, counter, ts)
    assert d.value == pytest.approx(-123.45)

    d = decode_frame(mdb, 0x120 + node, mdb.encode_voltage(node, 399.99, counter), ts)
    assert isinstance(d, Decoded)
    assert (d.kind, d.node, d.counter) == ("voltage", node, counter)
    assert d.value == pytest.approx(399.99)

    d = decode_frame(mdb, 0x7E0 + node, mdb.encode_truth(node, 0.1234, 250.0, -2999.5), ts)
    assert isinstance(d, Decoded)
    assert (d.kind, d.node, d.counter) == ("truth", node, None)
    assert d.value == pytest.approx(0.1234)
    assert d.raw["TrueCurrent"] == pytest.approx(250.0)
    assert d.raw["TrueSpeed"] == pytest.approx(-2999.5)

    state = HEALTH_STATES[counter % 4]
    d = decode_frame(mdb, 0x180 + node, mdb.encode_diagnosis(node, state, -0.012, -600.5, 255,
                                                        counter), ts)
    assert isinstance(d, Decoded)
    assert (d.kind, d.node, d.counter) == ("diagnosis", node, counter)
    assert d.value == pytest.approx(-0.012)
    assert d.raw["HealthState"] == counter % 4
    assert d.raw["FaultEstimate"] == pytest.approx(-600.5)
    assert d.raw["RuleCount"] == 255


def test_counter_wraparound_sequence(mdb: MotorDatabase) -> None:
    tracker = CounterTracker()
    checks: list[CounterCheck] = []
    for i in range(40):  # 2.5 laps: 15 -> 0 must be an ordinary step
        d = decode_frame(mdb, 0x115, mdb.encode_current(5, float(i), i % 16))
        assert isinstance(d, Decoded) and d.counter == i % 16
        check = tracker.observe(d)
        assert check is not None and check.outcome is CounterOutcome.OK
        checks.append(check)
    assert _tally(checks) == {"ok": 40, "repeated": 0, "jump": 0}


def test_health_state_by_index_and_name(mdb: MotorDatabase) -> None:
    assert mdb.encode_diagnosis(2, 2, 1.0, 5.0, 3, 1) == \
        mdb.encode_diagnosis(2, "outage", 1.0, 5.0, 3, 1)


def test_decoded_is_frozen(mdb: MotorDatabase) -> None:
    d = decode_frame(mdb, 0x110, mdb.encode_current(0, 1.0, 0))
    assert isinstance(d, Decoded)
    with pytest.raises(dataclasses.FrozenInstanceError):
        d.value = 2.0  # type: ignore[misc]


def test_decode_can_message(mdb: MotorDatabase) -> None:
    msg = can.Message(arbitration_id=0x121, data=mdb.encode_voltage(1, 12.0, 9),
                      is_extended_id=False, timestamp=12.5)
    d = mdb.decode_can(msg)
    assert isinstance(d, Decoded)
    assert (d.kind, d.node, d.value, d.counter, d.timestamp) == ("voltage", 1, 12.0, 9, 12.5)
    err = can.Message(arbitration_id=0x121, is_error_frame=True)
    r = mdb.decode_can(err)
    assert isinstance(r, Rejected) and r.reason is RejectReason.ERROR_FRAME


# ----------------------------------------------------------------------------- CRC


@pytest.mark.parametrize("kind", E2E_KINDS)
@pytest.mark.parametrize("counter", range(16))
def test_crc_matches_cantools(mdb: MotorDatabase, kind: Kind, counter: int) -> None:
    node = counter % N_NODES
    payload = _valid(mdb, kind, node, counter)
    fid = frame_id(kind, node)
    assert check_profile2_crc(payload, mdb.message(kind, node)) is True
    # The documented data ID, passed as a plain int, gives the same verdict.
    assert check_profile2_crc(payload, fid & 0xFF) is True
    assert check_profile2_crc(payload, (fid & 0xFF) ^ 1) is False


@pytest.mark.parametrize("kind", E2E_KINDS)
def test_every_single_bit_flip_is_bad_crc(mdb: MotorDatabase, kind: Kind) -> None:
    payload = _valid(mdb, kind, 4, 11)
    for bit in range(64):
        flipped = bytearray(payload)
        flipped[bit // 8] ^= 1 << (bit % 8)
        r = decode_frame(mdb, frame_id(kind, 4), bytes(flipped))
        assert isinstance(r, Rejected), bit
        assert r.reason is RejectReason.BAD_CRC, bit
        assert (r.kind, r.node) == (kind, 4)


def test_masquerade_is_bad_crc(mdb: MotorDatabase) -> None:
    for counter in range(16):
        payload = mdb.encode_current(1, 10.0, counter)
        for fid in (0x112, 0x121, 0x181):  # another node, another kind
            r = decode_frame(mdb, fid, payload)
            assert isinstance(r, Rejected) and r.reason is RejectReason.BAD_CRC


# ----------------------------------------------------------------------------- rejections


def test_every_reject_reason_has_a_concrete_frame(mdb: MotorDatabase) -> None:
    good = mdb.encode_current(3, 1.0, 0)
    reserved = bytearray(good)
    reserved[1] |= 0x80  # a bit no signal uses; CRC recomputed so only the layout is wrong
    protected = apply_profile2_crc(bytes(reserved), mdb.message("current", 3))
    assert protected is not None
    keyed = mdb.with_secoc_key(bytes(range(16)))
    sender = mdb.with_secoc_key(bytes(range(16)))
    unsynced = decode_frame(keyed, 0x113, good)  # nothing to verify against before a sync
    assert isinstance(decode_frame(keyed, 0x1F3, sender.encode_sync(3, "current")), Decoded)
    signed = sender.encode_current(3, 1.0, 0)
    assert isinstance(decode_frame(keyed, 0x113, signed), Decoded)
    cases: dict[RejectReason, Decoded | Rejected] = {
        RejectReason.UNKNOWN_ID: decode_frame(mdb, 0x100, good),
        RejectReason.WRONG_LENGTH: decode_frame(mdb, 0x113, good[:7]),
        RejectReason.BAD_CRC: decode_frame(mdb, 0x113, bytes([good[0] ^ 0xFF]) + good[1:]),
        RejectReason.OUT_OF_RANGE: decode_frame(
            mdb, 0x113, _raw_frame(mdb, "current", 3,
                                   {"CRC": 0, "Counter": 1, "ArmatureCurrent": 30001})),
        RejectReason.MALFORMED: decode_frame(mdb, 0x113, bytes(protected)),
        RejectReason.REMOTE_FRAME: mdb.decode(0x113, b"", False, True, False, 0.0),
        RejectReason.ERROR_FRAME: mdb.decode(0x20000004, bytes(8), True, False, True, 0.0),
        RejectReason.EXTENDED_ID: mdb.decode(0x113, good, True, False, False, 0.0),
        RejectReason.BAD_MAC: decode_frame(keyed, 0x113, good),  # unsigned frame, keyed monitor
        RejectReason.STALE_FRESHNESS: decode_frame(keyed, 0x113, signed),  # replayed
        RejectReason.UNSYNCED: unsynced,
        RejectReason.FD_FRAME: mdb.decode(0x113, good, False, False, False, 0.0, True),
    }
    assert set(cases) == set(RejectReason)
    for reason, result in cases.items():
        assert isinstance(result, Rejected), reason
        assert result.reason is reason
        assert result.reason == reason.value
        assert "\n" not in result.detail
    for reason in (RejectReason.WRONG_LENGTH, RejectReason.BAD_CRC,
                   RejectReason.OUT_OF_RANGE, RejectReason.MALFORMED, RejectReason.BAD_MAC,
                   RejectReason.STALE_FRESHNESS, RejectReason.UNSYNCED,
                   RejectReason.FD_FRAME):
        assert (cases[reason].node, cases[reason].kind) == (3, "current")
    assert cases[RejectReason.UNKNOWN_ID].node is None


def test_reject_reason_values() -> None:
    assert {r.value for r in RejectReason} == {
        "unknown_id", "wrong_length", "bad_crc", "out_of_range", "malformed",
        "remote_frame", "error_frame", "extended_id", "bad_mac", "stale_freshness",
        "unsynced", "fd_frame",
    }


@pytest.mark.parametrize(
    ("kind", "raw", "signal"),
    [
        ("voltage", {"CRC": 0, "Counter": 0, "VoltageCommand": -40001}, "VoltageCommand"),
        ("truth", {"TrueGamma": 10001, "TrueCurrent": 0, "TrueSpeed": 0}, "TrueGamma"),
        ("truth", {"TrueGamma": 0, "TrueCurrent": 0, "TrueSpeed": 300001}, "TrueSpeed"),
        ("diagnosis", {"CRC": 0, "Counter": 0, "HealthState": 4, "GammaEstimate": 0,
                       "FaultEstimate": 0, "RuleCount": 0, "ModelMismatch": 0}, "HealthState"),
        ("diagnosis", {"CRC": 0, "Counter": 0, "HealthState": 0, "GammaEstimate": -501,
                       "FaultEstimate": 0, "RuleCount": 0, "ModelMismatch": 0},
         "GammaEstimate"),
    ],
)
def test_out_of_range_per_signal(
    mdb: MotorDatabase, kind: Kind, raw: dict[str, int], signal: str
) -> None:
    r = decode_frame(mdb, frame_id(kind, 9), _raw_frame(mdb, kind, 9, raw))
    assert isinstance(r, Rejected)
    assert r.reason is RejectReason.OUT_OF_RANGE
    assert signal in r.detail


def test_wrong_length_longer_frame(mdb: MotorDatabase) -> None:
    r = decode_frame(mdb, 0x7E2, _valid(mdb, "truth", 2) + b"\0")
    assert isinstance(r, Rejected) and r.reason is RejectReason.WRONG_LENGTH


def test_bytearray_and_memoryview_payloads(mdb: MotorDatabase) -> None:
    payload = mdb.encode_current(0, 2.0, 1)
    for data in (bytearray(payload), memoryview(payload)):
        d = mdb.decode(0x110, data, False, False, False, 0.0)  # type: ignore[arg-type]
        assert isinstance(d, Decoded) and d.value == 2.0


# ----------------------------------------------------------------------------- encode errors


@pytest.mark.parametrize(
    "call",
    [
        lambda m: m.encode_current(0, 300.01, 0),
        lambda m: m.encode_current(0, math.nan, 0),
        lambda m: m.encode_voltage(0, math.inf, 0),
        lambda m: m.encode_current(16, 1.0, 0),
        lambda m: m.encode_current(-1, 1.0, 0),
        lambda m: m.encode_current(0, 1.0, 16),
        lambda m: m.encode_voltage(0, 1.0, -1),
        lambda m: m.encode_truth(0, 1.5, 0.0, 0.0),
        lambda m: m.encode_diagnosis(0, "broken", 0.0, 0.0, 0, 0),
        lambda m: m.encode_diagnosis(0, 4, 0.0, 0.0, 0, 0),  # past no_data (3)
        lambda m: m.encode_diagnosis(0, 0, 0.0, 0.0, 256, 0),
        lambda m: m.encode_diagnosis(0, 0, 1.6, 0.0, 1, 0),
    ],
)
def test_encode_rejects_bad_values(
    mdb: MotorDatabase, call: Callable[[MotorDatabase], bytes]
) -> None:
    with pytest.raises(CodecError):
        call(mdb)


# ----------------------------------------------------------------------------- fuzzing


@settings(max_examples=3000, deadline=None)
@given(
    fid=st.one_of(st.integers(0, 0x7FF), st.sampled_from([frame_id(k, n) for k in KINDS
                                                          for n in range(N_NODES)]),
                  st.integers(0, 0x1FFFFFFF)),
    data=st.binary(min_size=0, max_size=64),
    is_extended=st.booleans(),
    is_remote=st.booleans(),
    is_error=st.booleans(),
    ts=st.floats(allow_nan=True),
)
def test_decode_never_raises(
    mdb: MotorDatabase, fid: int, data: bytes, is_extended: bool, is_remote: bool,
    is_error: bool, ts: float,
) -> None:
    result = mdb.decode(fid, data, is_extended, is_remote, is_error, ts)
    assert isinstance(result, Decoded | Rejected)
    if isinstance(result, Decoded):
        assert not (is_extended or is_remote or is_error) and len(data) == 8
        assert math.isfinite(result.value)
    else:
        assert isinstance(result.reason, RejectReason)


@settings(max_examples=2000, deadline=None)
@given(kind=st.sampled_from(KINDS), node=st.integers(0, 15), data=st.binary(min_size=8,
                                                                             max_size=8))
def test_random_payload_on_known_ids(mdb: MotorDatabase, kind: Kind, node: int,
                                     data: bytes) -> None:
    result = decode_frame(mdb, frame_id(kind, node), data)
    if isinstance(result, Decoded):
        lo_hi = {s.name: (s.minimum, s.maximum) for s in mdb.message(kind, node).signals}
        for name, value in result.raw.items():
            lo, hi = lo_hi[name]
            assert lo is not None and hi is not None and lo <= value <= hi
        if kind not in ("truth", "sync"):  # no E2E on these
            assert check_profile2_crc(data, mdb.message(kind, node)) is True
    else:
        assert (result.node, result.kind) == (node, kind)


@settings(max_examples=500, deadline=None)
@given(
    node=st.integers(0, 15),
    counter=st.integers(0, 15),
    current=st.floats(-300, 300),
    volts=st.floats(-400, 400),
    gamma=st.floats(0, 1),
    speed=st.floats(-3000, 3000),
    gamma_hat=st.floats(-0.5, 1.5),
    fault=st.floats(-1000, 1000),
    state=st.sampled_from(HEALTH_STATES),
    rules=st.integers(0, 255),
)
def test_roundtrip_property(
    mdb: MotorDatabase, node: int, counter: int, current: float, volts: float, gamma: float,
    speed: float, gamma_hat: float, fault: float, state: str, rules: int,
) -> None:
    def back(fid: int, data: bytes) -> Decoded:
        d = decode_frame(mdb, fid, data)
        assert isinstance(d, Decoded), d
        return d

    assert back(0x110 + node, mdb.encode_current(node, current, counter)).value == \
        pytest.approx(current, abs=0.005 + 1e-9)
    assert back(0x120 + node, mdb.encode_voltage(node, volts, counter)).value == \
        pytest.approx(volts, abs=0.005 + 1e-9)
    t = back(0x7E0 + node, mdb.encode_truth(node, gamma, current, speed))
    assert t.value == pytest.approx(gamma, abs=0.00005 + 1e-9)
    assert t.raw["TrueSpeed"] == pytest.approx(speed, abs=0.005 + 1e-9)
    d = back(0x180 + node, mdb.encode_diagnosis(node, state, gamma_hat, fault, rules, counter))
    assert d.value == pytest.approx(gamma_hat, abs=0.0005 + 1e-9)
    assert d.raw["FaultEstimate"] == pytest.approx(fault, abs=0.05 + 1e-9)
    assert HEALTH_STATES[int(d.raw["HealthState"])] == state
    assert (d.raw["RuleCount"], d.counter) == (rules, counter)


# ----------------------------------------------------------------------------- counters


def test_counter_tracker_sequences() -> None:
    tr = _Checks()
    seq = [(14, "ok", 0), (15, "ok", 0), (0, "ok", 0), (1, "ok", 0), (1, "repeated", 0),
           (4, "jump", 2), (5, "ok", 0), (15, "jump", 9), (2, "jump", 2), (2, "repeated", 0)]
    for counter, outcome, lost in seq:
        check = tr.update("current", 1, counter)
        assert (check.outcome.value, check.lost) == (outcome, lost), counter
    assert tr.counts() == {"ok": 5, "repeated": 2, "jump": 3}
    assert tr.counts("current", 1) == tr.counts()
    assert tr.lost_frames() == 13
    # streams are independent: another node / kind starts fresh
    assert tr.update("current", 2, 9).outcome is CounterOutcome.OK
    assert tr.update("voltage", 1, 9).outcome is CounterOutcome.OK
    assert tr.counts("current", 2) == {"ok": 1, "repeated": 0, "jump": 0}
    assert tr.counts(node=1)["ok"] == 6
    assert tr.counts("voltage") == {"ok": 1, "repeated": 0, "jump": 0}


def test_counter_tracker_jump_by_three_and_a_fresh_stream() -> None:
    tr = _Checks()
    tr.update("voltage", 0, 7)
    check = tr.update("voltage", 0, 10)
    assert check.outcome is CounterOutcome.JUMP and check.lost == 2
    # a stream with no previous counter takes any counter as ok (was: after reset)
    assert CounterTracker().update("voltage", 0, 3).outcome is CounterOutcome.OK
    assert tr.lost_frames("voltage", 0) == 2
    with pytest.raises(ValueError, match=r"0\.\.15"):
        tr.update("voltage", 0, 16)


def test_counter_tracker_ignores_truth(mdb: MotorDatabase) -> None:
    d = decode_frame(mdb, 0x7E0, mdb.encode_truth(0, 0.0, 0.0, 0.0))
    assert isinstance(d, Decoded)
    assert CounterTracker().observe(d) is None


def test_load_database_copy_in_other_dir(tmp_path: Path) -> None:
    # A relocated copy loads too (an installed wheel finds its own package data).
    shutil.copy(REPO_DBC, tmp_path / "motor.dbc")
    assert load_database(tmp_path / "motor.dbc").frame_id("truth", 1) == 0x7E1
