"""monitor.bus.secoc: SecOC-style frame authentication (truncated AES-CMAC, freshness counters).

No mocks: real keys, real AES-CMAC (cryptography), cantools' own SecOC and E2E helpers as
the reference for the layout, and the monitor pipeline fed by the virtual ECU.
"""

from __future__ import annotations

import os
import re
import stat
from pathlib import Path
from typing import cast

import can
import pytest
from cantools.autosar.end_to_end import apply_profile2_crc, check_profile2_crc
from cantools.autosar.secoc import (
    apply_authenticator,
    compute_authenticator,
    verify_authenticator,
)
from hypothesis import given, settings
from hypothesis import strategies as st

from monitor.bus.codec import (
    N_NODES,
    SECOC_KINDS,
    CodecError,
    Decoded,
    Kind,
    MotorDatabase,
    Rejected,
    RejectReason,
    frame_id,
    load_database,
)
from monitor.bus.secoc import (
    DEFAULT_WINDOW,
    SecOC,
    SecOCError,
    SecOCLayout,
    aes_cmac,
    load_key,
    nearest_freshness,
    parse_key,
)
from monitor.pipeline import MonitorConfig, MonitorPipeline
from sim_ecu.ecu import ECUError, VirtualECU
from sim_ecu.scenario import load_scenario
from tests.support.dbc import REPO_DBC, decode_frame, edited_dbc
from tests.support.pipeline import feed_all

KEY = bytes.fromhex("000102030405060708090a0b0c0d0e0f")
OTHER_KEY = bytes.fromhex("f0e0d0c0b0a090807060504030201000")
T0 = 1_700_000_000.0
_BASE = load_database()  # keyless; with_secoc_key gives keyed copies with fresh counters

# RFC 4493 section 4 (AES-128) and NIST SP 800-38B appendix D.3 (AES-256).
RFC4493_KEY = bytes.fromhex("2b7e151628aed2a6abf7158809cf4f3c")
RFC4493_MESSAGE = bytes.fromhex(
    "6bc1bee22e409f96e93d7e117393172a"
    "ae2d8a571e03ac9c9eb76fac45af8e51"
    "30c81c46a35ce411e5fbc1191a0a52ef"
    "f69f2445df4f9b17ad2b417be66c3710"
)
RFC4493_VECTORS = [  # (message length, CMAC)
    (0, "bb1d6929e95937287fa37d129b756746"),
    (16, "070a16b46b4d4144f79bdd9dd04a287c"),
    (40, "dfa66747de9ae63030ca32611497c827"),
    (64, "51f0bebf7e3b9d92fc49741779363cfe"),
]
AES256_KEY = bytes.fromhex("603deb1015ca71be2b73aef0857d77811f352c073b6108d72d9810a30914dff4")
AES256_VECTORS = [
    (0, "028962f61b7bf89efc6b551f4667d983"),
    (16, "28a7023f452e8f82bd4bf28d8c37c35c"),
    (40, "aaf3d8f1de5640c232f5b169b9c911e6"),
    (64, "e1992190549f6ed5696a2c056c315410"),
]


def _encode(db: MotorDatabase, kind: Kind, node: int, value: float, counter: int) -> bytes:
    if kind == "current":
        return db.encode_current(node, value, counter)
    return db.encode_voltage(node, value, counter)


def _reason(result: Decoded | Rejected) -> RejectReason | None:
    return result.reason if isinstance(result, Rejected) else None


def _sync_all(tx: MotorDatabase, rx: MotorDatabase) -> None:
    """Every stream of `rx` synchronised to `tx` by real sync frames (as at an ECU's start)."""
    for node in range(N_NODES):
        for kind in SECOC_KINDS:
            d = decode_frame(rx, frame_id("sync", node), tx.encode_sync(node, kind))
            assert isinstance(d, Decoded) and d.kind == "sync", d


def _synced(rx: MotorDatabase) -> MotorDatabase:
    """`rx` with every stream synchronised at 0 (a monitor that saw the ECUs start)."""
    assert rx.secoc is not None
    for node in range(N_NODES):
        for kind in SECOC_KINDS:
            rx.secoc.set_rx_freshness((kind, node), 0)
    return rx


@pytest.fixture
def pair() -> tuple[MotorDatabase, MotorDatabase]:
    """(sender, receiver): two databases with the same key and their own counters, the
    receiver synchronised to the sender by its sync frames."""
    tx, rx = load_database(secoc_key=KEY), load_database(secoc_key=KEY)
    _sync_all(tx, rx)
    return tx, rx


def _forge(db: MotorDatabase, kind: Kind, node: int, frame: bytes, mac: bytes,
           value: float | None = None) -> bytes:
    """What an attacker without the key can send: any content, a guessed MAC, valid CRC.

    Starts from an observed `frame` (its counter and freshness bits), optionally changes
    the value, puts `mac` in the Authenticator bytes and recomputes the E2E CRC with
    cantools' profile 2 helper (the CRC protects against errors, not attackers).
    """
    msg = db.message(kind, node)
    signals = cast("dict[str, int]", dict(msg.decode(frame, decode_choices=False,
                                                     scaling=False)))
    if value is not None:
        name = "ArmatureCurrent" if kind == "current" else "VoltageCommand"
        signals[name] = round(value / 0.01)
    signals["Authenticator"] = int.from_bytes(mac, "little")
    signals["CRC"] = 0
    payload = msg.encode(signals, scaling=False, strict=False)
    protected = apply_profile2_crc(payload, msg)
    assert protected is not None
    assert check_profile2_crc(bytes(protected), msg) is True
    return bytes(protected)


# ----------------------------------------------------------------------------- AES-CMAC


@pytest.mark.parametrize(("length", "expected"), RFC4493_VECTORS)
def test_aes128_cmac_rfc4493(length: int, expected: str) -> None:
    message = RFC4493_MESSAGE[:length]
    assert aes_cmac(RFC4493_KEY, message).hex() == expected
    secoc = SecOC(RFC4493_KEY)
    for _ in range(3):  # the keyed prototype is copied, never consumed
        assert secoc.cmac(message).hex() == expected
    # the same through the cantools authenticator callback
    msg = load_database().message("current", 0)
    assert secoc.authenticator_fn()(msg, message, 0).hex() == expected


@pytest.mark.parametrize(("length", "expected"), AES256_VECTORS)
def test_aes256_cmac_sp800_38b(length: int, expected: str) -> None:
    message = RFC4493_MESSAGE[:length]
    assert aes_cmac(AES256_KEY, message).hex() == expected
    assert SecOC(AES256_KEY).cmac(message).hex() == expected


def test_bad_key_lengths_are_refused() -> None:
    for key in (b"", bytes(15), bytes(24), bytes(33)):
        with pytest.raises(SecOCError, match="16 or 32 bytes"):
            SecOC(key)
        with pytest.raises(SecOCError):
            aes_cmac(key, b"")
    with pytest.raises(SecOCError, match="window"):
        SecOC(KEY, window=0)


# ----------------------------------------------------------------------------- layout


