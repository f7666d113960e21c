"""Recordings that lose nothing: real processes, real signals, real files, no mocks.

* SIGKILL: a child logging at a steady rate with wall-clock time stamps (``time.time()``) and
  calling ``maybe_flush`` every loop turn, like the daemon, is killed; what is on disk reaches
  to within 0.25 s of the kill.
* SIGTERM: the child closes its sink; ``rerun rrd verify`` passes and every sample is there.
* Rotation by size and by age: every file passes ``rerun rrd verify``, the oldest are deleted
  beyond ``keep``/``max_total_bytes``, and the files together hold exactly what was logged.
* Compaction of rotated files: the result verifies and holds every row; it never blocks the
  caller; a failure (or a slow optimiser at close) keeps the file as written.
* Memory stays bounded over many rotations.
"""

from __future__ import annotations

import gc
import os
import shutil
import signal
import subprocess
import sys
import time
import warnings
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pytest
from numpy.typing import NDArray
from rerun.chunk import RrdReader

from monitor.sinks import compact
from monitor.sinks.base import Sink
from monitor.sinks.rerun import DEFAULT_FLUSH_INTERVAL_S, RerunSink
from monitor.sinks.rotation import RotatingRerunSink
from monitor.sinks.salvage import salvage_rrd
from tests.support.paths import ROOT
from tests.support.rrd import blueprint_names, recording_rows

RERUN_EXE = Path(sys.executable).with_name("rerun")
MAX_LOSS_S = 0.25  # the goal: after SIGKILL, readable up to at most 0.25 s before the kill
T0 = 1_700_000_000.0

# The child: 2 nodes x 1 kHz, gamma^ = the sample number k (so gaps and duplicates show),
# t = time.time(), maybe_flush every turn; SIGTERM sets a flag, the loop ends, close().
CHILD = r"""
import signal
import sys
import time
from pathlib import Path

from monitor.sinks.rerun import RerunSink
from monitor.sinks.rotation import RotatingRerunSink

kind, out = sys.argv[1], Path(sys.argv[2])
if kind == "rotating":
    sink = RotatingRerunSink(out, max_bytes=int(sys.argv[3]), max_age_s=None, keep=None,
                             nodes=(0, 1))
else:
    sink = RerunSink(rrd_path=out, nodes=(0, 1))
stop = []
signal.signal(signal.SIGTERM, lambda signum, frame: stop.append(signum))
period = 1e-3
k = 0
t = 0.0
next_turn = time.monotonic()
print("ready", flush=True)
while not stop:
    t = time.time()
    for node in (0, 1):
        sink.add_sample(node, t, 1.0, 1.0, float(k), 1, 0, 1.0)
    k += 1
    sink.maybe_flush(time.monotonic())
    next_turn += period
    delay = next_turn - time.monotonic()
    if delay > 0:
        time.sleep(delay)
sink.close()
print(k, repr(t), flush=True)
"""


# -- helpers --------------------------------------------------------------------------------


def _verify(paths: Iterable[Path], *, footers: bool = True) -> subprocess.CompletedProcess[str]:
    cmd = [str(RERUN_EXE), "rrd", "verify", *(str(p) for p in paths)]
    if not footers:
        cmd += ["--check-footers", "false"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120)


