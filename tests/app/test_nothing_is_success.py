"""Nothing read, nothing decoded or a damaged log is no success (issue 16 item 7, issue 17
item 5).

* an empty log, a log cut short (candump .log, .asc, .blf) or damaged half-way: `replay`
  of it exits 1 with one line saying what, where (line or byte) and how many frames were
  read before it, in both engines; the part before the damage is replayed as if it were the
  whole log (its events are those of a log of those frames alone);
* a log of another bus, a rig of another node layout, nodes that are not in the log: one
  line with the counts by outcome and the likely cause, exit 1; `calibrate` and `identify`
  say the same;
* an archive run (`--out DIR`): each such log is a `failed` row with that reason, the run
  exits 1, and a damaged log's row and events keep what was read;
* the live daemon says it once after the silence timeout, and its metrics show it.

Logs are written by python-can's writers; the CLI runs in its own process and the tests
read back what it wrote (stderr, the events, summary.csv, the metrics file).
"""

from __future__ import annotations

import csv
import re
import signal
import struct
import subprocess
import time
from pathlib import Path

import can
import pytest
from prometheus_client.parser import text_string_to_metric_families

from monitor.bus.codec import load_database
from monitor.bus.logfile import LogDamaged, read_log
from monitor.columnar import read_chunks
from monitor.pipeline import MonitorConfig, MonitorPipeline
from monitor.pipeline.counters import DecodeWatch, nothing_decoded
from monitor.sinks.base import FanOut
from monitor.sinks.metrics import MetricsSink
from tests.archive.logs import ecu_frames, write_log
from tests.support import BIN
from tests.support.paths import TEST_RIGS

MONITOR = str(BIN / "motor-monitor")
SERVO_RIG = TEST_RIGS / "servo.toml"
ENGINES = ("columnar", "per-frame")
SUFFIXES = (".log", ".asc", ".blf")
LAYOUT_CAUSE = ("no frame matches the rig's messages: check [bus] layout / node_bits and "
                "the DBC")


@pytest.fixture(scope="module")
def frames() -> list[can.Message]:
    """Node 0 through fault and outage (12 s, about 2600 frames)."""
    return ecu_frames(("fault-outage-recovery",), seed=4)


