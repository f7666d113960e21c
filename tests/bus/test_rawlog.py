"""The raw bus record: every frame in rotating python-can logs, readable after a kill with
absolute timestamps, rotated and pruned like the recordings. (The daemon writing it on a
real bus, and the replay of its own raw log giving the live events, is in
tests/rig/test_rig_vcan.py.)"""

from __future__ import annotations

import shutil
from pathlib import Path

import can
import pytest

from monitor.bus.rawlog import RAW_FORMATS, RotatingBusLog


def _frames(n: int, t0: float = 1.7e9) -> list[can.Message]:
    out = [can.Message(timestamp=t0 + i * 0.01, arbitration_id=0x110 + (i % 3),
                       data=bytes([i % 256]) * 8, is_extended_id=False) for i in range(n)]
    # an error frame as python-can's socketcan bus gives it: class bits in the ID
    out.append(can.Message(timestamp=t0 + n * 0.01, arbitration_id=0x4, is_error_frame=True,
                           data=bytes([0, 4, 0, 0, 0, 0, 0, 0])))
    out.append(can.Message(timestamp=t0 + n * 0.01 + 0.001, arbitration_id=0x18FF2001,
                           is_extended_id=True, data=b"\x01\x02"))
    return out


@pytest.mark.parametrize("suffix", RAW_FORMATS)
def test_a_flushed_file_reads_back_whole_after_a_kill(tmp_path: Path, suffix: str) -> None:
    sent = _frames(500)
    raw = RotatingBusLog(tmp_path / "raw", suffix=suffix)
    for m in sent:
        raw(m)
    raw.flush()
    killed = tmp_path / f"killed{suffix}"
    shutil.copy(raw.path, killed)  # what a SIGKILL leaves on disk
    got = list(can.LogReader(str(killed)))
    raw.stop()
    assert len(got) == len(sent)
    for a, b in zip(got, sent, strict=True):
        assert a.timestamp == pytest.approx(b.timestamp, abs=2e-6)  # absolute, not relative
        assert a.is_error_frame == b.is_error_frame
        if b.is_error_frame and suffix == ".log":
            continue  # python-can's candump writer keeps the error flag, not class and data
        assert (a.arbitration_id, a.is_extended_id) == (b.arbitration_id, b.is_extended_id)
        assert bytes(a.data) == bytes(b.data)


def test_rotation_and_retention(tmp_path: Path) -> None:
    raw = RotatingBusLog(tmp_path, suffix=".log", max_bytes=4096, max_age_s=None, keep=3)
    for m in _frames(2000):
        raw(m)
    raw.stop()
    files = raw.files()
    assert len(files) == 3  # the oldest deleted beyond keep
    assert raw.rollover_count >= 5
    assert all(f.name.startswith("bus-") and f.suffix == ".log" for f in files)
    kept = [m for f in files for m in can.LogReader(str(f))]
    assert kept[-1].arbitration_id == 0x18FF2001  # the newest frames survive