def test_layout_from_the_dbc_and_cantools_properties() -> None:
    db = load_database(secoc_key=KEY)
    for node in range(N_NODES):
        cur = db.secoc_layout("current", node)
        volt = db.secoc_layout("voltage", node)
        assert cur is not None and volt is not None
        assert (cur.data_id, cur.payload_length, cur.fv_start, cur.fv_bits, cur.auth_start,
                cur.auth_bytes, cur.freshness_bits, cur.trailer) == (
            0x110 + node, 4, 32, 8, 5, 3, 64, True)
        assert (volt.data_id, volt.payload_length, volt.fv_start, volt.fv_bits,
                volt.auth_start, volt.auth_bytes, volt.freshness_bits, volt.trailer) == (
            0x120 + node, 5, 12, 4, 5, 3, 64, False)
        for kind, layout in (("current", cur), ("voltage", volt)):
            autosar = db.message(kind, node).autosar  # type: ignore[arg-type]
            assert autosar is not None and autosar.is_secured and autosar.secoc is not None
            props = autosar.secoc
            assert (props.data_id, props.payload_length, props.freshness_bit_length,
                    props.freshness_tx_bit_length, props.auth_tx_bit_length) == (
                layout.data_id, layout.payload_length, 64, layout.fv_bits, 24)
            assert props.auth_algorithm_name == "AES-CMAC"
            assert autosar.e2e is not None  # E2E and SecOC side by side
        for kind in ("truth", "diagnosis"):
            assert db.secoc_layout(kind, node) is None  # type: ignore[arg-type]
            autosar = db.message(kind, node).autosar  # type: ignore[arg-type]
            assert autosar is None or autosar.secoc is None
    assert SECOC_KINDS == ("current", "voltage")


def test_frame_bytes_by_hand() -> None:
    # The layout written out with nothing but AES-CMAC: no SecOC class involved.
    tx = load_database(secoc_key=KEY)
    for k in range(1, 4):
        frame = tx.encode_current(9, 12.34, k % 16)
        auth_data = ((0x119).to_bytes(2, "big") + b"\0" + frame[1:4]
                     + k.to_bytes(8, "big"))
        assert frame[4] == k  # FreshnessValue: the low 8 bits
        assert frame[5:8] == aes_cmac(KEY, auth_data)[:3]
        assert check_profile2_crc(frame, tx.message("current", 9)) is True
        frame = tx.encode_voltage(9, -230.5, k % 16)
        assert frame[1] >> 4 == k  # FreshnessValue: high nibble of byte 1
        auth_data = ((0x129).to_bytes(2, "big") + b"\0" + frame[1:5]
                     + k.to_bytes(8, "big"))
        assert frame[5:8] == aes_cmac(KEY, auth_data)[:3]
        assert check_profile2_crc(frame, tx.message("voltage", 9)) is True
    # E2E over SecOC: the CRC is computed after the MAC and covers it.
    frame = tx.encode_current(9, 1.0, 4)
    no_mac = frame[:5] + bytes(3)
    assert check_profile2_crc(no_mac, tx.message("current", 9)) is False


@pytest.mark.parametrize("node", range(N_NODES))
def test_cantools_secoc_helpers_agree(node: int) -> None:
    tx = load_database(secoc_key=KEY)
    secoc = tx.secoc
    assert secoc is not None
    fn = secoc.authenticator_fn()
    for k in range(1, 40):
        # MotorCurrent is cantools' secured-PDU layout: its helpers build and accept it.
        frame = tx.encode_current(node, k * 0.5, k % 16)
        msg = tx.message("current", node)
        no_crc = b"\0" + frame[1:]
        authentic = no_crc[:4] + bytes(4)
        assert bytes(apply_authenticator(authentic, msg, fn, k)) == no_crc
        assert verify_authenticator(no_crc, msg, fn, k) is True
        assert verify_authenticator(no_crc, msg, fn, k + 256) is False  # same sent bits
        # MotorVoltage: cantools' authenticator input, our placement (4 bits in byte 1).
        frame = tx.encode_voltage(node, -k * 1.5, k % 16)
        msg = tx.message("voltage", node)
        mac = compute_authenticator(b"\0" + frame[1:], msg, fn, k)
        assert frame[5:8] == mac[:3]


# ----------------------------------------------------------------------------- round trip


@pytest.mark.parametrize("kind", SECOC_KINDS)
def test_sign_verify_every_node(pair: tuple[MotorDatabase, MotorDatabase], kind: Kind) -> None:
    tx, rx = pair
    for node in range(N_NODES):
        for k in range(40):  # 40 frames: the 4-bit and 8-bit sent values wrap or not
            frame = _encode(tx, kind, node, 10.0 + k, k % 16)
            d = decode_frame(rx, frame_id(kind, node), frame, T0 + k)
            assert isinstance(d, Decoded), (node, k, d)
            assert (d.kind, d.node, d.counter) == (kind, node, k % 16)
            assert d.value == pytest.approx(10.0 + k)
            assert d.raw["FreshnessValue"] == (k + 1) % (256 if kind == "current" else 16)
        assert tx.secoc is not None and rx.secoc is not None
        assert tx.secoc.tx_freshness((kind, node)) == rx.secoc.rx_freshness((kind, node)) == 40


def test_streams_and_keys_are_separate(pair: tuple[MotorDatabase, MotorDatabase]) -> None:
    tx, rx = pair
    frame = tx.encode_current(2, 5.0, 0)
    sync = tx.encode_sync(2, "current")
    # another key: bad MAC (not even the sync verifies: that stream stays unsynced)
    other = load_database(secoc_key=OTHER_KEY)
    assert _reason(decode_frame(other, 0x1F2, sync)) is RejectReason.BAD_MAC
    assert _reason(decode_frame(other, 0x112, frame)) is RejectReason.UNSYNCED
    assert _reason(decode_frame(_synced(other), 0x112, frame)) is RejectReason.BAD_MAC
    # the same key, AES-256 length: another key too
    assert _reason(decode_frame(_synced(load_database(secoc_key=KEY + KEY)), 0x112, frame)) is \
        RejectReason.BAD_MAC
    # a frame of node 2 is not valid for node 3 (data ID in the MAC; CRC also catches it)
    assert _reason(decode_frame(rx, 0x113, frame)) is RejectReason.BAD_CRC
    assert isinstance(decode_frame(rx, 0x112, frame), Decoded)
    assert rx.secoc is not None and rx.secoc.rx_freshness(("current", 3)) == 0


def test_keyless_monitor_decodes_signed_frames_and_unsigned_are_the_old_frames() -> None:
    tx = load_database(secoc_key=KEY)
    plain = load_database()
    assert not plain.secoc_enabled and plain.secoc is None
    frame = tx.encode_voltage(1, 100.0, 3)
    for _ in range(3):  # no key, no freshness state: replays are left to the counters
        d = decode_frame(plain, 0x121, frame)
        assert isinstance(d, Decoded) and d.value == 100.0
    unsigned = plain.encode_current(1, -7.5, 2)
    assert unsigned[4:] == bytes(4)
    assert load_database().encode_current(1, -7.5, 2) == unsigned


def test_keyed_monitor_rejects_unsigned_frames() -> None:
    rx = load_database(secoc_key=KEY)
    plain = load_database()
    for kind in SECOC_KINDS:  # not synchronised yet: nothing to verify against
        r = decode_frame(rx, frame_id(kind, 0), _encode(plain, kind, 0, 1.0, 0))
        assert isinstance(r, Rejected) and r.reason is RejectReason.UNSYNCED
    _synced(rx)
    for kind in SECOC_KINDS:
        r = decode_frame(rx, frame_id(kind, 0), _encode(plain, kind, 0, 1.0, 0))
        assert isinstance(r, Rejected) and r.reason is RejectReason.BAD_MAC
        assert (r.kind, r.node) == (kind, 0) and "\n" not in r.detail
    # frames SecOC does not cover still decode
    assert isinstance(decode_frame(rx, 0x7E0, plain.encode_truth(0, 0.5, 1.0, 2.0)), Decoded)
    assert isinstance(decode_frame(rx, 0x180, plain.encode_diagnosis(0, 1, 0.5, 10.0, 3, 0)),
                      Decoded)