def _run(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run([MONITOR, *args], capture_output=True, text=True, timeout=timeout)


def _one_line(proc: subprocess.CompletedProcess[str]) -> str:
    """The command's one line about the outcome (the pipeline's own warnings aside)."""
    assert "Traceback" not in proc.stderr, proc.stderr
    said = [ln for ln in proc.stderr.splitlines() if ln.startswith("motor-monitor: ")]
    assert len(said) == 1, proc.stderr
    assert said[0].startswith("motor-monitor: error: "), proc.stderr
    return said[0].removeprefix("motor-monitor: error: ")


def _frames_read(line: str) -> int:
    found = re.search(r"; (\d+|no) frames? read before it$", line)
    assert found, line
    return 0 if found[1] == "no" else int(found[1])


def _other_bus(n: int = 3000) -> list[can.Message]:
    """Frames of a bus that is not the rig's: standard IDs no DBC message has."""
    return [can.Message(timestamp=1.7e9 + k * 1e-3, arbitration_id=0x6A0 + k % 3,
                        is_extended_id=False, data=bytes([k & 0xFF] * 8)) for k in range(n)]


# -- python-can's own readers stop silently ----------------------------------------------

def test_python_can_stops_silently_at_a_cut_blf_and_we_do_not(
        tmp_path: Path, frames: list[can.Message]) -> None:
    """The finding this module is built on: python-can's BLF reader gives the frames of a
    cut file up to the cut and no word of it; both our readers give the same frames, then
    say where the file was cut."""
    data = write_log(tmp_path / "whole.blf", frames).read_bytes()
    cut = tmp_path / "cut.blf"
    cut.write_bytes(data[:len(data) * 2 // 3])
    python_can = list(can.BLFReader(str(cut)))  # no exception
    assert 0 < len(python_can) < len(frames)
    ours: list[can.Message] = []
    with pytest.raises(LogDamaged) as per_frame:
        ours.extend(read_log(cut))
    assert len(ours) == len(python_can) == per_frame.value.frames
    n = 0
    with pytest.raises(LogDamaged) as columnar:
        for chunk in read_chunks(cut, 500):
            n += len(chunk)
    assert n == len(python_can) and str(columnar.value) == str(per_frame.value)
    assert re.search(r"truncated at byte \d+ \(an object of \d+ bytes, \d+ of them in the "
                     r"file\)", str(per_frame.value)), per_frame.value


def _top_level_objects(data: bytes) -> list[int]:
    """The offsets of a BLF file's top-level objects (its log containers)."""
    pos, found = 144, []
    while pos < len(data):
        found.append(pos)
        size = struct.unpack_from("<4sHHLL", data, pos)[3]
        pos += size + size % 4
    return found


@pytest.mark.parametrize("header", ["finished", "killed writer"])
def test_a_blf_cut_between_its_containers_is_found_too(tmp_path: Path, header: str) -> None:
    """Cut where a log container ends, the file has no object cut short: the header's size
    says so (a writer that finished), or the last container ends in the middle of an object
    that the next one would have finished (a writer killed before its header)."""
    whole = tmp_path / "whole.blf"
    with can.BLFWriter(str(whole), max_container_size=1000) as writer:
        for m in _other_bus(500):
            writer.on_message_received(m)
    data = bytearray(whole.read_bytes())
    if header == "killed writer":
        struct.pack_into("<Q", data, 16, 144)  # the file size python-can writes at start
    cut = tmp_path / "cut.blf"
    found = []
    for at in _top_level_objects(bytes(data))[3:20]:
        cut.write_bytes(bytes(data[:at]))
        python_can = len(list(can.BLFReader(str(cut))))  # no exception
        try:
            assert len(list(read_log(cut))) == python_can  # the file may end on an object
        except LogDamaged as exc:
            n = 0
            with pytest.raises(LogDamaged) as columnar:
                for chunk in read_chunks(cut, 50):
                    n += len(chunk)
            assert str(columnar.value) == str(exc) and n == exc.frames == python_can
            found.append(str(exc))
    if header == "finished":
        assert len(found) == 17 and all(
            re.search(r"truncated at byte \d+ \(the header gives \d+ bytes\)", e)
            for e in found), found
    else:
        assert found and all("(the log container ends in the middle of an object" in e
                             for e in found), found


@pytest.mark.parametrize("suffix", [".log", ".asc"])
def test_bytes_that_are_no_text_are_damage_at_their_line(
        tmp_path: Path, frames: list[can.Message], suffix: str) -> None:
    """A text log overwritten half-way: both readers stop at the line that holds the
    damage, with every frame of the lines before it."""
    path = write_log(tmp_path / f"x{suffix}", frames)
    data = bytearray(path.read_bytes())
    at = data.index(b"\n", len(data) // 2) + 5  # inside the line after that line end
    data[at:at + 8] = bytes(range(0xF0, 0xF8))
    path.write_bytes(bytes(data))
    line = data[:at].count(b"\n") + 1
    before = [m.timestamp for m in can.LogReader(str(write_log(tmp_path / f"w{suffix}",
                                                                frames)))]
    ours: list[float] = []
    with pytest.raises(LogDamaged) as per_frame:
        ours.extend(m.timestamp for m in read_log(path))
    assert f"malformed log at line {line} (not " in str(per_frame.value), per_frame.value
    assert 0 < per_frame.value.frames == len(ours) < len(frames)
    assert ours == before[:len(ours)]
    n = 0
    with pytest.raises(LogDamaged) as columnar:
        for chunk in read_chunks(path):
            n += len(chunk)
    assert str(columnar.value) == str(per_frame.value) and n == len(ours)


# -- one log --------------------------------------------------------------------------------

@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("suffix", SUFFIXES)
def test_an_empty_log_fails_in_one_line(tmp_path: Path, suffix: str, engine: str) -> None:
    path = tmp_path / f"empty{suffix}"
    path.write_bytes(b"")
    events = tmp_path / "events.jsonl"
    proc = _run("replay", str(path), "--engine", engine, "--events", str(events))
    assert proc.returncode == 1, proc.stderr
    assert _one_line(proc) == f"{path}: empty file (0 bytes): no frames"
    assert not events.exists()  # nothing read: nothing written


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("suffix", SUFFIXES)
def test_a_truncated_log_fails_in_one_line_and_keeps_what_was_read(
        tmp_path: Path, frames: list[can.Message], suffix: str, engine: str) -> None:
    data = write_log(tmp_path / f"whole{suffix}", frames).read_bytes()
    cut = tmp_path / f"cut{suffix}"
    cut.write_bytes(data[:int(len(data) * 0.7) + 3])  # in the middle of a line, an object
    events = tmp_path / "cut.events.jsonl"
    proc = _run("replay", str(cut), "--engine", engine, "--events", str(events))
    assert proc.returncode == 1, proc.stderr
    line = _one_line(proc)
    where = "byte" if suffix == ".blf" else "line"
    assert re.match(rf"{re.escape(str(cut))}: truncated at {where} \d+ \(", line), line
    read = _frames_read(line)
    assert 0.5 * len(frames) < read < 0.75 * len(frames), line
    # the part before the damage was replayed as a log of those frames alone would be
    part = write_log(tmp_path / f"part{suffix}", frames[:read])
    part_events = tmp_path / "part.events.jsonl"
    good = _run("replay", str(part), "--engine", engine, "--events", str(part_events))
    assert good.returncode == 0, good.stderr
    assert f"replayed {read} frames" in good.stderr
    kept = events.read_text()
    assert kept == part_events.read_text() and kept.count("\n") >= 2, kept


def _header_only_blf(path: Path) -> Path:
    with can.BLFWriter(str(path)):
        pass
    return path


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("case", ["other bus", "other layout", "other nodes", "no frames"])
def test_nothing_decoded_fails_with_the_counts_and_the_cause(
        tmp_path: Path, frames: list[can.Message], case: str, engine: str) -> None:
    n = len(frames)
    extra: tuple[str, ...]
    if case == "other bus":
        path, extra = write_log(tmp_path / "other.log", _other_bus()), ()
        want = f"0 samples: 3000 frames, 3000 unknown_id: {LAYOUT_CAUSE}"
    elif case == "other layout":  # our bus read with the servo rig (node in ID bits 5..8)
        path, extra = write_log(tmp_path / "ours.blf", frames), ("--rig", str(SERVO_RIG))
        want = f"nodes 1, 2: 0 samples: {n} frames, {n} unknown_id: {LAYOUT_CAUSE}"
    elif case == "other nodes":
        path, extra = write_log(tmp_path / "ours.asc", frames), ("--nodes", "3")
        want = (f"node 3: 0 samples: {n} frames, {n} ignored/node: the frames are of other "
                "nodes: check the nodes asked for and [bus] node_bits")
    else:
        path, extra = _header_only_blf(tmp_path / "header.blf"), ()
        want = "0 samples: 0 frames: no frame at all (an empty log, or a silent bus)"
    proc = _run("replay", str(path), "--engine", engine, *extra)
    assert proc.returncode == 1, proc.stderr
    assert _one_line(proc) == f"{path}: {want}"
    assert "replayed" not in proc.stderr


def test_calibrate_and_identify_give_replays_cause(tmp_path: Path) -> None:
    path = write_log(tmp_path / "other.log", _other_bus())
    want = f"other.log: 0 samples: 3000 frames, 3000 unknown_id: {LAYOUT_CAUSE}"
    for argv in (("calibrate", str(path), "--out", str(tmp_path / "th.toml")),
                 ("identify", str(path), "--out", str(tmp_path / "rig.toml"))):
        proc = _run(*argv)
        assert proc.returncode == 2, proc.stderr  # they refuse, as a configuration mistake
        assert _one_line(proc) == want, argv
        assert not list(tmp_path.glob("th.toml")) and not list(tmp_path.glob("rig.*"))


# -- an archive -----------------------------------------------------------------------------

def _rows(out: Path) -> dict[str, list[dict[str, str]]]:
    with open(out / "summary.csv", newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    by_log: dict[str, list[dict[str, str]]] = {}
    for r in rows:
        by_log.setdefault(Path(r["log"]).name, []).append(r)
    return by_log


@pytest.mark.parametrize("engine", ENGINES)
def test_an_archive_makes_each_such_log_a_failed_row(
        tmp_path: Path, frames: list[can.Message], engine: str) -> None:
    logs = tmp_path / "logs"
    write_log(logs / "good.log", frames)
    for suffix in SUFFIXES:
        (logs / f"empty{suffix}").write_bytes(b"")
    for suffix in (".blf", ".asc"):
        data = write_log(tmp_path / f"whole{suffix}", frames).read_bytes()
        (logs / f"cut{suffix}").write_bytes(data[:len(data) // 2])
    write_log(logs / "other.log", _other_bus())
    out = tmp_path / "out"
    proc = _run("replay", str(logs), "--out", str(out), "--engine", engine)
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    assert "replayed 1 of 7 logs (6 failed)" in proc.stderr, proc.stderr
    rows = _rows(out)
    assert [r["status"] for r in rows["good.log"]] == ["ok"]
    for suffix in SUFFIXES:
        [r] = rows[f"empty{suffix}"]
        assert (r["status"], r["node"], r["frames"]) == ("failed", "", "0"), r
        assert r["reason"] == f"{logs / f'empty{suffix}'}: empty file (0 bytes): no frames"
        assert r["events"] == ""
    for suffix in (".blf", ".asc"):
        [r] = rows[f"cut{suffix}"]  # node 0's row: what was read before the cut
        assert (r["status"], r["node"]) == ("failed", "0"), r
        assert " truncated at " in r["reason"], r
        read = _frames_read(r["reason"])
        assert int(r["frames"]) == int(r["frames/received"]) == read > 1000, r
        assert int(r["samples"]) > 400 and r["transitions_count"] != "0", r
        assert (out / r["events"]).read_text().count("\n") == int(r["transitions_count"])
    [r] = rows["other.log"]
    assert r["status"] == "failed" and r["frames"] == "3000", r
    assert r["reason"].endswith(f": 0 samples: 3000 frames, 3000 unknown_id: {LAYOUT_CAUSE}")


def test_three_empty_logs_are_three_failures(tmp_path: Path) -> None:
    logs = tmp_path / "logs"
    logs.mkdir()
    for suffix in SUFFIXES:
        (logs / f"e{suffix}").write_bytes(b"")
    out = tmp_path / "out"
    proc = _run("replay", str(logs), "--out", str(out))
    assert proc.returncode == 1, proc.stderr
    assert "replayed 0 of 3 logs (3 failed), 0 frames" in proc.stderr, proc.stderr
    rows = _rows(out)
    assert sorted(rows) == ["e.asc", "e.blf", "e.log"]
    assert all(r["status"] == "failed" and "empty file" in r["reason"]
               for rs in rows.values() for r in rs)


# -- the live daemon ------------------------------------------------------------------------

def test_the_watch_and_the_metrics_of_a_bus_of_nothing_decoded(tmp_path: Path) -> None:
    """A pipeline fed another bus: after the silence timeout the watch says it once, the
    metrics show it (and every node asked for, at 0 samples); once samples come, the
    metric clears."""
    cfg = MonitorConfig(nodes=(0,))
    watch = DecodeWatch(cfg.nodes, cfg.silence_timeout_s, start=0.0)
    prom = tmp_path / "monitor.prom"
    metrics = MetricsSink(prom, live=False, watch=watch)
    pipe = MonitorPipeline(load_database(), cfg, sink=FanOut([metrics]))

    def samples() -> dict[int, int]:
        return {n: nm.samples for n, nm in pipe.nodes.items()}

    def read_back() -> dict[str, dict[str, float]]:
        metrics.flush()
        fams = text_string_to_metric_families(prom.read_text())
        return {f.name: {next(iter(s.labels.values()), ""): s.value for s in f.samples}
                for f in fams}

    for m in _other_bus(200):
        pipe.feed(m)
    pipe.emit_counters(1.0)
    assert watch.check(0.4, pipe.counters, samples()) is None  # before the timeout
    said = watch.check(0.6, pipe.counters, samples())
    assert said == f"node 0: 0 samples: 200 frames, 200 unknown_id: {LAYOUT_CAUSE}"
    assert said == nothing_decoded(pipe.counters, samples(), cfg.nodes)
    assert watch.check(5.0, pipe.counters, samples()) is None  # said once
    got = read_back()
    assert got["motor_monitor_nothing_decoded"] == {"": 1.0}
    assert got["motor_monitor_node_samples"] == {"0": 0.0}
    assert got["motor_monitor_events"]["samples/estimated"] == 0.0
    for m in ecu_frames(("healthy",), duration=1.0):
        pipe.feed(m)
    pipe.emit_counters(2.0)
    assert watch.check(6.0, pipe.counters, samples()) is None and not watch.active
    got = read_back()
    assert got["motor_monitor_nothing_decoded"] == {"": 0.0}
    assert got["motor_monitor_node_samples"]["0"] > 50


def test_the_daemon_says_once_that_nothing_is_decoded(tmp_path: Path) -> None:
    """`run` on a bus that stays silent: one warning line after the silence timeout, and
    motor_monitor_nothing_decoded 1 in its metrics."""
    prom = tmp_path / "monitor.prom"
    err = tmp_path / "stderr.txt"
    with open(err, "w") as fh:
        proc = subprocess.Popen([MONITOR, "run", "--interface", "virtual", "--channel",
                                 f"nothing-{tmp_path.name}", "--metrics", str(prom)],
                                stderr=fh, stdout=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 180
        while "nothing decoded" not in err.read_text():
            assert proc.poll() is None, err.read_text()
            assert time.monotonic() < deadline, err.read_text()
            time.sleep(0.2)
        time.sleep(1.0)  # more ticks: still said once
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)
    text = err.read_text()
    assert proc.returncode == 0, text
    said = [ln for ln in text.splitlines() if "nothing decoded" in ln]
    assert len(said) == 1, text
    assert said[0].endswith("WARNING motor_monitor: nothing decoded: 0 samples: 0 frames: no "
                            "frame at all (an empty log, or a silent bus)"), said
    fams = {f.name: f for f in text_string_to_metric_families(prom.read_text())}
    [gauge] = fams["motor_monitor_nothing_decoded"].samples
    assert gauge.value == 1.0
