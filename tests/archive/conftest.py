"""An archive of twenty bus logs (mixed .log/.asc/.blf, four scenarios, one and two nodes,
equal names in different directories) and two damaged ones, a local Dask cluster (a
scheduler and two workers on 127.0.0.1, real processes), and the serial replay of the
archive that the parallel runs are compared with."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
import pytest

from tests.archive.logs import SCENARIOS, corrupt_blf, corrupt_candump, ecu_frames, write_log
from tests.support import BIN

MONITOR = str(BIN / "motor-monitor")
DASK = str(BIN / "dask")

GOOD_LOGS = 20
SUFFIXES = (".log", ".asc", ".blf")


@dataclass(frozen=True)
class Archive:
    root: Path
    good: list[Path]
    corrupt: list[Path]


def archive_layout(i: int) -> tuple[str, tuple[str, ...]]:
    """The i-th good log's path below the archive and the scenario of each of its nodes:
    rigs A..D, two days each, every day's log named run.<suffix> (equal basenames in
    different directories), every third log with a second node."""
    rig = "ABCD"[i % 4]
    day = 1 + (i // 4) % 2
    suffix = SUFFIXES[i % 3]
    name = f"rig{rig}/day{day}/run{i // 8}{suffix}"
    scenarios = (SCENARIOS[i % 4],) if i % 3 else (SCENARIOS[i % 4], SCENARIOS[(i + 1) % 4])
    return name, scenarios


@pytest.fixture(scope="session")
def archive(tmp_path_factory: pytest.TempPathFactory) -> Archive:
    root = tmp_path_factory.mktemp("archive") / "logs"
    good = []
    for i in range(GOOD_LOGS):
        name, scenarios = archive_layout(i)
        good.append(write_log(root / name, ecu_frames(scenarios, seed=i, start_time=1.7e9 + i)))
    frames = ecu_frames(("healthy",), seed=99)
    corrupt = [corrupt_blf(root / "rigC" / "day1" / "broken.blf"),
               corrupt_candump(root / "rigD" / "day2" / "truncated.log", frames)]
    return Archive(root, good, corrupt)


def run_cli(*args: str, cwd: Path | None = None,
            timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run([MONITOR, *args], capture_output=True, text=True, timeout=timeout,
                          cwd=cwd)


def read_parquet(path: Path) -> list[dict[str, Any]]:
    return list(pq.read_table(path).to_pylist())


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def comparable(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rows without what depends on the machine's speed (wall time), in log order."""
    return sorted(({k: v for k, v in r.items() if k != "wall_s"} for r in rows),
                  key=lambda r: (r["log"], -1 if r["node"] is None else r["node"]))


def events_of(out: Path) -> dict[str, list[dict[str, Any]]]:
    """Every events file below `out`, by its path relative to `out`, parsed."""
    return {str(p.relative_to(out)): [json.loads(ln) for ln in p.read_text().splitlines()]
            for p in sorted(out.rglob("*.events.jsonl"))}


@dataclass(frozen=True)
class SerialRun:
    out: Path
    proc: subprocess.CompletedProcess[str]
    rows: list[dict[str, Any]]


@pytest.fixture(scope="session")
def serial_run(archive: Archive, tmp_path_factory: pytest.TempPathFactory) -> SerialRun:
    out = tmp_path_factory.mktemp("serial") / "out"
    proc = run_cli("replay", str(archive.root), "--out", str(out))
    return SerialRun(out, proc, read_parquet(out / "summary.parquet"))


@dataclass(frozen=True)
class DaskCluster:
    address: str
    processes: list[subprocess.Popen[bytes]]


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)  # its own session: the process and its children
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=20)


# Module scope: the scheduler and workers stop when the tests that use them are done; their
# event loops would otherwise wake the host CPU for the rest of the session, under the
# timing-sensitive vcan tests in User-Mode Linux.
@pytest.fixture(scope="module")
def dask_cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DaskCluster]:
    """`dask scheduler` on 127.0.0.1 (a free port, no dashboard) and two `dask worker`
    processes of one thread each, all from this virtual environment (so the workers have
    the project installed)."""
    pytest.importorskip("distributed")
    from distributed import Client

    tmp = tmp_path_factory.mktemp("dask")
    scheduler_file = tmp / "scheduler.json"
    procs: list[subprocess.Popen[bytes]] = []

    def start(*args: str, log: str) -> subprocess.Popen[bytes]:
        with open(tmp / log, "wb") as f:
            p = subprocess.Popen([DASK, *args], stdout=f, stderr=subprocess.STDOUT, cwd=tmp,
                                 start_new_session=True)
        procs.append(p)
        return p

    try:
        scheduler = start("scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                          "--scheduler-file", str(scheduler_file), log="scheduler.log")
        deadline = time.monotonic() + 120
        while not scheduler_file.exists():
            assert scheduler.poll() is None, (tmp / "scheduler.log").read_text()
            assert time.monotonic() < deadline, "the scheduler wrote no scheduler file"
            time.sleep(0.2)
        time.sleep(0.2)  # the file is written whole, but give it a moment
        address = json.loads(scheduler_file.read_text())["address"]
        assert address.startswith("tcp://127.0.0.1:"), address
        for k in range(2):
            start("worker", "--scheduler-file", str(scheduler_file), "--host", "127.0.0.1",
                  "--nthreads", "1", "--no-dashboard", "--no-nanny", "--memory-limit", "0",
                  "--name", f"worker-{k}", log=f"worker-{k}.log")
        with Client(address, timeout="60s", set_as_default=False) as client:
            client.wait_for_workers(2, timeout=180)
        yield DaskCluster(address, procs)
    finally:
        for p in reversed(procs):
            _stop(p)