# ----------------------------------------------------------------------------- attacks


@pytest.mark.parametrize("kind", SECOC_KINDS)
def test_forged_frame_is_bad_mac(pair: tuple[MotorDatabase, MotorDatabase], kind: Kind) -> None:
    tx, rx = pair
    fid = frame_id(kind, 6)
    for k in range(3):
        assert isinstance(decode_frame(rx, fid, _encode(tx, kind, 6, 20.0, k)), Decoded)
    genuine = _encode(tx, kind, 6, 20.0, 3)  # the attacker sees it and races it
    rng = os.urandom
    forged = [
        _forge(tx, kind, 6, genuine, rng(3), value=-99.0),  # changed value, random MAC
        _forge(tx, kind, 6, genuine, rng(3)),  # same content, random MAC
        _forge(tx, kind, 6, genuine, genuine[5:8], value=-99.0),  # MAC of another content
        _forge(tx, kind, 6, genuine, bytes(3)),  # unsigned
    ]
    for frame in forged:
        if frame[5:8] == genuine[5:8] and frame[2:5] == genuine[2:5]:
            continue  # 2^-24: the random MAC happened to be right
        r = decode_frame(rx, fid, frame)
        assert isinstance(r, Rejected), frame.hex()
        assert r.reason is RejectReason.BAD_MAC, r
    assert rx.secoc is not None and rx.secoc.rx_freshness((kind, 6)) == 3
    d = decode_frame(rx, fid, genuine)  # the forgeries consumed nothing
    assert isinstance(d, Decoded) and d.value == 20.0


@pytest.mark.parametrize("kind", SECOC_KINDS)
def test_replayed_frame_is_stale_freshness(pair: tuple[MotorDatabase, MotorDatabase],
                                           kind: Kind) -> None:
    tx, rx = pair
    fid = frame_id(kind, 11)
    sent = [_encode(tx, kind, 11, float(k), k % 16) for k in range(80)]
    for frame in sent[:70]:
        assert isinstance(decode_frame(rx, fid, frame), Decoded)
    # the last one again, and older ones within the window: authentic but not fresh
    for old in (69, 68, 60, 50, 7):
        r = decode_frame(rx, fid, sent[old])
        assert isinstance(r, Rejected), old
        assert r.reason is RejectReason.STALE_FRESHNESS, (old, r)
        assert "replay" in r.detail
    # a replay from too long ago cannot even be placed: it does not verify at all
    r = decode_frame(rx, fid, sent[2])
    assert isinstance(r, Rejected) and r.reason is RejectReason.BAD_MAC
    # the stream goes on
    for frame in sent[70:]:
        assert isinstance(decode_frame(rx, fid, frame), Decoded)


@pytest.mark.parametrize("kind", SECOC_KINDS)
def test_gaps_within_the_window_are_accepted(pair: tuple[MotorDatabase, MotorDatabase],
                                             kind: Kind) -> None:
    tx, rx = pair
    fid = frame_id(kind, 4)
    assert isinstance(decode_frame(rx, fid, _encode(tx, kind, 4, 1.0, 0)), Decoded)
    for gap in (1, 15, 16, 17, 31, 32, 33, DEFAULT_WINDOW - 1):  # frames lost in between
        for _ in range(gap):
            _encode(tx, kind, 4, 1.0, 0)
        before = rx.secoc.rx_freshness((kind, 4))  # type: ignore[union-attr]
        d = decode_frame(rx, fid, _encode(tx, kind, 4, 2.0, 0))
        assert isinstance(d, Decoded), (gap, d)
        assert rx.secoc.rx_freshness((kind, 4)) == before + gap + 1  # type: ignore[union-attr]


@pytest.mark.parametrize("kind", SECOC_KINDS)
def test_freshness_beyond_the_window_is_rejected(pair: tuple[MotorDatabase, MotorDatabase],
                                                 kind: Kind) -> None:
    tx, rx = pair
    fid = frame_id(kind, 8)
    assert isinstance(decode_frame(rx, fid, _encode(tx, kind, 8, 1.0, 0)), Decoded)  # fresh 1
    for _ in range(DEFAULT_WINDOW):  # 64 lost: the next one is 65 ahead
        _encode(tx, kind, 8, 1.0, 0)
    frame = _encode(tx, kind, 8, 1.0, 0)
    r = decode_frame(rx, fid, frame)
    assert isinstance(r, Rejected)
    assert r.reason in (RejectReason.STALE_FRESHNESS, RejectReason.BAD_MAC)
    if kind == "current":  # 8 bits place it exactly: authentic, but too far ahead
        assert r.reason is RejectReason.STALE_FRESHNESS and "beyond the window" in r.detail
    # far ahead (an authentic frame from the sender's future, e.g. recorded on another
    # monitor after a restart): rejected
    assert tx.secoc is not None and rx.secoc is not None
    tx.secoc.set_tx_freshness((kind, 8), 5000)
    far = _encode(tx, kind, 8, 1.0, 0)
    assert isinstance(decode_frame(rx, fid, far), Rejected)
    assert rx.secoc.rx_freshness((kind, 8)) == 1
    # resynchronised (e.g. from a freshness manager), it is accepted again
    rx.secoc.set_rx_freshness((kind, 8), 5000)
    assert _reason(decode_frame(rx, fid, far)) is None
    assert _reason(decode_frame(rx, fid, far)) is RejectReason.STALE_FRESHNESS


@pytest.mark.parametrize("kind", SECOC_KINDS)
@pytest.mark.parametrize("start", [250, 2**32 - 5, 2**40 - 13])
def test_truncated_freshness_wraps(pair: tuple[MotorDatabase, MotorDatabase], kind: Kind,
                                   start: int) -> None:
    tx, rx = pair
    assert tx.secoc is not None and rx.secoc is not None
    stream = (kind, 13)
    tx.secoc.set_tx_freshness(stream, start)
    rx.secoc.set_rx_freshness(stream, start)
    fid = frame_id(kind, 13)
    modulus = 256 if kind == "current" else 16
    sent_bits = []
    for k in range(40):  # across at least one 8-bit and two 4-bit wraps
        d = decode_frame(rx, fid, _encode(tx, kind, 13, 3.0, k % 16))
        assert isinstance(d, Decoded), (k, d)
        sent_bits.append(int(d.raw["FreshnessValue"]))
    assert sent_bits == [(start + 1 + k) % modulus for k in range(40)]
    assert 0 in sent_bits
    assert rx.secoc.rx_freshness(stream) == start + 40
    # a gap across the wrap, too
    for _ in range(20):
        _encode(tx, kind, 13, 3.0, 0)
    assert isinstance(decode_frame(rx, fid, _encode(tx, kind, 13, 3.0, 0)), Decoded)
    assert rx.secoc.rx_freshness(stream) == start + 61


def test_counter_exhaustion_is_an_error() -> None:
    tx = load_database(secoc_key=KEY)
    assert tx.secoc is not None
    tx.secoc.set_tx_freshness(("current", 0), 2**64 - 1)
    with pytest.raises(CodecError, match="exhausted"):
        tx.encode_current(0, 1.0, 0)
    with pytest.raises(SecOCError):
        tx.secoc.set_rx_freshness(("current", 0), 2**64)


@settings(max_examples=400, deadline=None)
@given(kind=st.sampled_from(SECOC_KINDS), node=st.integers(0, N_NODES - 1),
       data=st.binary(min_size=8, max_size=8))
