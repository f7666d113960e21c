"""`motor-monitor replay PATH... --out DIR`: twenty logs replayed serially, on two local
processes and on a local Dask cluster give one summary; damaged logs are rows with their
reason, not the end of the run; outputs are named after the logs' paths."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest

from monitor.archive.result import STATES
from tests.archive.conftest import (
    GOOD_LOGS,
    Archive,
    DaskCluster,
    SerialRun,
    archive_layout,
    comparable,
    events_of,
    read_csv,
    read_parquet,
    run_cli,
)

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_serial_run_summarises_every_log_and_reports_the_damaged_ones(
        archive: Archive, serial_run: SerialRun) -> None:
    proc, out, rows = serial_run.proc, serial_run.out, serial_run.rows
    assert proc.returncode == 1, proc.stderr  # some log failed
    assert "Traceback" not in proc.stderr
    failures = [ln for ln in proc.stderr.splitlines() if "log failed" in ln]
    assert len(failures) == 2, proc.stderr  # each logged once
    assert f"replayed {GOOD_LOGS} of {GOOD_LOGS + 2} logs (2 failed)" in proc.stderr

    by_log: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        by_log.setdefault(str(r["log"]), []).append(r)
    assert len(by_log) == GOOD_LOGS + 2
    broken = by_log.pop(str(archive.corrupt[0]))
    truncated = by_log.pop(str(archive.corrupt[1]))
    # a log that cannot be opened: one row, no events or recording behind
    assert len(broken) == 1 and broken[0]["status"] == "failed" and broken[0]["node"] is None
    assert "cannot read log" in str(broken[0]["reason"]), broken
    assert broken[0]["events"] is None and not list(out.rglob("broken*"))
    # a log damaged half-way: failed, with where and the frames read before the damage,
    # whose figures and events are kept
    [half] = truncated
    reason = str(half["reason"])
    assert half["status"] == "failed" and half["node"] == 0, half
    assert "malformed log at line " in reason and " frames read before it" in reason, reason
    read_before = int(reason.rsplit("; ", 1)[1].split()[0])
    assert half["frames"] == half["frames/received"] == read_before > 1000, half
    assert int(str(half["samples"])) > 100
    assert half["events"] == "rigD/day2/truncated.log.events.jsonl"
    assert (out / str(half["events"])).read_text().count("\n") >= 1

    for i, path in enumerate(archive.good):
        name, scenarios = archive_layout(i)
        log_rows = by_log[str(path)]
        assert [r["node"] for r in log_rows] == list(range(len(scenarios))), log_rows
        for r in log_rows:
            assert r["status"] == "ok" and r["reason"] == ""
            assert r["frames"] == r["frames/received"] and r["frames"] > 3000
            in_states = sum(float(r[f"seconds_{s}"]) for s in STATES)
            assert in_states == pytest.approx(r["duration_s"], abs=1e-6)
            assert r["events"] == name + ".events.jsonl"
            assert math.isfinite(r["worst_nis"]) and r["worst_nis"] > 0
            assert 1000 < r["samples"] <= 100 * r["duration_s"] + 1
            transitions = r["transitions"]
            assert isinstance(transitions, list) and len(transitions) == r["transitions_count"]
            assert transitions[0]["previous"] == "no_data"
            assert transitions[0]["state"] == "fault_free"
        if scenarios[0] == "fault-outage-recovery":
            states = [t["state"] for t in log_rows[0]["transitions"]]
            assert "fault" in states and "outage" in states, states
            assert float(log_rows[0]["seconds_outage"]) > 1.0
        if scenarios[0] == "healthy":
            assert float(log_rows[0]["seconds_fault_free"]) > 0.9 * float(
                log_rows[0]["duration_s"])

    # outputs named after the logs' paths: equal basenames in other directories kept apart
    events = events_of(out)
    assert sorted(events) == sorted([*(archive_layout(i)[0] + ".events.jsonl"
                                       for i in range(GOOD_LOGS)),
                                     "rigD/day2/truncated.log.events.jsonl"])
    assert (out / "fleet.png").read_bytes()[:8] == PNG_MAGIC


def test_csv_holds_the_same_table_as_parquet(serial_run: SerialRun) -> None:
    rows = read_csv(serial_run.out / "summary.csv")
    assert len(rows) == len(serial_run.rows)
    for got, want in zip(rows, serial_run.rows, strict=True):
        assert list(got) == list(want)  # the same columns in the same order
        for key, value in want.items():
            if value is None:
                assert got[key] == "", key
            elif key == "transitions":
                assert json.loads(got[key]) == value
            elif isinstance(value, float):
                assert float(got[key]) == value, key
            else:
                assert got[key] == str(value), key


def test_events_equal_the_single_log_replay(archive: Archive, serial_run: SerialRun) -> None:
    """The archive writes each log's events as `replay LOG` prints them."""
    for i in (1, 2, 3):  # a .asc, a .blf and a two-node .log
        one = run_cli("replay", str(archive.good[i]))
        assert one.returncode == 0, one.stderr
        name = archive_layout(i)[0]
        assert (serial_run.out / (name + ".events.jsonl")).read_text() == one.stdout


def test_two_local_jobs_give_the_serial_summary(archive: Archive, serial_run: SerialRun,
                                                tmp_path: Path) -> None:
    out = tmp_path / "out"
    proc = run_cli("replay", str(archive.root), "--out", str(out), "--jobs", "2")
    assert proc.returncode == 1, proc.stderr
    assert comparable(read_parquet(out / "summary.parquet")) == comparable(serial_run.rows)
    assert events_of(out) == events_of(serial_run.out)


def test_a_local_dask_cluster_gives_the_serial_summary(
        archive: Archive, serial_run: SerialRun, dask_cluster: DaskCluster,
        tmp_path: Path) -> None:
    out = tmp_path / "out"
    proc = run_cli("replay", str(archive.root), "--out", str(out),
                   "--cluster", dask_cluster.address)
    assert proc.returncode == 1, proc.stderr  # the damaged logs, reported
    assert "Traceback" not in proc.stderr
    assert len([ln for ln in proc.stderr.splitlines() if "log failed" in ln]) == 2
    rows = read_parquet(out / "summary.parquet")
    assert comparable(rows) == comparable(serial_run.rows)
    assert events_of(out) == events_of(serial_run.out)
    # the two workers both took logs
    assert all(p.poll() is None for p in dask_cluster.processes)


def test_the_per_frame_engine_gives_the_columnar_summary(archive: Archive, serial_run: SerialRun,
                                                          tmp_path: Path) -> None:
    """The default (columnar) engine and the live daemon's per-frame pipeline agree on every
    log of the archive: every summary column (time in each state, transitions, worst NIS,
    frames by outcome) and every events file; the damaged logs fail the same way."""
    out = tmp_path / "out"
    proc = run_cli("replay", str(archive.root), "--out", str(out), "--engine", "per-frame")
    assert proc.returncode == 1, proc.stderr

    def what_failed(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
        # a damaged file's reason names the reader's own error after "malformed log"
        return [{**r, "reason": r["reason"] and str(r["reason"]).split(" (")[0]}
                for r in comparable(rows)]

    assert what_failed(read_parquet(out / "summary.parquet")) == what_failed(serial_run.rows)
    assert events_of(out) == events_of(serial_run.out)
