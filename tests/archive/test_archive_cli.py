"""The archive replay's command line: files, directories and glob patterns, outputs named
after the logs' paths, one-line mistakes, the missing extra, the progress bar, and the
per-file engine as a parameter (the seam another engine plugs into)."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

import can
import pytest

from monitor.app.cli import main
from monitor.archive import run as archive_run
from monitor.archive.engine import EngineRun, MonitorSetup, NodeStats, ReplaySettings
from monitor.archive.inputs import find_logs
from monitor.archive.run import run_archive
from monitor.bus.logfile import suffix_list
from monitor.pipeline.events import DiagnosisEvent
from monitor.sinks.base import Sink
from tests.archive.conftest import read_csv, read_parquet, run_cli
from tests.archive.logs import ecu_frames, write_log


@pytest.fixture(scope="module")
def short_frames() -> list[can.Message]:
    return list(ecu_frames(("fault-outage-recovery",), seed=5, duration=5.0))


@pytest.fixture
def tree(tmp_path: Path, short_frames: list[can.Message]) -> Path:
    """a/run.log, b/run.log (equal basenames), c/x/run.asc, c/y/notes.txt, d/run.blf,
    d/run.log (equal stems)."""
    root = tmp_path / "tree"
    for name in ("a/run.log", "b/run.log", "c/x/run.asc", "d/run.blf", "d/run.log"):
        write_log(root / name, short_frames)
    (root / "c" / "y").mkdir(parents=True)
    (root / "c" / "y" / "notes.txt").write_text("not a log\n")
    return root


def test_files_directories_and_patterns_each_log_once(tree: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    proc = run_cli("replay", str(tree / "a"), str(tree / "b" / "run.log"),
                   str(tree / "c" / "**" / "*"), str(tree / "*" / "run.blf"),
                   str(tree / "a" / "run.log"), str(tree / "d" / "run.log"),
                   "--out", str(out), "--rrd")
    assert proc.returncode == 0, proc.stderr
    rows = read_parquet(out / "summary.parquet")
    logs = [r["log"] for r in rows]
    assert logs == [str(tree / n) for n in ("a/run.log", "b/run.log", "c/x/run.asc",
                                           "d/run.blf", "d/run.log")]
    assert all(r["status"] == "ok" and r["node"] == 0 for r in rows)
    names = ["a/run.log", "b/run.log", "c/x/run.asc", "d/run.blf", "d/run.log"]
    assert [r["events"] for r in rows] == [n + ".events.jsonl" for n in names]
    assert [r["rrd"] for r in rows] == [n + ".rrd" for n in names]
    for n in names:
        assert (out / (n + ".events.jsonl")).read_text().count("\n") >= 2
        assert (out / (n + ".rrd")).stat().st_size > 0
    # every log is the same run: the same diagnosis wherever it lies (timestamps to the
    # precision of each format)
    assert len({(r["transitions_count"], round(r["seconds_fault"], 3)) for r in rows}) == 1
    assert len(read_csv(out / "summary.csv")) == len(rows)


def test_output_names_below_the_deepest_common_directory(tree: Path) -> None:
    logs = find_logs([str(tree / "c"), str(tree / "a" / "run.log"), str(tree / "nope.log"),
                      str(tree / "zz*")])
    assert [(x.name, x.problem) for x in logs] == [
        ("c/x/run.asc", None), ("a/run.log", None), ("nope.log", None),
        ("", f"{tree / 'zz*'}: no log matches this pattern")]
    (empty := tree / "empty").mkdir()
    [only] = find_logs([str(empty)])
    assert only.problem is not None and f"holds no {suffix_list()} file" in only.problem


def test_missing_unsupported_and_unmatched_are_rows_not_the_end(
        tree: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    out = tmp_path / "out"
    code = main(["replay", str(tree / "a"), str(tree / "missing.log"),
                 str(tree / "c" / "y" / "notes.txt"), str(tree / "nothing*.blf"),
                 "--out", str(out)])
    assert code == 1
    failed = [r.getMessage() for r in caplog.records if "log failed" in r.getMessage()]
    assert len(failed) == 3, failed  # each once
    rows = {r["log"]: r for r in read_parquet(out / "summary.parquet")}
    assert rows[str(tree / "a" / "run.log")]["status"] == "ok"
    reasons = {k: r["reason"] for k, r in rows.items() if r["status"] == "failed"}
    assert reasons == {
        str(tree / "missing.log"): f"{tree / 'missing.log'}: no such file",
        str(tree / "c" / "y" / "notes.txt"):
            f"{tree / 'c/y/notes.txt'}: unsupported log format (use {suffix_list()})",
        str(tree / "nothing*.blf"): f"{tree / 'nothing*.blf'}: no log matches this pattern",
    }


@pytest.mark.parametrize(
    ("args", "expect"),
    [
        (["{a}", "{b}"], "need --out DIR"),
        (["{dir}"], "need --out DIR"),
        (["{a}", "--out", "{out}", "--events", "{out}/e.jsonl"], "--events names one file"),
        (["{a}", "--out", "{out}", "--rrd", "{out}/x.rrd"], "--rrd takes no file name"),
        (["{a}", "--out", "{out}", "--connect", "rerun+http://127.0.0.1:1/proxy"], "--connect"),
        (["{a}", "--out", "{out}", "--jobs", "2", "--cluster", "tcp://127.0.0.1:1"],
         "--jobs and --cluster exclude each other"),
        (["{a}", "--out", "{out}", "--jobs", "0"], "--jobs: must be at least 1"),
        (["{a}", "--out", "{out}", "--jobs", "two"], "--jobs: not a whole number"),
        (["{a}", "--out", "{a}"], "--out: "),
        (["{a}", "--rrd"], "--rrd: give the recording's file name"),
        (["{a}", "--jobs", "2"], "give --out DIR"),
        (["{a}", "{b}", "--out", "{out}", "--rig", "{out}/none.toml"], "none.toml"),
    ],
)
def test_every_mistake_is_one_line(tree: Path, tmp_path: Path, args: list[str],
                                   expect: str) -> None:
    files = {"a": str(tree / "a" / "run.log"), "b": str(tree / "b" / "run.log"),
             "dir": str(tree), "out": str(tmp_path / "out")}
    proc = run_cli("replay", *(a.format(**files) for a in args))
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("motor-monitor") and expect in lines[0], lines
    assert not (tmp_path / "out" / "summary.parquet").exists()


def test_cluster_without_the_extra_names_it(tree: Path, tmp_path: Path,
                                            monkeypatch: pytest.MonkeyPatch,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed fails
    code = main(["replay", str(tree / "a"), "--out", str(tmp_path / "out"),
                 "--cluster", "tcp://127.0.0.1:8786"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert "--cluster needs Dask distributed" in err[0] and "motor-monitor[archive]" in err[0]


def test_unreachable_cluster_is_one_line(tree: Path, tmp_path: Path,
                                         monkeypatch: pytest.MonkeyPatch,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("distributed")
    monkeypatch.setattr(archive_run, "CONNECT_TIMEOUT_S", 2.0)
    code = main(["replay", str(tree / "a"), "--out", str(tmp_path / "out"),
                 "--cluster", "tcp://127.0.0.1:9"])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert code == 2, err
    assert err[-1].startswith("motor-monitor: error: --cluster: cannot reach a Dask scheduler "
                              "at tcp://127.0.0.1:9"), err


def test_progress_bar_shows_logs_frames_and_rate(tree: Path, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("tqdm")
    done = run_archive(find_logs([str(tree / "a"), str(tree / "b")]), ReplaySettings(),
                       tmp_path / "out", show_progress=True, fleet_png=False)
    err = capsys.readouterr().err
    assert not done.failed
    assert "2/2 logs" in err and f"{done.frames:,} frames" in err and "frames/s" in err, err
    assert "100%" in err


def test_quiet_when_not_a_terminal(tree: Path, tmp_path: Path,
                                   capsys: pytest.CaptureFixture[str]) -> None:
    run_archive(find_logs([str(tree / "a")]), ReplaySettings(), tmp_path / "out",
                fleet_png=False)
    assert capsys.readouterr().err == ""  # pytest's stderr is no terminal


def canned_engine(path: Path, setup: MonitorSetup, open_sinks: Callable[[], list[Sink]],
                  progress: Callable[[int], None] | None = None) -> EngineRun:
    """An engine that reads nothing: node 3 is fault-free from 1 s, faulty from 4 s to the
    end at 10 s, the way a columnar engine would report a log."""
    events = [DiagnosisEvent(1.0, 3, "fault_free", "no_data", 0.0, 0.0, 1, "estimate"),
              DiagnosisEvent(4.0, 3, "fault", "fault_free", 0.4, 4.8, 2, "estimate")]
    sinks = open_sinks()
    try:
        for e in events:
            for s in sinks:
                s.on_transition(e)
    finally:
        for s in sinks:
            s.close()
    if progress is not None:
        progress(1000)
    return EngineRun(frames=1000, counters={"frames/received": 1000, "rejected/bad_crc": 2},
                     transitions=events, nodes={3: NodeStats(samples=900, worst_nis=7.5)},
                     t_first=0.0, t_last=10.0, feed_s=0.01)


def test_the_per_file_engine_is_a_parameter(tree: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    done = run_archive(find_logs([str(tree / "a"), str(tree / "b")]), ReplaySettings(), out,
                       engine=canned_engine, fleet_png=False)
    assert [r.frames for r in done.results] == [1000, 1000]
    [row, _] = read_parquet(out / "summary.parquet")
    assert row["node"] == 3 and row["samples"] == 900 and row["worst_nis"] == 7.5
    assert (row["seconds_no_data"], row["seconds_fault_free"], row["seconds_fault"]) == (
        1.0, 3.0, 6.0)
    assert row["rejected/bad_crc"] == 2
    assert [t["state"] for t in row["transitions"]] == ["fault_free", "fault"]
    assert (out / "a" / "run.log.events.jsonl").read_text().count("\n") == 2