def test_random_frames_never_verify(kind: Kind, node: int, data: bytes) -> None:
    # Random content with a correct CRC and no reserved bit set reaches the MAC check;
    # a random 24-bit MAC passes with probability 2^-24 per candidate (ignored here).
    rx = _synced(_BASE.with_secoc_key(KEY))
    payload = bytearray(data)
    if kind == "current":
        payload[1] &= 0x0F  # MotorCurrent's reserved high nibble
    msg = rx.message(kind, node)
    protected = apply_profile2_crc(bytes(payload), msg)
    assert protected is not None
    r = decode_frame(rx, frame_id(kind, node), bytes(protected))
    assert isinstance(r, Rejected)
    assert r.reason is RejectReason.BAD_MAC


@settings(max_examples=200, deadline=None)
@given(kind=st.sampled_from(SECOC_KINDS), node=st.integers(0, N_NODES - 1),
       value=st.floats(-300, 300), mac=st.binary(min_size=3, max_size=3))
def test_changed_payload_with_any_mac_never_verifies(kind: Kind, node: int, value: float,
                                                     mac: bytes) -> None:
    tx, rx = _BASE.with_secoc_key(KEY), _synced(_BASE.with_secoc_key(KEY))
    genuine = _encode(tx, kind, node, 1.0, 0)
    forged = _forge(tx, kind, node, genuine, mac, value=value)
    if forged[2:5] == genuine[2:5] and mac == genuine[5:8]:
        return  # the genuine frame itself
    assert _reason(decode_frame(rx, frame_id(kind, node), forged)) is RejectReason.BAD_MAC


# ----------------------------------------------------------------------------- keys


def _key_file(path: Path, content: bytes, mode: int = 0o600) -> Path:
    path.write_bytes(content)
    path.chmod(mode)
    return path


def test_load_key_formats(tmp_path: Path) -> None:
    assert load_key(_key_file(tmp_path / "a", KEY.hex().encode())) == KEY
    assert load_key(_key_file(tmp_path / "b", KEY.hex().upper().encode() + b"\n")) == KEY
    assert load_key(_key_file(tmp_path / "c", b"  " + (KEY + KEY).hex().encode() + b"\r\n")) \
        == KEY + KEY
    assert load_key(_key_file(tmp_path / "d", KEY)) == KEY  # raw AES-128
    raw256 = bytes(range(200, 232))
    assert load_key(_key_file(tmp_path / "e", raw256)) == raw256  # raw AES-256
    assert load_key(str(tmp_path / "a")) == KEY
    assert parse_key(b"00" * 16) == bytes(16)


def test_load_key_permissions(tmp_path: Path) -> None:
    path = _key_file(tmp_path / "key", KEY.hex().encode(), 0o644)
    with pytest.raises(SecOCError) as info:
        load_key(path)
    text = str(info.value)
    assert "\n" not in text and "0644" in text and "chmod 600" in text
    assert KEY.hex() not in text
    assert isinstance(info.value, ValueError)
    for mode in (0o640, 0o604, 0o620, 0o660, 0o601, 0o610):
        path.chmod(mode)
        with pytest.raises(SecOCError, match="group or others"):
            load_key(path)
    path.chmod(0o644)
    assert load_key(path, allow_insecure=True) == KEY
    for mode in (0o600, 0o400, 0o700):
        path.chmod(mode)
        assert load_key(path) == KEY
    assert stat.S_IMODE(path.stat().st_mode) == 0o700


@pytest.mark.parametrize(
    "content",
    [b"", b"\n", b"00" * 15, b"00" * 16 + b"0", b"00" * 24, b"zz" * 16,
     b"00" * 15 + b"0g", b"00" * 8 + b"\n", bytes(15), bytes(20), bytes(33), b"00" * 64],
    ids=["empty", "newline", "30hex", "33hex", "48hex", "nonhex", "typo", "16text", "raw15",
         "raw20", "raw33", "128hex"],
)
def test_load_key_wrong_length(tmp_path: Path, content: bytes) -> None:
    with pytest.raises(SecOCError, match="not an AES key") as info:
        load_key(_key_file(tmp_path / "key", content))
    assert "\n" not in str(info.value) and str(tmp_path / "key") in str(info.value)


def test_load_key_missing_or_not_a_file(tmp_path: Path) -> None:
    with pytest.raises(SecOCError, match="key file not found") as info:
        load_key(tmp_path / "nope")
    assert "\n" not in str(info.value)
    with pytest.raises(SecOCError, match="not a regular file"):
        load_key(tmp_path)
    big = _key_file(tmp_path / "big", b"0" * 100_000)
    with pytest.raises(SecOCError, match=r"big: is 97\.7 KiB, more than the 4 KiB"):
        load_key(big)


def test_database_and_ecu_key_errors_are_one_line(tmp_path: Path) -> None:
    with pytest.raises(CodecError, match="16 or 32 bytes") as info:
        load_database(secoc_key=b"short")
    assert "\n" not in str(info.value)
    with pytest.raises(ECUError, match="16 or 32 bytes"):
        VirtualECU(None, load_database(), 0, load_scenario("healthy"), key=bytes(8))
    # an older DBC without the SecOC signals (and sync frames) loads, but cannot
    # authenticate
    no_sync = _without_sync_frames(REPO_DBC.read_text())
    old = "\n".join(line for line in no_sync.splitlines()
                    if "FreshnessValue" not in line and "Authenticator" not in line)
    path = tmp_path / "old.dbc"
    path.write_text(old + "\n")
    plain = load_database(path)
    assert plain.secoc_layout("current", 0) is None
    with pytest.raises(CodecError, match="cannot authenticate") as info:
        load_database(path, secoc_key=KEY)
    assert "\n" not in str(info.value)
    with pytest.raises(CodecError, match="cannot authenticate"):
        plain.with_secoc_key(KEY)
    # the SecOC signals without the sync frames: loads, but a key needs the syncs
    path.write_text(no_sync)
    plain = load_database(path)
    assert plain.secoc_layout("current", 0) is not None
    with pytest.raises(CodecError, match="cannot resynchronise") as info:
        load_database(path, secoc_key=KEY)
    assert "\n" not in str(info.value)
    # half of them missing is a broken DBC
    half = re.sub(r"BO_ 511 SecOCSync_N15: 8 MotorECU\n( SG_ .*\n)+", "",
                  REPO_DBC.read_text())
    path.write_text("\n".join(ln for ln in half.splitlines()
                              if not re.search(r"(BO_|SG_|VAL_) 511 ", ln)) + "\n")
    with pytest.raises(CodecError, match="missing message SecOCSync_N15"):
        load_database(path)


def _without_sync_frames(text: str) -> str:
    """The DBC as it was before the SecOCSync messages (0x1F0..0x1FF)."""
    text = re.sub(r"BO_ (49[6-9]|50\d|51[01]) SecOCSync_N\d+: 8 MotorECU\n( SG_ .*\n)+\n?",
                  "", text)
    return "\n".join(ln for ln in text.splitlines()
                     if not re.search(r"(BO_|SG_|VAL_) (49[6-9]|50\d|51[01]) ", ln)) + "\n"