def _gamma(path: Path, node: int = 0) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(time [s], gamma^) rows of one node in one file, in file order."""
    ts: list[NDArray[np.float64]] = []
    vs: list[NDArray[np.float64]] = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a file without footer warns
        try:
            chunks = RrdReader(path).stream()
        except ValueError:  # no recording in it: killed right after it was created
            return np.zeros(0), np.zeros(0)
        for chunk in chunks:
            if chunk.is_static or chunk.entity_path != f"/node/{node}/gamma/estimate":
                continue
            rb = chunk.to_record_batch()
            ts.append(rb.column("time").cast(pa.int64()).to_numpy() / 1e9)
            vs.append(rb.column("Scalars:scalars").flatten().to_numpy())
    if not ts:
        return np.zeros(0), np.zeros(0)
    return np.concatenate(ts), np.concatenate(vs)


def _union(paths: Iterable[Path], node: int = 0) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    parts = [_gamma(p, node) for p in paths]
    if not parts:
        return np.zeros(0), np.zeros(0)
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def _readable(path: Path) -> bool:
    """A killed writer may leave a torn last message: salvage it if the strict reader fails."""
    try:
        _gamma(path)
        return True
    except RuntimeError:
        removed = salvage_rrd(path)
        assert removed > 0, f"{path} unreadable and nothing to salvage"
        _gamma(path)
        return False


def _spawn(tmp_path: Path, kind: str, out: Path, max_bytes: int = 0) -> subprocess.Popen[str]:
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("RERUN", None)
    proc = subprocess.Popen(
        [sys.executable, str(script), kind, str(out), str(max_bytes)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if line.strip() != "ready":
        proc.kill()
        _, err = proc.communicate(timeout=30)
        pytest.fail(f"child did not start: {line!r} {err[-2000:]}")
    return proc


def _rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _threads() -> int:
    return len(os.listdir("/proc/self/task"))


# -- SIGKILL ------------------------------------------------------------------------------------


def test_default_flush_interval_is_short_enough(tmp_path: Path) -> None:
    assert DEFAULT_FLUSH_INTERVAL_S <= 0.2
    for sink in (RerunSink(rrd_path=tmp_path / "a.rrd"), RotatingRerunSink(tmp_path / "rot")):
        try:
            assert sink.flush_interval_s == DEFAULT_FLUSH_INTERVAL_S
        finally:
            sink.close()


@pytest.mark.parametrize("kind", ["plain", "rotating"])
def test_sigkill_loses_at_most_a_quarter_second(tmp_path: Path, kind: str) -> None:
    margins: list[float] = []
    torn = in_rotation = 0
    for i in range(3):
        out = tmp_path / (f"run{i}" if kind == "rotating" else f"run{i}.rrd")
        # rotating: ~100 kB files, a rotation every ~0.4 s, so kills land anywhere
        proc = _spawn(tmp_path, kind, out, max_bytes=100_000)
        time.sleep(1.0 + 0.173 * i)  # different phases of the 0.1 s flush period
        kill_time = time.time()
        os.kill(proc.pid, signal.SIGKILL)
        proc.communicate(timeout=30)
        assert proc.returncode == -signal.SIGKILL

        if kind == "rotating":
            files = sorted(out.iterdir())
            assert len(files) >= 2, files  # it did rotate
            closed, last = files[:-1], files[-1]
            # rotated files are complete, footer and all ...
            if len(closed) > 1:
                proc_v = _verify(closed[:-1])
                assert proc_v.returncode == 0, proc_v.stderr
            # ... but the SDK writes a file's footer after it has created the next file: a kill
            # in that window (a few ms per rotation) leaves the previous file without one
            if _verify(closed[-1:]).returncode != 0:
                in_rotation += 1
                # the new file has no samples yet (or nothing at all: below)
                assert last.stat().st_size == 0 or len(_gamma(last)[1]) == 0
                assert _verify(closed[-1:], footers=False).returncode == 0
                torn += not _readable(closed[-1])
        else:
            closed, last = [], out
        if kind == "rotating" and (last.stat().st_size == 0 or len(_gamma(last)[1]) == 0):
            # killed right after a rotation opened the file, before its first write of a
            # sample (nothing in it, or the stream's header alone, which `rerun rrd verify`
            # counts as no file): every sample is in the files before it
            in_rotation += 1
            kept = closed
        else:
            # the killed file has no footer, but the SDK's streaming decoder reads it
            proc_v = _verify([last], footers=False)
            assert proc_v.returncode == 0, proc_v.stderr
            assert _verify([last]).returncode != 0  # no footer: the strict verify says so
            torn += not _readable(last)
            kept = [*closed, last]

        t, g = _union(kept)
        # nothing lost before the tail: gamma^ = 0, 1, 2, ... without gap or duplicate
        np.testing.assert_array_equal(g, np.arange(len(g)))
        assert np.all(np.diff(t) > 0)
        margin = kill_time - t[-1]
        margins.append(margin)
        assert t[-1] <= kill_time + 0.01
        assert margin <= MAX_LOSS_S, (margin, kill_time, t[-1])
    print(
        f"\n{kind}: SIGKILL margins (kill time - last sample on disk): "
        + ", ".join(f"{m * 1e3:.0f} ms" for m in margins)
        + f"; torn files: {torn}; killed while rotating: {in_rotation}"
    )


def test_salvaged_file_reads_up_to_the_tear(tmp_path: Path) -> None:
    """Cut a recording at every kind of place a kill can stop a write; salvage, then read."""
    path = tmp_path / "whole.rrd"
    with RerunSink(rrd_path=path, nodes=(0,), batch_size=100, write_footer=False) as sink:
        for k in range(1000):
            sink.add_sample(0, T0 + k * 1e-3, 1.0, 1.0, float(k), 1, 0, 1.0)
    data = path.read_bytes()
    _, full = _gamma(path)
    assert len(full) == 1000
    assert salvage_rrd(path) == 0 and path.read_bytes() == data  # intact: untouched
    for cut in (len(data) - 1, len(data) - 500, len(data) // 2 + 7):
        torn = tmp_path / f"cut{cut}.rrd"
        torn.write_bytes(data[:cut])
        with pytest.raises(RuntimeError):  # the strict reader refuses a torn file
            _gamma(torn)
        assert _verify([torn], footers=False).returncode == 0  # the lenient one reads it
        removed = salvage_rrd(torn)
        assert 0 < removed < cut
        assert salvage_rrd(torn) == 0
        _, g = _gamma(torn)
        assert 0 < len(g) <= 1000
        np.testing.assert_array_equal(g, np.arange(len(g)))
    torn = tmp_path / "cut40.rrd"  # inside the first message
    torn.write_bytes(data[:40])
    assert salvage_rrd(torn) == 28 and torn.read_bytes() == data[:12]


def test_salvage_a_torn_footer_and_reject_other_files(tmp_path: Path) -> None:
    path = tmp_path / "f.rrd"
    with RerunSink(rrd_path=path, nodes=(0,)) as sink:
        sink.add_sample(0, T0, 1.0, 1.0, 0.5, 1, 0, 1.0)
    assert _verify([path]).returncode == 0
    data = path.read_bytes()
    assert salvage_rrd(path) == 0 and path.read_bytes() == data
    path.write_bytes(data[:-10])  # killed while writing the footer
    assert salvage_rrd(path) > 10
    assert list(_gamma(path)[1]) == [0.5]
    other = tmp_path / "x.rrd"
    other.write_bytes(b"not a recording at all")
    with pytest.raises(ValueError):
        salvage_rrd(other)
    assert other.read_bytes() == b"not a recording at all"


# -- SIGTERM ------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["plain", "rotating"])
def test_sigterm_closes_a_verified_recording_with_every_sample(tmp_path: Path, kind: str) -> None:
    out = tmp_path / ("run" if kind == "rotating" else "run.rrd")
    proc = _spawn(tmp_path, kind, out, max_bytes=100_000)
    time.sleep(1.2)
    term_time = time.time()
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 0, stderr
    n_str, t_str = stdout.split()
    n, t_last = int(n_str), float(t_str)
    files = sorted(out.iterdir()) if kind == "rotating" else [out]
    if kind == "rotating":
        assert len(files) >= 2
    result = _verify(files)  # footers required
    assert result.returncode == 0, result.stderr
    for node in (0, 1):
        t, g = _union(files, node)
        np.testing.assert_array_equal(g, np.arange(n))  # every sample, once, in order
        assert np.all(np.diff(t) > 0)
        assert t[-1] == pytest.approx(t_last, abs=1e-6)
    assert t_last >= term_time - 0.05  # logged up to the signal


# -- rotation -----------------------------------------------------------------------------------


def _feed(
    sink: RotatingRerunSink, start: int, count: int, *, flush_every: int = 100, settle: bool = True
) -> None:
    """2 nodes, a voltage every 50 samples, counters and a flush every ``flush_every``.

    The test produces far faster than real time, so the SDK's writer thread lags behind and
    the size a flush sees would not be the size of what was sent; ``settle`` waits for the
    writer before each flush (the daemon's real-time rate never gets ahead of it).
    """
    for k in range(start, start + count):
        t = T0 + k * 1e-3
        sink.add_sample(0, t, 1.0, 2.0, float(k), 1 + k % 3, k % 4, 1.0, true_gamma=0.5)
        sink.add_sample(1, t, 1.0, 2.0, float(k), 1, 0, 1.0)
        if k % 50 == 0:
            sink.add_input(0, t, 24.0)
        if k % flush_every == flush_every - 1:
            sink.log_counters(t, {"frames/ok": k})
            if settle:
                sink.recording.flush(timeout_sec=30)
            sink.flush()


def _static_entities(path: Path) -> set[str]:
    return {c.entity_path for c in RrdReader(path).stream() if c.is_static}


def test_rotation_by_size_keeps_everything_contiguous_and_verified(tmp_path: Path) -> None:
    sink = RotatingRerunSink(
        tmp_path, max_bytes=200_000, max_age_s=None, keep=None, nodes=(0,), batch_size=128,
        recording_id="size-run", f1=0.1, f2=0.9,
    )  # fmt: skip
    assert isinstance(sink, Sink)
    first = sink.path
    n = 12_010
    _feed(sink, 0, n // 2)
    sink.set_thresholds(0.2, 0.8)
    rotated = sink.rotations
    assert rotated >= 2 and sink.path != first
    # rotated files are finished while the sink still runs: footer written
    done = sink.files()[:-1]
    assert _verify(done).returncode == 0
    _feed(sink, n // 2, n // 2)
    sink.close()
    sink.close()  # idempotent
    files = sink.files()
    assert len(files) == sink.rotations + 1 >= 6, files
    assert files == sorted(files) and files[-1] == sink.path
    names = [p.name for p in files]
    assert all(name.startswith("monitor-") and name.endswith(".rrd") for name in names)
    seqs = [int(name[-8:-4]) for name in names]
    assert seqs == list(range(len(files)))
    result = _verify(files)
    assert result.returncode == 0, result.stderr
    sizes = [p.stat().st_size for p in files]
    # rotated once the size was reached; overshoot: the flush the check saw (it lags one flush
    # here, ~40 kB each), the one that triggered it, and the footer (~100 kB for these files)
    assert min(sizes[:-1]) >= 200_000 and max(sizes[:-1]) < 200_000 + 250_000, sizes
    for node in (0, 1):
        t, g = _union(files, node)
        np.testing.assert_array_equal(g, np.arange(n))  # no gap, no duplicate at a boundary
        assert np.all(np.diff(t) > 0)
    # every file is self-contained
    for p in files:
        (rec,) = RrdReader(p).recordings()
        assert rec.recording_id == "size-run"
        static = _static_entities(p)
        assert {"/node/0/gamma/F1", "/node/1/nis", "/node/0/gamma/true",
                "/node/1/gamma/sd"} <= static, p
        assert {"node 0", "node 1", "daemon counters"} <= blueprint_names(p), p
    # the thresholds in the last file are the current ones
    last = [c for c in RrdReader(files[-1]).stream() if c.entity_path == "/node/0/gamma/F1"]
    f1 = np.concatenate(
        [
            c.to_record_batch().column("Scalars:scalars").flatten().to_numpy()
            for c in last
            if not c.is_static
        ]
    )
    assert np.all(f1 == 0.2)


def test_rotation_by_age(tmp_path: Path) -> None:
    sink = RotatingRerunSink(tmp_path, max_bytes=None, max_age_s=0.3, keep=None, nodes=(0,))
    k = 0
    start = time.monotonic()
    while time.monotonic() - start < 1.6:
        sink.add_sample(0, time.time(), 1.0, 1.0, float(k), 1, 0, 1.0)
        k += 1
        sink.maybe_flush(time.monotonic())
        time.sleep(0.002)
    sink.close()
    files = sink.files()
    assert 4 <= len(files) <= 7, files  # ~1.6 s / 0.3 s
    assert _verify(files).returncode == 0
    _, g = _union(files)
    np.testing.assert_array_equal(g, np.arange(k))
    spans = [np.ptp(_gamma(p)[0]) for p in files[:-1]]
    assert max(spans) < 0.3 + 2 * DEFAULT_FLUSH_INTERVAL_S, spans


def test_retention_by_count_and_total_size(tmp_path: Path) -> None:
    # files of an earlier run count as well, and go first
    old = RotatingRerunSink(tmp_path, max_bytes=None, max_age_s=None, keep=None, nodes=(0,))
    _feed(old, 0, 100)
    old.close()
    (tmp_path / "unrelated.rrd").write_bytes(b"keep me")
    sink = RotatingRerunSink(tmp_path, max_bytes=100_000, max_age_s=None, keep=3, nodes=(0,),
                             batch_size=128)  # fmt: skip
    assert old.path in sink.files()  # 2 files <= keep
    n = 10_000
    _feed(sink, 100, n)
    sink.close()
    files = sink.files()
    assert len(files) == 3 and sink.rotations >= 5
    assert old.path not in files
    assert (tmp_path / "unrelated.rrd").read_bytes() == b"keep me"
    assert _verify(files).returncode == 0
    # what is left is the newest data, contiguous up to the last sample
    _, g = _union(files)
    np.testing.assert_array_equal(g, np.arange(100 + n - len(g), 100 + n))

    by_size = tmp_path / "by_size"
    sink = RotatingRerunSink(by_size, max_bytes=300_000, max_total_bytes=1_000_000, max_age_s=None,
                             keep=None, nodes=(0,), batch_size=128)  # fmt: skip
    _feed(sink, 0, n)
    sink.close()
    files = sink.files()
    assert sink.rotations >= 5 and len(files) >= 2
    # at the last rotation the closed files were cut down to leave room for the new one
    assert sum(p.stat().st_size for p in files[:-1]) <= 1_000_000 - 300_000
    # the current one: up to what the last flushes sent, and its footer (~50-100 kB)
    assert files[-1].stat().st_size < 2 * 300_000
    _, g = _union(files)
    np.testing.assert_array_equal(g, np.arange(n - len(g), n))


def test_a_failed_rotation_keeps_recording_and_retries(tmp_path: Path) -> None:
    d = tmp_path / "rec"
    sink = RotatingRerunSink(d, max_bytes=100_000, max_age_s=None, keep=None, nodes=(0,),
                             batch_size=128)  # fmt: skip
    first = sink.path
    # the directory is replaced by a plain file: no new file can be created in it
    first_copy = tmp_path / "first.rrd"
    os.rename(first, first_copy)
    os.rmdir(d)
    d.write_bytes(b"")
    _feed(sink, 0, 2_000)  # rotation due (the file is gone), fails, recording goes on
    assert sink.rotations == 0 and sink.path == first
    d.unlink()
    time.sleep(1.1)  # the retry back-off
    _feed(sink, 2_000, 2_000)
    assert sink.rotations >= 1
    sink.close()
    files = sink.files()
    assert _verify([first_copy, *files]).returncode == 0
    _, g = _union([first_copy, *files])
    np.testing.assert_array_equal(g, np.arange(4_000))


def test_rotation_arguments_are_checked(tmp_path: Path) -> None:
    for kwargs in ({"max_bytes": 0}, {"max_age_s": 0.0}, {"keep": 0}, {"prefix": "a/b"},
                   {"max_bytes": 100, "max_total_bytes": 50}):  # fmt: skip
        with pytest.raises(ValueError):
            RotatingRerunSink(tmp_path / "x", **kwargs)


# -- compaction of rotated files ------------------------------------------------------------------


def _fake_rerun(tmp_path: Path, optimize: str) -> Path:
    """A ``rerun`` CLI whose ``rrd optimize`` runs the shell code `optimize` (arguments: rrd
    optimize IN -o OUT ...), everything else the real one."""
    exe = tmp_path / "fake-rerun"
    exe.write_text(f"""#!/bin/sh
if [ "$2" = optimize ]; then
{optimize}
fi
exec {compact.rerun_cli()} "$@"
""")
    exe.chmod(0o755)
    return exe


def test_rotated_files_are_compacted_with_the_same_rows(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each rotated file (and the last, at close) is rewritten by ``rerun rrd optimize``: it
    verifies, has a few times fewer chunks, and holds every row (row ids, times, values, the
    blueprint) of the file as the rotation closed it."""
    written = tmp_path / "as-written"
    written.mkdir()
    real = compact.compact_rrd

    def keep_a_copy(p: Path, **kwargs: Any) -> int:
        shutil.copyfile(p, written / p.name)
        return real(p, **kwargs)

    monkeypatch.setattr(compact, "compact_rrd", keep_a_copy)
    out = tmp_path / "rec"
    sink = RotatingRerunSink(out, max_bytes=None, max_age_s=None, keep=None, nodes=(0, 1),
                             batch_size=128, compactor=compact.Compactor(),
                             recording_id="compacted")
    assert sink.compactor is not None
    n = 3000
    for part in range(3):
        _feed(sink, part * n, n, settle=False)
        if part < 2:
            sink.rotate()
    sink.close()
    assert sink.compactor.stats.compacted == 3 and sink.compactor.stats.failed == 0
    files = sink.files()
    assert [p.name for p in files] == sorted(p.name for p in written.iterdir())
    result = _verify(files)
    assert result.returncode == 0, result.stderr
    for p in files:
        before = written / p.name
        assert recording_rows(p) == recording_rows(before), p
        n_before = sum(1 for _ in RrdReader(before).stream())
        n_after = sum(1 for _ in RrdReader(p).stream())
        assert n_after < n_before / 3, (p, n_before, n_after)
        assert p.stat().st_size < before.stat().st_size
    for node in (0, 1):
        _, g = _union(files, node)
        np.testing.assert_array_equal(g, np.arange(3 * n))
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary file


def test_compaction_never_blocks_and_a_failure_keeps_the_file(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    exe = _fake_rerun(tmp_path, "  sleep 1; echo 'error: no space left' >&2; exit 3")
    out = tmp_path / "rec"
    sink = RotatingRerunSink(out, max_bytes=None, max_age_s=None, keep=None, nodes=(0,),
                             compactor=compact.Compactor(exe=exe))
    _feed(sink, 0, 500, settle=False)
    started = time.monotonic()
    first = sink.rotate()  # closes the first file and queues it
    sink.flush()
    assert time.monotonic() - started < 0.9  # the loop did not wait for the 1 s compaction
    assert sink.compactor is not None and sink.compactor.pending() == 1
    closed = sink.files()[0]
    data = closed.read_bytes()
    _feed(sink, 500, 500, settle=False)
    with caplog.at_level("WARNING"):
        sink.close()
    assert sink.compactor.stats.failed == 2  # the rotated file and the last one
    assert "no space left" in caplog.text and "kept as written" in caplog.text
    assert closed.read_bytes() == data  # untouched
    assert [p.name for p in sink.files()] == [closed.name, first.name]
    assert _verify(sink.files()).returncode == 0
    _, g = _union(sink.files())
    np.testing.assert_array_equal(g, np.arange(1000))
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize("kind", ["fails", "garbage", "no_cli", "file_changed", "deleted"])
def test_a_failed_compaction_keeps_the_original(tmp_path: Path, kind: str) -> None:
    path = tmp_path / "rec.rrd"
    with RerunSink(rrd_path=path, nodes=(0,), batch_size=100) as sink:
        for k in range(1000):
            sink.add_sample(0, T0 + k * 1e-3, 1.0, 1.0, float(k), 1, 0, 1.0)
    data = path.read_bytes()
    optimize, why = {
        "fails": ("  echo 'Error: cannot decode' >&2; exit 1", "Error: cannot decode"),
        "garbage": ('  echo not a recording > "$5"; exit 0', "verify"),  # refused by verify
        # a valid result, but the original changed or was deleted (retention) meanwhile
        "file_changed": ('  cp "$3" "$5"; printf x >> "$3"; exit 0', "changed"),
        "deleted": ('  cp "$3" "$5"; rm "$3"; exit 0', "No such file"),
        "no_cli": ("", "cannot run"),
    }[kind]
    exe = tmp_path / "missing" if kind == "no_cli" else _fake_rerun(tmp_path, optimize)
    with pytest.raises(compact.CompactionError, match=why):
        compact.compact_rrd(path, exe=exe)
    if kind == "file_changed":
        assert path.read_bytes() == data + b"x"  # what the other writer made of it, as it is
    elif kind == "deleted":
        assert not path.exists()  # not brought back
    else:
        assert path.read_bytes() == data
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_close_gives_up_on_a_slow_compaction_and_leftovers_are_swept(tmp_path: Path) -> None:
    exe = _fake_rerun(tmp_path, '  echo partial > "$5"; exec sleep 60')
    out = tmp_path / "rec"
    sink = RotatingRerunSink(out, max_bytes=None, max_age_s=None, keep=None, nodes=(0,),
                             compactor=compact.Compactor(exe=exe), compact_wait_s=0.5)
    _feed(sink, 0, 300, settle=False)
    sink.rotate()
    _feed(sink, 300, 300, settle=False)
    started = time.monotonic()
    sink.close()
    assert time.monotonic() - started < 5.0  # 0.5 s, then the optimiser is stopped
    assert sink.compactor is not None and sink.compactor.stats.abandoned >= 1
    files = sink.files()
    assert _verify(files).returncode == 0  # kept as written
    # a killed daemon's leftover temporary file goes at the next start
    leftover = out / f".{files[0].name}.compacting.rrd"
    leftover.write_bytes(b"partial")
    again = RotatingRerunSink(out, max_bytes=None, max_age_s=None, keep=None, nodes=(0,),
                              compactor=compact.Compactor())
    assert not leftover.exists()
    again.close()
    assert again.compactor is not None and again.compactor.stats.compacted == 1


# -- memory -------------------------------------------------------------------------------------


def test_memory_and_files_stay_bounded_over_many_rotations(tmp_path: Path) -> None:
    """2e6 samples, about 16 rotations, 3 files kept: the SDK's per-file chunk manifest is freed
    at each rotation, and no thread or stream is leaked. (Without rotation, the same run grows
    by ~100 MB: a footer manifest entry per chunk.)"""
    n = 2_000_000
    keep = 3
    sink = RotatingRerunSink(tmp_path, max_bytes=15_000_000, max_age_s=None, keep=keep,
                             nodes=(0,), batch_size=64)  # fmt: skip
    warm = n // 10
    rss: list[float] = []
    most_files = 0
    base_rss, base_threads, base_rotations = 0.0, 0, 0
    for k in range(n):
        sink.add_sample(0, T0 + k * 1e-4, 1.0 + k * 1e-7, 1.0, (k % 1000) / 1000, 2, 1, 1.0, 0.3)
        if k % 1000 == 999:
            sink.maybe_flush(time.monotonic())
        if k % 100_000 == 99_999:
            most_files = max(most_files, len(sink.files()))
            if k == warm - 1:
                gc.collect()
                base_rss, base_threads, base_rotations = _rss_mb(), _threads(), sink.rotations
            elif k >= warm:
                rss.append(_rss_mb())
    sink.close()
    gc.collect()
    rss.append(_rss_mb())
    growth = max(rss) - base_rss
    rotations = sink.rotations - base_rotations
    print(
        f"\nRSS after warm-up {base_rss:.1f} MB, max growth over {rotations} rotations "
        f"{growth:.1f} MB (samples: {', '.join(f'{r - base_rss:+.1f}' for r in rss)}); "
        f"threads {base_threads} -> {_threads()}; files at most {most_files}"
    )
    assert rotations >= 12, sink.rotations
    assert growth < 30.0, rss
    assert _threads() <= base_threads + 1
    assert most_files <= keep and len(sink.files()) <= keep
    assert _verify(sink.files()).returncode == 0
