"""The log formats beside candump, ASC and BLF: ASAM MDF4 (``.mf4``), PEAK TRC (``.trc``, each
version python-can reads) and gzip-compressed text logs (``.log.gz``, ``.asc.gz``,
``.trc.gz``). Files are written by python-can's writers (`can.Logger`, `MF4Writer`,
`TRCWriter`, the gzip its Logger writes) and by asammdf itself; the per-frame path
(`read_log`, python-can's readers) and the columnar path (`read_chunks`) give the same frames,
timestamps bit for bit, as python-can's own `can.LogReader`, and the same one line for a
damaged file (truncated, a corrupted gzip, an MF4 data block asammdf cannot read, a TRC line
python-can cannot read), after the frames before the damage. `motor-monitor replay` of an
.mf4, .trc or .log.gz of a simulated run gives the events of the .log of the same frames.
"""

from __future__ import annotations

import gzip
import json
import math
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from can.io.trc import TRCFileVersion

from monitor.archive.inputs import find_logs
from monitor.bus.logfile import (
    LOG_FORMATS,
    LogDamaged,
    LogError,
    check_log_path,
    log_format,
    read_log,
)
from monitor.columnar import read_chunks
from tests.archive.logs import ecu_frames
from tests.support import BIN
from tests.support.log_readers import columnar, per_frame, python_can, random_frames, write_mf4

MONITOR = str(BIN / "motor-monitor")


def _write(path: Path, frames: list[can.Message], **kwargs: Any) -> Path:
    with can.Logger(str(path), **kwargs) as writer:
        for m in frames:
            writer.on_message_received(m)
    return path


def _classic(n: int, seed: int) -> list[can.Message]:
    """Classic data frames only (what python-can's TRC writer writes)."""
    return [m for m in random_frames(3 * n, seed)
            if not (m.is_fd or m.is_remote_frame or m.is_error_frame)][:n]


def _both(path: Path, chunk_frames: int = 777) -> tuple[list[Any], str | None]:
    """The per-frame path's frames and error, checked to be the columnar path's."""
    want = per_frame(path)
    assert columnar(path, chunk_frames) == want
    return want


# -- the one suffix table -----------------------------------------------------------------