@pytest.mark.parametrize(
    ("old", "new", "what"),
    [
        ('BA_ "SecOCDataID" BO_ 273 273;', 'BA_ "SecOCDataID" BO_ 273 274;',
         "SecOCDataID must be 273"),
        ('BA_ "SecOCFreshnessValueLength" BO_ 290 64;',
         'BA_ "SecOCFreshnessValueLength" BO_ 290 12;', "multiple of 8"),
        (' SG_ Authenticator : 40|24@1+ (1,0) [0|16777215] "" Monitor\n\nBO_ 289',
         ' SG_ Authenticator : 40|16@1+ (1,0) [0|65535] "" Monitor\n\nBO_ 289',
         "end of the frame"),
    ],
)
def test_inconsistent_secoc_dbc(tmp_path: Path, old: str, new: str, what: str) -> None:
    with pytest.raises(CodecError, match=what):
        load_database(edited_dbc(tmp_path, old, new))


def test_layout_refuses_a_trailer_that_is_not_one_byte() -> None:
    db = load_database()
    msg = db.message("current", 0)
    assert SecOCLayout.from_message(msg).trailer
    assert SecOCLayout.from_message(db.message("voltage", 0)).payload_length == 5
    with pytest.raises(SecOCError, match="needs signals"):
        SecOCLayout.from_message(db.message("truth", 0))


# ----------------------------------------------------------------------------- ECU, pipeline


def test_virtual_ecu_with_a_key_signs_and_continues_its_counters() -> None:
    scenario = load_scenario("healthy")
    plain = load_database()
    ecu = VirtualECU(None, plain, 3, scenario, seed=1, key=KEY)
    assert ecu.db.secoc_enabled and not plain.secoc_enabled  # its own copy
    rx = load_database(secoc_key=KEY)
    first = list(ecu.frames(0.5))
    second = list(ecu.frames(0.5))  # a fresh run, but freshness goes on
    unsigned = list(VirtualECU(None, plain, 3, scenario, seed=1).frames(0.5))
    for frames in (first, second):
        decoded = [rx.decode_can(m) for m in frames]
        assert all(isinstance(d, Decoded) for d in decoded), decoded[:3]
        # each run starts with one sync per stream, before its first data frame
        assert [d.kind for d in decoded[:3]] == ["sync", "sync", "current"]
        values = [d.value for d in decoded if isinstance(d, Decoded) and d.kind != "sync"]
        assert values == [d.value for d in map(plain.decode_can, unsigned)
                          if isinstance(d, Decoded)]
    assert ecu.db.secoc is not None
    assert ecu.db.secoc.tx_freshness(("current", 3)) == 100
    assert ecu.db.secoc.tx_freshness(("voltage", 3)) == 20
    assert all(isinstance(decode_frame(rx, m.arbitration_id, bytes(m.data)), Rejected)
               for m in first if m.arbitration_id != 0x7E3)  # replays of the first run
    assert not any(m.arbitration_id == 0x1F3 for m in unsigned)  # no key, no syncs


def _current(pipe: MonitorPipeline) -> int:
    return pipe.counters.get("samples/estimated", 0)


def test_pipeline_with_a_key_estimates_and_rejects_forged_and_replayed_frames() -> None:
    scenario = load_scenario("fault-outage-recovery")
    frames = list(VirtualECU(None, load_database(), 0, scenario, seed=3, key=KEY)
                  .frames(start_time=T0))
    reference = MonitorPipeline(load_database(), MonitorConfig())  # keyless: as before
    feed_all(reference, frames)

    pipe = MonitorPipeline(load_database(secoc_key=KEY), MonitorConfig())
    half = len(frames) // 2
    feed_all(pipe, frames[:half])
    estimated = _current(pipe)
    assert estimated > 0
    assert not any(k.startswith("rejected/") for k in pipe.counters)

    last = frames[half - 1]
    currents = [m for m in frames[:half] if m.arbitration_id == 0x110]
    db = _db(pipe)
    injected: list[can.Message] = []
    for i, m in enumerate(currents[-5:]):  # replays, with timestamps that move on
        injected.append(can.Message(arbitration_id=m.arbitration_id, data=bytes(m.data),
                                    is_extended_id=False, timestamp=last.timestamp + 1e-4 * i))
    genuine_next = next(m for m in frames[half:] if m.arbitration_id == 0x110)
    for i in range(5):  # forgeries of the next current frame: -250 A, guessed MACs
        data = _forge(db, "current", 0, bytes(genuine_next.data), os.urandom(3), value=-250.0)
        injected.append(can.Message(arbitration_id=0x110, data=data, is_extended_id=False,
                                    timestamp=last.timestamp + 1e-3 + 1e-4 * i))
    voltage = next(m for m in reversed(frames[:half]) if m.arbitration_id == 0x120)
    injected.append(can.Message(arbitration_id=0x120, data=bytes(voltage.data),
                                is_extended_id=False, timestamp=last.timestamp + 2e-3))
    feed_all(pipe, injected)
    assert pipe.counters["rejected/stale_freshness"] == 6
    assert pipe.counters["rejected/bad_mac"] == 5
    assert _current(pipe) == estimated  # none of them reached the estimator
    assert pipe.counters.get("e2e/repeated", 0) == 0  # stopped before the alive counter

    feed_all(pipe, frames[half:])  # the genuine stream goes on undisturbed
    assert _current(pipe) == _current(reference)
    assert pipe.summary()["nodes"] == reference.summary()["nodes"]
    rejected = {k: v for k, v in pipe.counters.items() if k.startswith("rejected/")}
    assert rejected == {"rejected/stale_freshness": 6, "rejected/bad_mac": 5}


def test_pipeline_with_a_key_rejects_an_unsigned_ecu() -> None:
    frames = list(VirtualECU(None, load_database(), 1, load_scenario("healthy"), seed=2)
                  .frames(1.0, start_time=T0))
    pipe = MonitorPipeline(load_database(secoc_key=KEY), MonitorConfig())
    feed_all(pipe, frames)
    assert _current(pipe) == 0
    # an unsigned ECU sends no sync either: its streams are never synchronised
    assert pipe.counters["rejected/unsynced"] == 100 + 20  # every current and voltage frame
    assert pipe.counters["samples/truth"] == 100  # SimTruth is not authenticated
    _synced(_db(pipe))  # synchronised by hand, its frames are plainly unauthentic
    feed_all(pipe, VirtualECU(None, load_database(), 1, load_scenario("healthy"), seed=2)
                   .frames(1.0, start_time=T0 + 1.0))
    assert _current(pipe) == 0
    assert pipe.counters["rejected/bad_mac"] == 100 + 20


# ----------------------------------------------------------------------------- resynchronisation

SYNC_IDS = range(0x1F0, 0x200)


def _ecu_frames(seconds: float, node: int = 0, seed: int = 5) -> list[can.Message]:
    """A keyed virtual ECU's frames (syncs at sample 0 and every 100 samples)."""
    ecu = VirtualECU(None, load_database(), node, load_scenario("fault-outage-recovery"),
                     seed=seed, key=KEY)
    return list(ecu.frames(seconds, start_time=T0))


def _k(m: can.Message) -> int:
    """The sample index of a virtual-ECU frame (100 Hz, from T0)."""
    return round((m.timestamp - T0) * 100)


def _rejected(pipe: MonitorPipeline) -> dict[str, int]:
    return {k: v for k, v in pipe.counters.items() if k.startswith("rejected/")}


def _keyed_pipe(db: MotorDatabase | None = None) -> MonitorPipeline:
    return MonitorPipeline(db if db is not None else load_database(secoc_key=KEY),
                           MonitorConfig())


def _db(pipe: MonitorPipeline) -> MotorDatabase:
    """The pipeline's decoder: our own bus's database in these tests."""
    assert isinstance(pipe.db, MotorDatabase), pipe.db
    return pipe.db


