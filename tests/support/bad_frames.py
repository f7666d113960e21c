"""The bad frames of the robustness boot A: what is sent, and which daemon counters must
count it (`frame_kinds`), checked offline against the pipeline (`check_kinds_offline`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from cantools.autosar.end_to_end import apply_profile2_crc

from monitor.bus.codec import Decoded, Kind, MotorDatabase, RejectReason
from monitor.pipeline import MonitorConfig, MonitorPipeline
from tests.support.candump import Frame

__all__ = ["NODE", "OTHER", "PER_KIND", "FrameKind", "check_kinds_offline", "frame_kinds"]

NODE = 0  # the monitored node
OTHER = 1  # a node the daemon is told not to monitor
PER_KIND = 20  # frames of each bad kind


@dataclass(frozen=True)
class FrameKind:
    """A kind of bad frame: what is sent, and which daemon counters must count it.

    `expect` maps a counter to its increase per frame sent; every other counter of
    `tests.support.rrd.BAD_OUTCOMES` must not move. `reason` says why the daemon must not
    use the frame.
    """

    key: str  # [a-z_]+, used in the guest script's marks
    title: str
    frames: tuple[Frame, ...]
    expect: Mapping[str, int]
    reason: str = ""


def _current(mdb: MotorDatabase, node: int, amps: float, counter: int) -> bytes:
    return mdb.encode_current(node, amps, counter)


def _with_crc(mdb: MotorDatabase, kind: Kind, node: int, payload: bytes) -> bytes:
    protected = apply_profile2_crc(payload, mdb.message(kind, node))
    assert protected is not None
    return bytes(protected)


def _decode(mdb: MotorDatabase, f: Frame) -> Decoded | RejectReason:
    r = mdb.decode_can(f.message(0.0))
    return r if isinstance(r, Decoded) else r.reason


def _out_of_range(mdb: MotorDatabase, counter: int) -> Frame:
    """A frame with a valid CRC whose physical value lies beyond its DBC range."""
    candidates: list[tuple[Kind, str]] = [("current", "ArmatureCurrent"), ("truth", "TrueGamma")]
    for kind, name in candidates:
        msg = mdb.message(kind, NODE)
        sig = msg.get_signal_by_name(name)
        assert sig.maximum is not None
        values: dict[str, float] = {s.name: 0 for s in msg.signals}
        values[name] = float(sig.maximum) + 10.0 * float(sig.scale)
        if "Counter" in values:
            values["Counter"] = counter
        try:
            payload = bytes(msg.encode(values, scaling=True, padding=False, strict=False))
        except Exception:  # the raw field cannot carry it: try the next candidate
            continue
        if kind != "truth":
            payload = _with_crc(mdb, kind, NODE, payload)
        f = Frame(msg.frame_id, payload)
        if _decode(mdb, f) == RejectReason.OUT_OF_RANGE:
            return f
    raise AssertionError("no out-of-range frame can be built from this DBC")


def _malformed(mdb: MotorDatabase, counter: int) -> Frame:
    """A frame with a valid CRC and a reserved (unused) bit set."""
    valid: list[tuple[Kind, bytes]] = [
        ("truth", mdb.encode_truth(NODE, 0.5, 123.45, 100.0)),
        ("diagnosis", mdb.encode_diagnosis(NODE, "fault_free", 0.0, 0.0, 2, counter)),
        ("current", _current(mdb, NODE, 123.45, counter)),
    ]
    for kind, payload in valid:
        for bit in range(63, 7, -1):
            data = bytearray(payload)
            data[bit // 8] ^= 1 << (bit % 8)
            raw = bytes(data) if kind == "truth" else _with_crc(mdb, kind, NODE, bytes(data))
            f = Frame(mdb.frame_id(kind, NODE), raw)
            if _decode(mdb, f) == RejectReason.MALFORMED:
                return f
    raise AssertionError("no frame with a reserved bit can be built from this DBC")


def frame_kinds(mdb: MotorDatabase, n: int = PER_KIND) -> list[FrameKind]:
    """The bad frames of boot A, built on the host with our codec (values distinct from the
    healthy ECU's ~68 A, so a frame that reached the estimator would show)."""
    cur_id = mdb.frame_id("current", NODE)
    amps = 123.45
    valid = [_current(mdb, NODE, amps, k % 16) for k in range(n)]

    def flip(p: bytes) -> bytes:
        d = bytearray(p)
        d[2] ^= 0x01  # the low byte of the current: CRC no longer matches
        return bytes(d)

    unknown = [0x555, 0x000, 0x7FF, 0x130, 0x17F, 0x190, 0x7DF, 0x7F0]
    errors = {
        "bus_off": Frame(0x040, bytes(8), error=True),
        "controller/rx_overflow": Frame(0x004, bytes([0, 0x01, 0, 0, 0, 0, 0, 0]), error=True),
        "controller/rx_error_passive": Frame(0x004, bytes([0, 0x10, 0, 0, 0, 0, 0, 0]),
                                             error=True),
    }
    kinds = [
        FrameKind("unknown_id", "unknown ID", tuple(
            Frame(unknown[k % len(unknown)], bytes(range(k, k + 8))) for k in range(n)),
            {"rejected/unknown_id": 1}, "not in the DBC"),
        FrameKind("wrong_length", "wrong length (node 0 current, 4 bytes)", tuple(
            Frame(cur_id, p[:4]) for p in valid), {"rejected/wrong_length": 1}),
        FrameKind("bad_crc", "bad CRC (a valid frame with one bit flipped)", tuple(
            Frame(cur_id, flip(p)) for p in valid), {"rejected/bad_crc": 1}),
        FrameKind("out_of_range", "out of range (valid CRC, value beyond the DBC range)", tuple(
            _out_of_range(mdb, k % 16) for k in range(n)), {"rejected/out_of_range": 1}),
        FrameKind("malformed", "malformed (valid CRC, reserved bit set)", tuple(
            _malformed(mdb, k % 16) for k in range(n)), {"rejected/malformed": 1}),
        FrameKind("remote", "remote frame (node 0 current ID)", tuple(
            Frame(cur_id, remote=True, dlc=8) for _ in range(n)), {"rejected/remote_frame": 1}),
        FrameKind("extended", "extended ID (node 0 current ID and payload)", tuple(
            Frame(cur_id, p, extended=True) for p in valid), {"rejected/extended_id": 1}),
        FrameKind("masquerade", "spoofed: node 0's valid frame under node 1's ID", tuple(
            Frame(mdb.frame_id("current", OTHER), p) for p in valid), {"rejected/bad_crc": 1}),
        FrameKind("other_node", "spoofed: valid frame of an unmonitored node (1)", tuple(
            Frame(mdb.frame_id("current", OTHER), _current(mdb, OTHER, amps, k % 16))
            for k in range(n)), {"ignored/node": 1}),
        FrameKind("fake_diagnosis", "spoofed: another monitor's MonitorDiagnosis (outage)",
                  tuple(Frame(mdb.frame_id("diagnosis", NODE),
                              mdb.encode_diagnosis(NODE, "outage", 1.0, 220.0, 9, k % 16))
                        for k in range(n)), {"ignored/diagnosis": 1}),
    ]
    for name, frame in errors.items():
        kinds.append(FrameKind(
            "err_" + name.split("/")[-1], f"error frame: {name}", (frame,) * max(1, n // 2),
            {"bus/error_frames": 1, f"bus/errors/{name}": 1}))
    return kinds


def check_kinds_offline(mdb: MotorDatabase,
                        kinds: Sequence[FrameKind]) -> dict[str, dict[str, int]]:
    """Feed each kind to a fresh pipeline (nodes=(0,)) after a valid voltage: the counters
    each moves. Used to check the frames are built as intended before any vcan run."""
    out: dict[str, dict[str, int]] = {}
    for kind in kinds:
        pipe = MonitorPipeline(mdb, MonitorConfig(nodes=(NODE,)))
        pipe.feed(Frame(mdb.frame_id("voltage", NODE), mdb.encode_voltage(NODE, 220.0, 0))
                  .message(1.0))
        before = dict(pipe.counters)
        for i, f in enumerate(kind.frames):  # one at a time: the pipeline has no feed_many
            pipe.feed(f.message(2.0 + 0.01 * i))
        out[kind.key] = {k: v - before.get(k, 0) for k, v in pipe.counters.items()
                         if v != before.get(k, 0)}
    return out
