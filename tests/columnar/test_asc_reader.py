"""The columnar ASC reader (`monitor.columnar.asc`) against python-can's `ASCReader`, the
reader of the per-frame path: on files python-can writes (classic and CAN FD frames, error
and remote frames), on hand-written lines python-can's writer never makes (other bases,
CRLF, comments, statistics and J1939 lines, symbolic names, odd fields), and on damaged
files (hypothesis: cut, overwritten with the characters ASC lines are made of) the two give
the same frames, timestamps bit for bit, and the same error line."""

from __future__ import annotations

import random
import tempfile
from pathlib import Path

import can
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from monitor.columnar.asc import _header, _scan_asc
from monitor.columnar.chunk import empty_chunk
from monitor.jit import JIT_DISABLED
from tests.support.log_readers import columnar, per_frame, random_frames, write_log

pytestmark = pytest.mark.skipif(JIT_DISABLED, reason="the scanner runs compiled only")


def _data_frames(n: int, seed: int) -> list[can.Message]:
    """Classic and FD data frames only: the lines the scanner takes itself."""
    rng = random.Random(seed)
    return [m for m in random_frames(n, seed)
            if not (m.is_error_frame or m.is_remote_frame)
            and (m.is_fd or rng.random() < 0.9)]


@pytest.mark.parametrize("seed", [1, 2])
@pytest.mark.parametrize("chunk_frames", [100, 1 << 18])
def test_files_python_can_writes_read_the_same(tmp_path: Path, seed: int,
                                               chunk_frames: int) -> None:
    for name, frames in (("mixed", random_frames(2000, seed)),
                         ("data", _data_frames(2000, seed))):
        path = write_log(tmp_path / f"{name}.asc", frames)
        rows, error = columnar(path, chunk_frames)
        assert error is None
        assert (rows, error) == per_frame(path)
        assert len(rows) == len(frames)


def test_the_scanner_itself_takes_python_cans_data_lines(tmp_path: Path) -> None:
    """The comparison above would pass on python-can alone: here the scanner reads the body
    of a file of data frames without handing it over."""
    frames = _data_frames(3000, 5)
    raw = write_log(tmp_path / "d.asc", frames).read_bytes()
    header = _header(raw)
    assert header is not None and header[0] == "hex"
    body = np.frombuffer(raw[header[1]:], np.uint8)
    c = empty_chunk(len(frames) + 10, 64)
    assert c.bitrate_switch is not None and c.error_state_indicator is not None
    n = _scan_asc(body, 16, c.t, c.arbitration_id, c.extended, c.remote, c.error, c.length,
                  c.data, c.is_fd, c.bitrate_switch, c.error_state_indicator)
    assert n == len(frames)


_HAND = """date Tue Nov 24 12:00:00.000 2026
base {base}  timestamps absolute
// a comment in the header
internal events logged
// version 13.0.0
Begin Triggerblock Tue Nov 24 12:00:00.000 2026
   0.000000 Start of measurement
   0.001000 1  {id1}             Rx   d 8 {d8} Length = 272000 BitCount = 140 ID = 291
   0.002000 2  {id2}x           Tx   d 2 {d2}
   0.003000 1  Statistic: D 1 R 0 XD 0 XR 0 E 0 O 0 B 0.50%
   0.004000 1  {id1}             rx   D 3 {d2}
   0.005000 CANFD   1 Rx       {id1}  EngineData  1 0 {dlc32} 32 {d32}  0 0 3000 0 0 0 0 0
   0.006000 CANFD   2 Tx       {id2}x                                   0 1 0  0 0 0 0 0 0
   0.007000 1  J1939TP FEE3p 6 0 0 - Rx d 23 A0 0F A6 60 3B D1 B3 FF
   0.008000 1  {id1}             Rx   d {dlc15} {d8}
   0.009000 CANFD
1.5 1 {id1} Rx d 1 00
   0.010000 1  {id1}             Rx   d 1
   0.011000 CANFDX 1 Rx {id1} 1 0 1 1 00
0000000.012000 1  {id1}             Rx   d 1 {d1}
End TriggerBlock
"""


def _hand(base: str) -> str:
    fmt = "{:02X}" if base == "hex" else "{:d}"

    def data(n: int) -> str:
        return " ".join(fmt.format(b) for b in range(250, 250 - n, -1))
    ids = ("123", "1ABCDEF") if base == "hex" else ("291", "28036591")
    return _HAND.format(base=base, id1=ids[0], id2=ids[1], d8=data(8), d2=data(2),
                        d32=data(32), d1=data(1), dlc32="d" if base == "hex" else "13",
                        dlc15="f" if base == "hex" else "15")


@pytest.mark.parametrize("base", ["hex", "dec"])
@pytest.mark.parametrize("newline", ["\n", "\r\n"])
def test_hand_written_lines_read_the_same(tmp_path: Path, base: str, newline: str) -> None:
    path = tmp_path / "h.asc"
    path.write_bytes(_hand(base).replace("\n", newline).encode())
    rows, error = columnar(path)
    assert (rows, error) == per_frame(path)
    assert error is None and len(rows) >= 7, rows


@pytest.mark.parametrize("line", [
    "   0.013000 1  ErrorFrame",  # error frame: python-can reads the block
    "   0.013000 1  123  Rx   r 8",  # remote frame
    "   0.013000 1  123  Rx   d 8 01 02 0x3",  # python's int reads 0x3: python-can fails
    "   0.013000 1  123  Rx",  # nothing after the direction: python-can fails
    "   0.013000 CANFD 1 Rx 123 1 0 9 16 00",  # DLC and length differ: python-can warns
    "   0.013000 1  0x12  Rx   d 1 01",  # an ID python's int reads
    "   0.0130000000000000000001 1  123  Rx   d 1 01",  # more digits than exact
])
def test_lines_left_to_python_can_read_the_same(tmp_path: Path, line: str) -> None:
    path = tmp_path / "o.asc"
    path.write_text(_hand("hex").replace("End TriggerBlock", line + "\nEnd TriggerBlock"))
    assert columnar(path) == per_frame(path)


_BASE: dict[str, bytes] = {}
_ALPHABET: list[int | bytes] = [*b"0123456789ABCDEFabcdefxXrRdD. \t\n\r", b"CANFD", b"ErrorFrame",
                                 b"Rx"]


def _base() -> bytes:
    if "b" not in _BASE:
        with tempfile.TemporaryDirectory() as td:
            p = write_log(Path(td) / "b.asc", _data_frames(1500, 9))
            _BASE["b"] = p.read_bytes()
    return _BASE["b"]


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cut=st.floats(0.0, 1.0), where=st.floats(0.0, 1.0),
       junk=st.lists(st.sampled_from(_ALPHABET), min_size=1, max_size=12),
       how=st.sampled_from(["cut", "overwrite", "insert"]))
def test_damaged_files_give_the_same_frames_and_error(cut: float, where: float,
                                                      junk: list[int | bytes],
                                                      how: str) -> None:
    data = bytearray(_base())
    piece = b"".join(bytes([j]) if isinstance(j, int) else j for j in junk)
    at = int(where * (len(data) - len(piece)))
    if how == "cut":
        data = data[:int(cut * len(data))]
    elif how == "overwrite":
        data[at:at + len(piece)] = piece
    else:
        data[at:at] = piece
    with tempfile.TemporaryDirectory() as td:
        path = Path(td) / "d.asc"
        path.write_bytes(bytes(data))
        assert columnar(path, 500) == per_frame(path)