def _secoc(pipe: MonitorPipeline) -> SecOC:
    """The SecOC state of a keyed pipeline's database."""
    secoc = _db(pipe).secoc
    assert secoc is not None
    return secoc


def _sync_of(frames: list[can.Message], k: int, kind: Kind = "current") -> can.Message:
    index = SECOC_KINDS.index(kind)
    return next(m for m in frames if m.arbitration_id in SYNC_IDS and _k(m) == k
                and m.data[0] & 0xF == index)


def _with_data(m: can.Message, data: bytes, timestamp: float | None = None) -> can.Message:
    return can.Message(arbitration_id=m.arbitration_id, data=data, is_extended_id=False,
                       timestamp=m.timestamp if timestamp is None else timestamp)


def test_sync_frame_bytes_by_hand() -> None:
    tx = load_database(secoc_key=KEY)
    assert tx.secoc is not None
    tx.secoc.set_tx_freshness(("voltage", 9), 0x1_2345_6789)
    frame = tx.encode_sync(9, "voltage")
    assert frame[0] == 1  # SyncKind voltage, reserved nibble 0
    assert int.from_bytes(frame[1:5], "little") == 0x2345_6789  # low 32 bits
    auth_data = (0x1F9).to_bytes(2, "big") + frame[:5] + (0x1_2345_6789).to_bytes(8, "big")
    assert frame[5:8] == aes_cmac(KEY, auth_data)[:3]
    assert tx.secoc.tx_freshness(("voltage", 9)) == 0x1_2345_6789  # a sync consumes nothing
    layout = tx.sync_layout(9)
    assert (layout.data_id, layout.payload_length, layout.kind_start, layout.kind_bits,
            layout.fv_start, layout.fv_bits, layout.auth_start, layout.auth_bytes,
            layout.freshness_bits) == (0x1F9, 5, 0, 4, 8, 32, 5, 3, 64)
    with pytest.raises(CodecError, match="need a SecOC key"):
        load_database().encode_sync(9, "current")
    with pytest.raises(CodecError, match="not 'truth'"):
        tx.encode_sync(9, "truth")
    # without a key a sync frame is a plain sample, ignored by the pipeline
    d = decode_frame(load_database(), 0x1F9, frame)
    assert isinstance(d, Decoded) and (d.kind, d.node, d.counter) == ("sync", 9, None)
    assert d.value == 0x2345_6789 and d.raw["SyncKind"] == 1


def test_sync_sets_freshness_and_never_moves_it_back() -> None:
    tx, rx = load_database(secoc_key=KEY), load_database(secoc_key=KEY)
    assert tx.secoc is not None and rx.secoc is not None
    stream = ("current", 2)
    for _ in range(1000):  # the ECU ran before the monitor started
        tx.encode_current(2, 1.0, 0)
    late = tx.encode_current(2, 1.0, 0)
    r = decode_frame(rx, 0x112, late)
    assert isinstance(r, Rejected) and r.reason is RejectReason.UNSYNCED
    assert "\n" not in r.detail and not rx.secoc.is_synchronised(stream)
    sync = tx.encode_sync(2, "current")  # freshness 1001
    assert isinstance(decode_frame(rx, 0x1F2, sync), Decoded)
    assert rx.secoc.rx_freshness(stream) == 1001 and rx.secoc.is_synchronised(stream)
    assert _reason(decode_frame(rx, 0x112, late)) is RejectReason.STALE_FRESHNESS  # 1001 itself
    assert _reason(decode_frame(rx, 0x112, tx.encode_current(2, 2.0, 1))) is None  # 1002
    assert _reason(decode_frame(rx, 0x1F2, sync)) is RejectReason.STALE_FRESHNESS  # replayed sync
    assert rx.secoc.rx_freshness(stream) == 1002
    now = tx.encode_sync(2, "current")
    assert _reason(decode_frame(rx, 0x1F2, now)) is None  # equal: accepted, changes nothing
    assert _reason(decode_frame(rx, 0x1F2, now)) is None
    assert rx.secoc.rx_freshness(stream) == 1002
    # the other stream of the node is still unsynchronised
    assert _reason(decode_frame(rx, 0x122, tx.encode_voltage(2, 1.0, 0))) is RejectReason.UNSYNCED


def test_forged_syncs_are_bad_mac() -> None:
    tx, rx = load_database(secoc_key=KEY), load_database(secoc_key=KEY)
    assert rx.secoc is not None
    for _ in range(10):
        tx.encode_current(4, 1.0, 0)
    genuine = tx.encode_sync(4, "current")
    assert _reason(decode_frame(rx, 0x1F4, genuine)) is None
    msg = rx.message("sync", 4)

    def forge(kind: int, fresh: int, mac: bytes) -> bytes:
        return bytes(msg.encode({"SyncKind": kind, "SyncFreshness": fresh,
                                 "SyncAuthenticator": int.from_bytes(mac, "little")},
                                scaling=False))

    data_frame = tx.encode_current(4, 1.0, 0)
    forged = [
        forge(0, 2**32 - 1, os.urandom(3)),  # far ahead: would stall the stream
        forge(0, 5000, genuine[5:8]),  # another value under the genuine MAC
        forge(1, 10, genuine[5:8]),  # the genuine sync relabelled as the voltage stream
        forge(0, 10, bytes(3)),  # unsigned
        genuine[:5] + data_frame[5:8],  # a data frame's MAC
    ]
    for frame in forged:
        r = decode_frame(rx, 0x1F4, frame)
        assert isinstance(r, Rejected) and r.reason is RejectReason.BAD_MAC, frame.hex()
        assert (r.kind, r.node) == ("sync", 4) and "\n" not in r.detail
    # a sync of node 4 on node 5's id: the data ID is in the MAC
    assert _reason(decode_frame(rx, 0x1F5, genuine)) is RejectReason.BAD_MAC
    assert rx.secoc.rx_freshness(("current", 4)) == 10  # nothing moved
    assert rx.secoc.rx_freshness(("voltage", 4)) == 0
    assert not rx.secoc.is_synchronised(("voltage", 4))
    # a SyncKind no stream has: out of range, nothing verified; a reserved bit: malformed
    assert _reason(decode_frame(rx, 0x1F4, bytes([2]) + genuine[1:])) is RejectReason.OUT_OF_RANGE
    assert _reason(decode_frame(rx, 0x1F4, bytes([0x10]) + genuine[1:])) is RejectReason.MALFORMED
    assert _reason(decode_frame(rx, 0x114, data_frame)) is None  # the stream goes on


@pytest.mark.parametrize("kind", SECOC_KINDS)
def test_sync_low_bits_wrap(kind: Kind) -> None:
    tx, rx = load_database(secoc_key=KEY), load_database(secoc_key=KEY)
    assert tx.secoc is not None and rx.secoc is not None
    stream, fid, sid = (kind, 6), frame_id(kind, 6), frame_id("sync", 6)
    tx.secoc.set_tx_freshness(stream, 2**32 - 3)
    assert _reason(decode_frame(rx, sid, tx.encode_sync(6, kind))) is None  # fresh: high part 0
    assert rx.secoc.rx_freshness(stream) == 2**32 - 3
    old = tx.encode_sync(6, kind)
    for _ in range(500):  # low 32 bits wrap to 497
        _encode(tx, kind, 6, 1.0, 0)
    wrapped = tx.encode_sync(6, kind)
    assert int.from_bytes(wrapped[1:5], "little") == 497
    assert _reason(decode_frame(rx, sid, wrapped)) is None  # 497 < low part: one more on top
    assert rx.secoc.rx_freshness(stream) == 2**32 + 497
    assert isinstance(decode_frame(rx, fid, _encode(tx, kind, 6, 2.0, 0)), Decoded)
    r = decode_frame(rx, sid, old)  # from before the wrap: resolves into the past, a replay
    assert isinstance(r, Rejected) and r.reason is RejectReason.STALE_FRESHNESS
    assert str(2**32 - 3) in r.detail


