"""The columnar BLF reader (`monitor.columnar.blf`) against python-can's `BLFReader`, the
reader of the per-frame path: on files python-can writes (compressed and not, objects cut
across containers), on hand-built objects python-can's writer never makes (CAN_FD_MESSAGE_64
with and without an extended-data offset, object header version 2, 10-us timestamps, an
unknown object type), and on damaged files (hypothesis: truncated, bytes overwritten, an
unknown header version) the two give the same frames, timestamps bit for bit, and the same
error line."""

from __future__ import annotations

import struct
import tempfile
import zlib
from pathlib import Path

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from monitor.columnar import read_chunks
from monitor.jit import JIT_DISABLED
from tests.support.log_readers import columnar, per_frame, random_frames

pytestmark = pytest.mark.skipif(JIT_DISABLED, reason="the scanner runs compiled only")

def _write_python_can(frames: list[can.Message], path: Path, compression: int) -> Path:
    with can.BLFWriter(str(path), compression_level=compression) as writer:
        for m in frames:
            writer.on_message_received(m)
    return path


@pytest.mark.parametrize("compression", [0, 6])
@pytest.mark.parametrize("chunk_frames", [777, 1 << 18])
def test_files_python_can_writes_read_the_same(tmp_path: Path, compression: int,
                                               chunk_frames: int) -> None:
    path = _write_python_can(random_frames(20_000, compression), tmp_path / "x.blf",
                             compression)
    want = per_frame(path)
    assert want[1] is None and len(want[0]) == 20_000
    got = columnar(path, chunk_frames)
    assert got == want
    if chunk_frames == 777:  # chunks of about the size asked for, every frame once
        sizes = [len(c) for c in read_chunks(path, chunk_frames)]
        assert sum(sizes) == 20_000 and max(sizes) < 20_000


# -- hand-built objects -------------------------------------------------------------------

def _header_v1(flags: int, stamp: int) -> bytes:
    return struct.pack("<LHHQ", flags, 0, 0, stamp)


def _header_v2(flags: int, stamp: int) -> bytes:
    return struct.pack("<LBxHQ8x", flags, 0, 0, stamp)


def _object(obj_type: int, body: bytes, *, version: int = 1, flags: int = 2,
            stamp: int = 0) -> bytes:
    head = _header_v1(flags, stamp) if version == 1 else _header_v2(flags, stamp)
    size = 16 + len(head) + len(body)
    return (struct.pack("<4sHHLL", b"LOBJ", 16 + len(head), version, size, obj_type) + head
            + body + bytes(size % 4))


def _fd64(can_id: int, payload: bytes, fd_flags: int, *, valid: int | None = None,
          ext_offset: int = 0) -> bytes:
    valid = len(payload) if valid is None else valid
    return struct.pack("<BBBBLLLLLLLHBBL", 1, 15, valid, 0, can_id, 0, fd_flags, 0, 0, 0, 0,
                       0, 0, ext_offset, 0) + payload


def _file(path: Path, inner: bytes, *, compress: bool, container: int = 1000) -> Path:
    """A BLF file: python-can's file header, then `inner` in containers of `container`
    bytes (objects cut across them)."""
    with can.BLFWriter(str(path)) as writer:
        writer.on_message_received(can.Message(timestamp=1.7e9, arbitration_id=1))
    header = path.read_bytes()[:144]
    out = [header]
    for k in range(0, len(inner), container):
        part = inner[k:k + container]
        data = zlib.compress(part) if compress else part
        size = 16 + 16 + len(data)
        out.append(struct.pack("<4sHHLL", b"LOBJ", 16, 1, size, 10)
                   + struct.pack("<H6xL4x", 2 if compress else 0, len(part)) + data
                   + bytes(size % 4))
    path.write_bytes(b"".join(out))
    return path


def _hand_built() -> bytes:
    objs = []
    for k in range(300):
        payload = bytes((k + j) & 0xFF for j in range(k % 65))
        objs.append(_object(101, _fd64(0x80000000 | (0x1234 + k), payload,
                                       0x1000 | (0x2000 if k % 2 else 0)
                                       | (0x4000 if k % 7 == 0 else 0)),
                            stamp=1_000_000 * k + 3))
        objs.append(_object(1, struct.pack("<HBBL8s", 1, 0, k % 9, 0x100 + k,
                                           bytes(range(8))),
                            version=2, flags=1, stamp=100 * k + 7))  # v2, 10 us
        objs.append(_object(86, struct.pack("<HBBL8s", 1, 0x80, 4, 0x200, bytes(8)),
                            stamp=5 * k))  # CAN_MESSAGE2, remote
        objs.append(_object(101, _fd64(0x400 + k, bytes(range(8)), 0x0010),
                            stamp=5 * k + 1))  # CAN_FD_MESSAGE_64, remote (no data)
        objs.append(_object(96, bytes(40), stamp=k))  # a global marker: skipped
    # CAN_FD_MESSAGE_64 whose data field ends at its extended-data offset (zero-padded to
    # its valid bytes, python-can issue 1905), and one claiming more bytes than it holds
    objs.append(_object(101, _fd64(0x300, bytes(range(1, 9)), 0x1000, valid=16,
                                   ext_offset=16 + 16 + 40 + 8)))
    objs.append(_object(101, _fd64(0x301, bytes(range(1, 5)), 0x1000, valid=12)))
    return b"".join(objs)


@pytest.mark.parametrize("compress", [False, True])
def test_hand_built_objects_read_the_same(tmp_path: Path, compress: bool) -> None:
    path = _file(tmp_path / "x.blf", _hand_built(), compress=compress)
    want = per_frame(path)
    assert want[1] is None and len(want[0]) == 1202, want[1]
    assert any(f[5] and len(f[8]) == 64 for f in want[0])  # FD 64-byte frames among them
    assert columnar(path) == want


# -- damaged files ------------------------------------------------------------------------

_BASE: dict[bool, bytes] = {}


def _base(compress: bool) -> bytes:
    if compress not in _BASE:
        with tempfile.TemporaryDirectory() as td:
            frames = random_frames(3000, 7)
            p = _write_python_can(frames, Path(td) / "b.blf", 6 if compress else 0)
            _BASE[compress] = p.read_bytes()
    return _BASE[compress]


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(compress=st.booleans(), cut=st.floats(0.0, 1.0), where=st.floats(0.0, 1.0),
       junk=st.binary(min_size=1, max_size=24), how=st.sampled_from(["cut", "overwrite",
                                                                       "version"]))
def test_damaged_files_give_the_same_frames_and_error(compress: bool, cut: float,
                                                      where: float, junk: bytes,
                                                      how: str) -> None:
    data = bytearray(_base(compress))
    if how == "cut":
        data = data[:int(144 + cut * (len(data) - 144))]
    elif how == "overwrite":
        at = int(144 + where * (len(data) - 144 - len(junk)))
        data[at:at + len(junk)] = junk
    else:  # an unknown object header version inside an uncompressed container
        first = data.find(b"LOBJ", 144 + 32 + int(where * 1000))
        if first > 0:
            data[first + 6] = 9
    with tempfile.TemporaryDirectory() as td:
        path = Path(td) / "d.blf"
        path.write_bytes(bytes(data))
        assert columnar(path, 500) == per_frame(path)