def test_one_table_names_every_format_by_its_longest_suffix(tmp_path: Path) -> None:
    assert set(LOG_FORMATS) == {".log", ".log.gz", ".asc", ".asc.gz", ".trc", ".trc.gz",
                                ".blf", ".mf4"}
    assert log_format("RUN.LOG.GZ") is LOG_FORMATS[".log.gz"]
    assert log_format("a/b.Mf4") is LOG_FORMATS[".mf4"]
    assert log_format("x.blf.gz") is None and log_format("x.gz") is None
    with pytest.raises(LogError, match=r"unsupported log format \(use \.log, \.log\.gz, "
                                       r"\.asc, \.asc\.gz, \.trc, \.trc\.gz, \.blf, \.mf4\)"):
        check_log_path(tmp_path / "x.blf.gz")
    for name in ("a.mf4", "b.trc", "c.log.gz", "d/e.asc.gz", "notes.txt", "f.gz"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_bytes(b"x")
    assert sorted(x.name for x in find_logs([str(tmp_path)])) == \
        ["a.mf4", "b.trc", "c.log.gz", "d/e.asc.gz"]


# -- MF4 ----------------------------------------------------------------------------------

@pytest.mark.parametrize("chunk_frames", [777, 1 << 18])
def test_mf4_python_can_writes_reads_the_same(tmp_path: Path, chunk_frames: int) -> None:
    """Data, error and remote frames, classic and FD: three channel groups merged in
    python-can's order."""
    frames = random_frames(3000, 7)
    path = _write(tmp_path / "x.mf4", frames)
    want = python_can(path)
    assert len(want) == 3000
    assert {(f[3], f[4]) for f in want} == {(False, False), (True, False), (False, True)}
    assert _both(path, chunk_frames) == (want, None)


def test_mf4_groups_out_of_time_order_merge_as_python_can_merges(tmp_path: Path) -> None:
    """python-can's MF4Writer keeps each frame's own time: groups need not be sorted, and
    heapq's merge of unsorted groups is no sort. Ties go to the first group."""
    frames = random_frames(400, 11)
    for i in range(0, 400, 7):
        frames[i].timestamp -= 0.5  # late frames of every kind
    frames[10].timestamp = frames[11].timestamp  # a tie across kinds
    path = _write(tmp_path / "x.mf4", frames)
    want = python_can(path)
    assert [f[0] for f in want] != sorted(f[0] for f in want)
    assert _both(path, 50) == (want, None)


@pytest.mark.parametrize("fields", [("IDE", "DLC"), (), ("IDE", "DLC", "EDL", "BRS", "ESI")])
def test_mf4_asammdf_writes_reads_the_same(tmp_path: Path, fields: tuple[str, ...]) -> None:
    """A file asammdf writes column by column, with or without the optional fields (a field
    left out: python-can's default, extended IDs without IDE); 8-byte payload fields."""
    rng = np.random.default_rng(3)
    n = 25_000
    t = np.cumsum(rng.choice([1e-4, 1e-3, 0.0137], n))
    ids = rng.integers(0, 1 << 29, n) >> rng.choice([0, 18], n)
    length = rng.integers(0, 9, n)
    data = rng.integers(0, 256, (n, 8)).astype(np.uint8)
    path = write_mf4(tmp_path / "x.mf4", t, ids, data, length, fields=fields)
    want = python_can(path)
    assert len(want) == n and [f[9] for f in want] == list(length)
    assert all(f[2] for f in want) == ("IDE" not in fields)
    assert _both(path, 4000) == (want, None)
    assert _both(path, 1 << 18) == (want, None)


def _dz_blocks(data: bytes) -> list[int]:
    return [m.start() for m in re.finditer(rb"##DZ", data)]


def test_mf4_with_a_bad_data_block_keeps_the_frames_before_it(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    n = 300_000
    path = write_mf4(tmp_path / "whole.mf4", np.arange(n) * 1e-4, rng.integers(0, 0x800, n),
                     rng.integers(0, 256, (n, 8)).astype(np.uint8), np.full(n, 8))
    whole = python_can(path)
    data = bytearray(path.read_bytes())
    blocks = _dz_blocks(bytes(data))
    assert len(blocks) >= 2
    at = blocks[1] + 200  # compressed data in the second data block
    data[at:at + 40] = bytes(40)
    bad = tmp_path / "bad.mf4"
    bad.write_bytes(bytes(data))
    got, error = _both(bad, 100_000)
    assert error is not None and 0 < len(got) < n, error
    assert got == whole[:len(got)]
    assert re.fullmatch(rf"{re.escape(str(bad))}: malformed MF4 at frame {len(got) + 1} \(a "
                        rf"data block asammdf cannot read: .+\); {len(got)} frames read "
                        rf"before it", error), error


@pytest.mark.parametrize("damage", ["truncated", "not mdf", "a block past the end"])
def test_an_mf4_asammdf_cannot_open_fails_before_any_frame(tmp_path: Path, damage: str) -> None:
    path = _write(tmp_path / "whole.mf4", random_frames(500, 2))
    data = path.read_bytes()
    bad = tmp_path / "bad.mf4"
    if damage == "truncated":  # a logger that lost power: the block tree is written last
        bad.write_bytes(data[:len(data) * 2 // 3])
    elif damage == "not mdf":
        bad.write_bytes(b"MDF     " + bytes(range(256)) * 4)
    else:
        first = _dz_blocks(data)[0] if _dz_blocks(data) else data.index(b"##DT")
        bad.write_bytes(data[:first + 8] + b"\xff" * 8 + data[first + 16:])
    with pytest.raises(LogDamaged) as per_frame_error:
        read_log(bad)  # at open: before the caller opens any output
    with pytest.raises(LogDamaged) as columnar_error:
        read_chunks(bad)
    said = str(per_frame_error.value)
    assert said == str(columnar_error.value)
    assert said.startswith(f"{bad}: malformed MF4 (") and said.endswith("): no frames read")


def test_an_install_without_asammdf_says_so_in_one_line(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = _write(tmp_path / "x.mf4", random_frames(50, 1))
    monkeypatch.setitem(sys.modules, "asammdf", None)  # import asammdf fails
    said = (f"{path}: reading MF4 needs asammdf, which is not installed "
            "(the mf4 extra: pip install 'motor-monitor[mf4]')")
    with pytest.raises(LogError) as per_frame_error:
        read_log(path)
    with pytest.raises(LogError) as columnar_error:
        read_chunks(path)
    assert str(per_frame_error.value) == str(columnar_error.value) == said
    assert not isinstance(per_frame_error.value, LogDamaged)


# -- TRC ----------------------------------------------------------------------------------

@pytest.mark.parametrize("version", [TRCFileVersion.V1_0, TRCFileVersion.V2_1])
def test_trc_python_can_writes_reads_the_same(tmp_path: Path, version: TRCFileVersion) -> None:
    path = tmp_path / "x.trc"
    with can.TRCWriter(str(path)) as writer:
        writer.file_version = version
        for m in _classic(3000, 4):
            writer.on_message_received(m)
    want = python_can(path)
    assert len(want) == 3000
    assert _both(path) == (want, None)


_TRC = {
    "1.1": """;$FILEVERSION=1.1
;$STARTTIME=46022.5136204861
;   Message Number
;   |         Time Offset (ms)
;   |         |        Type
;---+--   ----+----  --+--  ----+---  +  -+ -- -- -- -- -- -- --
     1)         1.3  Rx         0100  8  00 01 02 03 04 05 06 07
     2)        11.1  Tx     00000101  2  AA BB
     3)        21.4  Rx         0102  1  RTR
     4)        30.0  Warng  FFFFFFFF  4  00 00 00 08  BUSHEAVY
     5)        41.7  Rx         07FF  0
""",
    "1.3": """;$FILEVERSION=1.3
;$STARTTIME=46022.5136204861
;   Message   Time    Bus  Type   ID    Reserved
;---+-- ------+------ +- --+-- ----+--- +- -+-- -+ -- -- --
     1)         1.312 1  Rx        0100 -  8    00 01 02 03 04 05 06 07
     2)        11.101 2  Tx    00000101 -  2    AA BB
     3)        21.400 1  Rx        0102 -  3    RTR
""",
    "2.0": """;$FILEVERSION=2.0
;$STARTTIME=46022.5136204861
;$COLUMNS=N,O,T,I,d,l,D
;
      1         1.312 DT     0100 Rx 8  00 01 02 03 04 05 06 07
      2        11.101 FD 00000101 Tx 12 00 01 02 03 04 05 06 07 08 09 0A 0B
      3        15.000 FB     0103 Rx 16 00 01 02 03 04 05 06 07 08 09 0A 0B 0C 0D 0E 0F
      4        21.000 RR     0102 Rx 2
      5        25.000 ST     0000 Rx 4  00 00 00 01
""",
}


@pytest.mark.parametrize("version", sorted(_TRC))
def test_trc_versions_python_can_reads_read_the_same(tmp_path: Path, version: str) -> None:
    path = tmp_path / f"v{version}.trc"
    path.write_text(_TRC[version])
    want = python_can(path)
    assert len(want) >= 3
    assert _both(path) == (want, None)


def _trc_lines(tmp_path: Path) -> tuple[Path, list[str]]:
    path = tmp_path / "whole.trc"
    with can.TRCWriter(str(path)) as writer:
        for m in _classic(200, 6):
            writer.on_message_received(m)
    return path, path.read_text().splitlines(keepends=True)


@pytest.mark.parametrize(("damage", "said"), [
    ("few columns", r"malformed log at line (\d+) \(5 columns, fewer than a frame of TRC "
                    r"V2_1 has\)"),
    ("bad hex", r"malformed log at line (\d+) \(.*\)"),
    ("cut", r"truncated at line (\d+) \(the last line has no line end\)"),
])
def test_a_trc_with_a_bad_line_says_where(tmp_path: Path, damage: str, said: str) -> None:
    path, lines = _trc_lines(tmp_path)
    whole = python_can(path)
    header = sum(1 for ln in lines if ln.startswith(";"))
    k = header + 120  # the 121st frame's line (0-based index)
    if damage == "few columns":
        lines[k] = " ".join(lines[k].split()[:5]) + "\r\n"
    elif damage == "bad hex":
        lines[k] = lines[k].replace(lines[k].split()[4], "XYZ", 1)
    else:
        lines = lines[:k + 1]
        lines[k] = lines[k][:30]
    bad = tmp_path / "bad.trc"
    bad.write_bytes("".join(lines).encode())
    got, error = _both(bad)
    assert error is not None
    found = re.fullmatch(rf"{re.escape(str(bad))}: {said}; 120 frames read before it", error)
    assert found, error
    assert int(found[1]) == k + 1 and got == whole[:120]


# -- gzip ---------------------------------------------------------------------------------

def _frames_for(suffix: str) -> list[can.Message]:
    return _classic(4000, 8) if suffix.startswith(".trc") else random_frames(4000, 8)


@pytest.mark.parametrize("suffix", [".log.gz", ".asc.gz", ".trc.gz"])
def test_gzip_logs_read_as_the_log_they_hold(tmp_path: Path, suffix: str) -> None:
    frames = _frames_for(suffix)
    packed = _write(tmp_path / f"x{suffix}", frames)  # python-can's Logger compresses
    plain = _write(tmp_path / f"x{suffix.removesuffix('.gz')}", frames)
    assert packed.read_bytes()[:2] == b"\x1f\x8b"
    want = python_can(packed)
    assert len(want) == 4000 and want == python_can(plain)
    assert _both(packed) == (want, None)
    assert _both(packed, 1 << 18) == (want, None)


def _gz(tmp_path: Path, suffix: str) -> tuple[Path, list[Any]]:
    path = _write(tmp_path / f"whole{suffix}", _frames_for(suffix))
    return path, python_can(path)


@pytest.mark.parametrize("suffix", [".log.gz", ".asc.gz"])
def test_a_truncated_gzip_log_keeps_the_frames_before_the_cut(tmp_path: Path,
                                                              suffix: str) -> None:
    path, whole = _gz(tmp_path, suffix)
    cut = tmp_path / f"cut{suffix}"
    cut.write_bytes(path.read_bytes()[:int(path.stat().st_size * 0.6)])
    got, error = _both(cut)
    assert error is not None and 0.4 * len(whole) < len(got) < 0.8 * len(whole), error
    assert got == whole[:len(got)]
    assert re.fullmatch(rf"{re.escape(str(cut))}: truncated at line \d+ \(the gzip stream "
                        rf"ends before its end marker\); {len(got)} frames read before it",
                        error), error


@pytest.mark.parametrize("suffix", [".log.gz", ".asc.gz"])
def test_a_gzip_log_with_a_wrong_checksum_is_damaged_after_its_frames(
        tmp_path: Path, suffix: str) -> None:
    path, whole = _gz(tmp_path, suffix)
    data = bytearray(path.read_bytes())
    data[-8] ^= 0xFF  # the CRC-32 of the member: found once all of it is decompressed
    bad = tmp_path / f"crc{suffix}"
    bad.write_bytes(bytes(data))
    got, error = _both(bad)
    assert got == whole
    assert error is not None and re.fullmatch(
        rf"{re.escape(str(bad))}: malformed log at line \d+ \(damaged gzip: CRC check "
        rf"failed.*\); {len(whole)} frames read before it", error), error


@pytest.mark.parametrize("suffix", [".log.gz", ".asc.gz", ".trc.gz"])
def test_a_corrupted_gzip_log_is_damaged_where_it_breaks(tmp_path: Path, suffix: str) -> None:
    path, whole = _gz(tmp_path, suffix)
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 16] = bytes(range(200, 216))
    bad = tmp_path / f"bad{suffix}"
    bad.write_bytes(bytes(data))
    got, error = _both(bad)
    assert error is not None and error.startswith(f"{bad}: "), error
    assert re.search(r" at line \d+ \(.*\); (\d+|no) frames? read before it$", error), error
    assert len(got) < len(whole)


def test_a_file_named_gz_that_is_no_gzip_says_so(tmp_path: Path) -> None:
    bad = tmp_path / "plain.log.gz"
    bad.write_text("(1700000000.000000) vcan0 123#00\n")
    got, error = _both(bad)
    assert got == [] and error == (f"{bad}: malformed log at line 1 (damaged gzip: Not a "
                                   f"gzipped file (b'(1')); no frame read before it")


@pytest.mark.parametrize("stamp", ["(.)", "()", "(1.)", "(.5)", "(0000.000000)", "(7)",
                                   "(1.2.3)", "(12345678901234567890.1)"])
def test_a_candump_time_stamp_reads_as_python_can_reads_it(tmp_path: Path, stamp: str) -> None:
    # the compiled scanner takes a plain stamp, python-can reads (or refuses) every other one
    log = tmp_path / "stamp.log"
    log.write_text(f"(1.5) vcan0 123#11\n{stamp} vcan0 124#22\n")
    got, error = _both(log)
    if stamp in ("(.)", "()", "(1.2.3)"):
        assert len(got) == 1 and error is not None and " at line 2 " in error, (got, error)
    else:
        assert len(got) == 2 and error is None, error


# -- end to end: motor-monitor replay -----------------------------------------------------

@pytest.fixture(scope="module")
def sim_logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A simulated run through fault and outage (node 0, about 2600 frames) in each format,
    written by python-can's writers."""
    frames = ecu_frames(("fault-outage-recovery",), seed=4)
    where = tmp_path_factory.mktemp("sim")
    return {s: _write(where / f"run{s}", frames) for s in (".log", ".log.gz", ".trc", ".mf4")}


def _events(log: Path, tmp_path: Path, *engine: str) -> list[dict[str, Any]]:
    events = tmp_path / f"{log.name}{''.join(engine)}.events.jsonl"
    proc = subprocess.run([MONITOR, "replay", str(log), "--events", str(events), *engine],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr and "asammdf" not in proc.stderr, proc.stderr
    return [json.loads(line) for line in events.read_text().splitlines()]


def _close(a: Any, b: Any) -> bool:
    """Equal, floats to 1e-6 relative or 1e-5 absolute: TRC keeps microseconds after its
    start time in days, MF4 times after its own start time (a float sum each)."""
    if isinstance(a, float) and isinstance(b, float):
        return math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-5)
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_close(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_close(x, y) for x, y in zip(a, b, strict=True))
    return bool(a == b)


@pytest.mark.parametrize(("suffix", "engine"), [(".log.gz", ()), (".trc", ()), (".mf4", ()),
                                                (".mf4", ("--engine", "per-frame"))])
def test_replay_of_each_format_gives_the_events_of_the_log(
        sim_logs: dict[str, Path], tmp_path: Path, suffix: str, engine: tuple[str, ...]) -> None:
    want = _events(sim_logs[".log"], tmp_path)
    assert len(want) >= 3 and {e["state"] for e in want} >= {"fault", "outage"}, want
    got = _events(sim_logs[suffix], tmp_path, *engine)
    if suffix == ".log.gz":
        assert got == want  # the same bytes
    assert [(e["node"], e["state"], e["previous"]) for e in got] == \
        [(e["node"], e["state"], e["previous"]) for e in want]
    assert _close(got, want), (got, want)


def test_replay_of_a_damaged_gzip_log_fails_in_one_line_and_keeps_its_events(
        sim_logs: dict[str, Path], tmp_path: Path) -> None:
    data = sim_logs[".log.gz"].read_bytes()
    cut = tmp_path / "cut.log.gz"
    cut.write_bytes(data[:len(data) * 3 // 4])
    events = tmp_path / "cut.events.jsonl"
    proc = subprocess.run([MONITOR, "replay", str(cut), "--events", str(events)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 1, proc.stderr
    said = [ln for ln in proc.stderr.splitlines() if ln.startswith("motor-monitor: error: ")]
    assert len(said) == 1 and re.search(r"truncated at line \d+ \(the gzip stream ends before "
                                        r"its end marker\); \d+ frames read before it$",
                                        said[0]), proc.stderr
    assert events.exists()


def test_gzip_module_reads_what_the_log_holds(sim_logs: dict[str, Path]) -> None:
    """The .log.gz of the end-to-end tests holds the .log's bytes (python-can's Logger)."""
    with gzip.open(sim_logs[".log.gz"], "rb") as fh:
        assert fh.read() == sim_logs[".log"].read_bytes()