def test_nearest_freshness() -> None:
    m = 2**32
    assert nearest_freshness(0, 5, 32) == 5
    assert nearest_freshness(0, m - 1, 32) == m - 1  # nothing below 0
    assert nearest_freshness(7 * m + 10, 20, 32) == 7 * m + 20
    assert nearest_freshness(7 * m + 10, 5, 32) == 7 * m + 5  # older: same high part
    assert nearest_freshness(7 * m + m - 10, 5, 32) == 8 * m + 5  # wrapped
    assert nearest_freshness(8 * m + 5, m - 10, 32) == 7 * m + m - 10  # from before a wrap
    assert nearest_freshness(2**64 - 1, 0, 32) == 2**64 - m  # never beyond 64 bits
    for ref in (0, 1, m // 2, m, 5 * m + 123):
        for delta in (-m // 2, -1, 0, 1, m // 2 - 1):
            if ref + delta >= 0:
                assert nearest_freshness(ref, (ref + delta) % m, 32) == ref + delta


def test_monitor_started_after_500_frames_recovers_at_the_first_sync() -> None:
    frames = _ecu_frames(9.0)
    late = [m for m in frames if _k(m) >= 510]  # the ECU has sent 510 current frames
    pipe = _keyed_pipe()
    before = [m for m in late if _k(m) < 600]  # the next syncs come at sample 600
    feed_all(pipe, before)
    n_data = sum(1 for m in before if m.arbitration_id in (0x110, 0x120))
    assert _rejected(pipe) == {"rejected/unsynced": n_data}
    assert n_data == 90 + 18 and _current(pipe) == 0
    feed_all(pipe, (m for m in late if _k(m) >= 600))
    assert _rejected(pipe) == {"rejected/unsynced": n_data}  # none after the sync
    assert pipe.counters["samples/secoc_sync"] == 2 * 3  # samples 600, 700, 800
    assert _secoc(pipe).rx_freshness(("current", 0)) == 900
    # from the sync on it estimates exactly as a monitor that started there
    reference = _keyed_pipe()
    feed_all(reference, (m for m in frames if _k(m) >= 600))
    assert _current(pipe) == _current(reference) > 250
    assert pipe.summary()["nodes"] == reference.summary()["nodes"]
    # a keyless monitor ignores the syncs and estimates from the start
    plain = MonitorPipeline(load_database(), MonitorConfig())
    feed_all(plain, late)
    assert plain.counters["ignored/secoc_sync"] == 6 and not _rejected(plain)


def test_restart_with_saved_state(tmp_path: Path) -> None:
    frames = _ecu_frames(6.0)
    state = tmp_path / "secoc.state"
    first = _keyed_pipe()
    feed_all(first, (m for m in frames if _k(m) < 250))
    assert not _rejected(first)
    _secoc(first).save_state(state)
    assert _secoc(first).rx_freshness(("current", 0)) == 250

    # a quick restart (20 samples lost): continues at once, before the next sync (300)
    db = load_database(secoc_key=KEY)
    assert db.secoc is not None and db.secoc.load_state(state) == 2
    assert not db.secoc.is_synchronised(("current", 0))
    quick = _keyed_pipe(db)
    feed_all(quick, (m for m in frames if 270 <= _k(m) < 300))
    assert not _rejected(quick) and _current(quick) == 30 - 1  # the first waits for a voltage
    assert db.secoc.is_synchronised(("current", 0))

    # a longer outage (2 s, beyond the window): unsynced until the next sync, then normal
    db = load_database(secoc_key=KEY)
    assert db.secoc is not None and db.secoc.load_state(state) == 2
    slow = _keyed_pipe(db)
    feed_all(slow, (m for m in frames if 450 <= _k(m) < 500))
    # 200 current frames on: unsynced; 40 voltage frames on: still in the window
    assert _rejected(slow) == {"rejected/unsynced": 50} and _current(slow) == 0
    assert slow.counters["samples/input"] == 10
    feed_all(slow, (m for m in frames if _k(m) >= 500))
    assert _rejected(slow) == {"rejected/unsynced": 50}
    assert _current(slow) == 100
    assert db.secoc.rx_freshness(("current", 0)) == 600


def test_replayed_old_sync_after_a_restart_cannot_roll_back(tmp_path: Path) -> None:
    frames = _ecu_frames(5.0)
    old_sync = _sync_of(frames, 100)  # captured by an attacker in the first seconds
    old_current = [m for m in frames if m.arbitration_id == 0x110 and 100 <= _k(m) < 110]
    recent_current = next(m for m in frames if m.arbitration_id == 0x110 and _k(m) == 340)
    state = tmp_path / "state.json"
    first = _keyed_pipe()
    feed_all(first, (m for m in frames if _k(m) < 350))
    _secoc(first).save_state(state)

    db = load_database(secoc_key=KEY)
    assert db.secoc is not None and db.secoc.load_state(state) == 2
    stream = ("current", 0)
    assert db.secoc.rx_freshness(stream) == 350
    t = frames[-1].timestamp + 1.0
    r = db.decode_can(_with_data(old_sync, bytes(old_sync.data), t))
    assert isinstance(r, Rejected) and r.reason is RejectReason.STALE_FRESHNESS
    assert "replayed sync" in r.detail and "350" in r.detail
    assert db.secoc.rx_freshness(stream) == 350  # not rolled back
    for m in old_current:  # the frames after the old sync are still replays
        r = db.decode_can(_with_data(m, bytes(m.data), t))
        assert isinstance(r, Rejected) and r.reason in (RejectReason.STALE_FRESHNESS,
                                                        RejectReason.UNSYNCED), r
    r = db.decode_can(_with_data(recent_current, bytes(recent_current.data), t))
    assert isinstance(r, Rejected) and r.reason is RejectReason.STALE_FRESHNESS  # a replay
    assert db.secoc.rx_freshness(stream) == 350
    # the genuine stream continues within the window, and the replays stay dead
    pipe = _keyed_pipe(db)
    feed_all(pipe, (m for m in frames if _k(m) >= 355))
    assert not _rejected(pipe) and _current(pipe) > 100
    feed_all(pipe, (_with_data(m, bytes(m.data), frames[-1].timestamp + 2.0)
                   for m in [old_sync, *old_current]))
    assert _rejected(pipe) == {"rejected/stale_freshness": 1, "rejected/bad_mac": 10}


def test_without_state_the_first_sync_is_trusted_on_first_use() -> None:
    # The documented limit: a monitor with no state believes the first authentic sync,
    # even an old one replayed; the ECU's next genuine sync moves it past all of them.
    frames = _ecu_frames(3.0)
    old_sync = _sync_of(frames, 100)
    old_current = next(m for m in frames if m.arbitration_id == 0x110 and _k(m) == 100)
    db = load_database(secoc_key=KEY)
    t = frames[-1].timestamp
    assert isinstance(db.decode_can(_with_data(old_sync, bytes(old_sync.data), t)), Decoded)
    assert isinstance(db.decode_can(_with_data(old_current, bytes(old_current.data), t)),
                      Decoded)
    new_sync = _sync_of(frames, 200)
    assert isinstance(db.decode_can(new_sync), Decoded)
    assert _reason(db.decode_can(_with_data(old_sync, bytes(old_sync.data), t))) is \
        RejectReason.STALE_FRESHNESS


def test_more_than_a_window_of_lost_frames_recovers_at_the_next_sync() -> None:
    frames = _ecu_frames(5.0)
    outage = [m for m in frames if 150 <= _k(m) < 250]  # 1 s lost, the sync at 200 too
    assert sum(m.arbitration_id == 0x110 for m in outage) == 100 > DEFAULT_WINDOW
    pipe = _keyed_pipe()
    feed_all(pipe, (m for m in frames if _k(m) < 150 or 250 <= _k(m) < 300))
    # after the gap the current stream is beyond the window until the sync at 300 (its
    # 8 freshness bits place the frames exactly: authentic, but too far ahead)
    rejected = _rejected(pipe)
    assert rejected == {"rejected/stale_freshness": 50}  # samples 250..299
    assert pipe.counters["samples/input"] == 40  # 20 voltage frames lost: in the window
    feed_all(pipe, (m for m in frames if _k(m) >= 300))
    assert _rejected(pipe) == rejected  # recovered at the sync
    assert _secoc(pipe).rx_freshness(("current", 0)) == 500
    assert _current(pipe) == 150 + 200 - 1


# ----------------------------------------------------------------------------- state files


def test_state_round_trip_and_file_mode(tmp_path: Path) -> None:
    tx, rx = load_database(secoc_key=KEY), load_database(secoc_key=KEY)
    assert tx.secoc is not None and rx.secoc is not None
    _sync_all(tx, rx)
    for k in range(70):
        decode_frame(rx, 0x113, tx.encode_current(3, 1.0, k % 16))
    for k in range(5):
        decode_frame(rx, 0x12F, tx.encode_voltage(15, 1.0, k % 16))
    state = rx.secoc.export_state()
    assert state["rx/current/3"] == 70 and state["rx/voltage/15"] == 5
    assert state["rx/current/0"] == 0 and len(state) == 2 * N_NODES
    assert tx.secoc.export_state() == {"tx/current/3": 70, "tx/voltage/15": 5}
    path = tmp_path / "sub" / "secoc.state"
    with pytest.raises(SecOCError, match="cannot save") as info:
        rx.secoc.save_state(path)  # no such directory
    assert "\n" not in str(info.value)
    path.parent.mkdir()
    rx.secoc.save_state(path)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert [p.name for p in path.parent.iterdir()] == ["secoc.state"]  # no temp file left
    again = SecOC(KEY)
    assert again.load_state(path) == 2 * N_NODES
    assert again.export_state() == state
    assert not again.is_synchronised(("current", 3))  # a floor, not a synchronisation
    path.chmod(0o644)  # others may read it (freshness values are public on the bus)
    rx.secoc.save_state(path)  # replaced atomically, owner-only again
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert SecOC(KEY).load_state(tmp_path / "missing") is None  # fresh start
    # the sender's counters, restored past what it may have signed after the save
    tx.secoc.save_state(tmp_path / "tx")
    sender = load_database(secoc_key=KEY)
    assert sender.secoc is not None
    assert sender.secoc.load_state(tmp_path / "tx", tx_margin=1000) == 2
    assert sender.secoc.tx_freshness(("current", 3)) == 1070
    frame = sender.encode_current(3, 1.0, 0)  # 1071: beyond the window...
    assert _reason(decode_frame(rx, 0x113, frame)) is RejectReason.BAD_MAC  # (8 bits can't tell)
    assert _reason(decode_frame(rx, 0x1F3, sender.encode_sync(3, "current"))) is None  # ...synced
    assert _reason(decode_frame(rx, 0x113, sender.encode_current(3, 1.0, 1))) is None


def test_import_state_only_moves_forward() -> None:
    secoc = SecOC(KEY)
    secoc.set_rx_freshness(("current", 1), 500)
    secoc.import_state({"rx/current/1": 400, "rx/voltage/1": 30, "tx/current/1": 9})
    assert secoc.rx_freshness(("current", 1)) == 500 and secoc.is_synchronised(("current", 1))
    assert secoc.rx_freshness(("voltage", 1)) == 30
    assert not secoc.is_synchronised(("voltage", 1))
    assert secoc.tx_freshness(("current", 1)) == 9
    secoc.import_state({"tx/current/1": 5}, tx_margin=2)
    assert secoc.tx_freshness(("current", 1)) == 9
    with pytest.raises(SecOCError, match="bad stream name"):
        secoc.import_state({"rx/current/1": 1, "up/current/1": 2})
    assert secoc.rx_freshness(("current", 1)) == 500  # all or nothing
    for bad in (-1, 2**64, True, 1.5, "7"):
        with pytest.raises(SecOCError, match=r"0\.\.2\^64-1"):
            secoc.import_state({"rx/current/1": bad})  # type: ignore[dict-item]
    with pytest.raises(SecOCError, match="tx_margin"):
        secoc.import_state({}, tx_margin=-1)
    # streams not named (kind, node) are not saved
    secoc.set_rx_freshness("legacy", 3)
    assert "legacy" not in str(secoc.export_state())


@pytest.mark.parametrize(
    ("content", "needle"),
    [
        (b"", "not a SecOC state file"),
        (b"{not json", "not a SecOC state file"),
        (b"\xff\xfe", "not a SecOC state file"),
        (b"[]", "not a SecOC state file"),
        (b'{"format": "something else", "version": 1, "freshness": {}}', "format"),
        (b'{"format": "motor-monitor SecOC freshness state", "version": 9, "freshness": {}}',
         "version 9"),
        (b'{"format": "motor-monitor SecOC freshness state", "version": 1}', "freshness"),
        (b'{"format": "motor-monitor SecOC freshness state", "version": 1,\n'
         b' "freshness": {"rx/current/0": -5}}', "rx/current/0 must be"),
        (b'{"format": "motor-monitor SecOC freshness state", "version": 1,\n'
         b' "freshness": {"rx/current": 5}}', "bad stream name"),
        (b'{"format": "motor-monitor SecOC freshness state", "version": 1,\n'
         b' "freshness": {"rx/current/0": 1e3}}', "must be an int"),
    ],
    ids=["empty", "json", "utf8", "list", "format", "version", "no-freshness", "negative",
         "name", "float"],
)
def test_malformed_state_file_is_one_line(tmp_path: Path, content: bytes, needle: str) -> None:
    path = tmp_path / "state"
    path.write_bytes(content)
    path.chmod(0o600)
    secoc = SecOC(KEY)
    with pytest.raises(SecOCError, match=needle) as info:
        secoc.load_state(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)
    assert secoc.export_state() == {}  # nothing restored


def test_state_file_permissions_and_type(tmp_path: Path) -> None:
    secoc = SecOC(KEY)
    secoc.set_rx_freshness(("current", 0), 7)
    path = tmp_path / "state"
    secoc.save_state(path)
    for mode in (0o620, 0o602, 0o666):
        path.chmod(mode)
        with pytest.raises(SecOCError, match="writable by group or others") as info:
            SecOC(KEY).load_state(path)
        assert "\n" not in str(info.value) and "chmod 600" in str(info.value)
    path.chmod(0o644)  # readable is fine: freshness values are no secret
    assert SecOC(KEY).load_state(path) == 1
    with pytest.raises(SecOCError, match="not a regular file"):
        SecOC(KEY).load_state(tmp_path)
