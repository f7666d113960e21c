"""Archive replay scaling benchmark: `python -m tests.bench.archive [--logs N] [--seconds S]`.

A set of logs (virtual ECUs' runs, .log/.asc/.blf in turn, four scenarios, one and two
nodes) replayed by `motor-monitor replay DIR --out OUT` as the command runs it
(`monitor.archive.run.run_archive` with `--engine per-frame`, whose work per log is large
enough to show the scaling; no recordings): on 1 and on 2
local workers (`--jobs 1`: in this process; `--jobs 2`: two spawned processes), and, with
the archive extra, on a local Dask cluster of 1 and of 2 worker processes (one thread each,
127.0.0.1). Each time is the whole run as a user waits for it: worker start-up, every log,
the summary and the fleet PNG. Speedup is the 1-worker time over the 2-worker time; on a
machine whose cores are shared with other work, it shows what those cores gave. Last line
JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from monitor.archive.engine import ReplaySettings, per_frame_engine
from monitor.archive.inputs import find_logs
from monitor.archive.run import run_archive
from tests.archive.logs import SCENARIOS, ecu_frames, write_log

SUFFIXES = (".log", ".asc", ".blf")


def make_logs(root: Path, n: int, seconds: float) -> int:
    """`n` logs of `seconds` each below `root`; returns the frames written."""
    frames = 0
    for i in range(n):
        scenarios = (SCENARIOS[i % 4],) if i % 2 else (SCENARIOS[i % 4], SCENARIOS[(i + 1) % 4])
        run = ecu_frames(scenarios, seed=i, duration=seconds)
        write_log(root / f"rig{i % 2}" / f"run{i}{SUFFIXES[i % 3]}", run)
        frames += len(run)
    return frames


@contextmanager
def local_dask(workers: int) -> Iterator[str]:
    """A Dask cluster of `workers` processes on 127.0.0.1; yields the scheduler address."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                      host="127.0.0.1", dashboard_address=None) as cluster:
        yield str(cluster.scheduler_address)


def timed(root: Path, out: Path, **how: Any) -> dict[str, Any]:
    t0 = time.perf_counter()
    done = run_archive(find_logs([str(root)]), ReplaySettings(), out, show_progress=False,
                       engine=per_frame_engine,
                       **how)
    el = time.perf_counter() - t0
    assert not done.failed, [r.reason for r in done.failed]
    busy = sum(r.wall_s for r in done.results)
    return {"seconds": el, "frames": done.frames, "frames_per_s": done.frames / el,
            "log_seconds": busy}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", type=int, default=8, help="logs in the set (default 8)")
    ap.add_argument("--seconds", type=float, default=60.0,
                    help="bus time per log, s (default 60)")
    ap.add_argument("--no-dask", action="store_true", help="skip the Dask cluster runs")
    args = ap.parse_args()
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="bench-archive-") as tmp:
        root = Path(tmp) / "logs"
        frames = make_logs(root, args.logs, args.seconds)
        print(f"{args.logs} logs, {frames} frames ({args.seconds:g} s of bus each), "
              f"{os.cpu_count()} cores")
        for workers in (1, 2):
            r = timed(root, Path(tmp) / f"jobs{workers}", jobs=workers)
            runs.append({"runner": "jobs", "workers": workers, **r})
        dask = not args.no_dask
        if dask:
            try:
                import distributed  # noqa: F401
            except ImportError:
                dask = False
        if dask:
            for workers in (1, 2):
                with local_dask(workers) as address:
                    r = timed(root, Path(tmp) / f"dask{workers}", cluster=address)
                runs.append({"runner": "dask", "workers": workers, **r})
    print(f"{'runner':8s} {'workers':>7s} {'seconds':>8s} {'frames/s':>9s} {'speedup':>8s}")
    speedups: dict[str, float] = {}
    for r in runs:
        one = next(x for x in runs if x["runner"] == r["runner"] and x["workers"] == 1)
        r["speedup"] = one["seconds"] / r["seconds"]
        if r["workers"] == 2:
            speedups[r["runner"]] = r["speedup"]
        print(f"{r['runner']:8s} {r['workers']:7d} {r['seconds']:8.2f} "
              f"{r['frames_per_s']:9.0f} {r['speedup']:8.2f}")
    print(json.dumps({"benchmark": "archive", "logs": args.logs, "frames": frames,
                      "seconds_per_log": args.seconds, "cores": os.cpu_count(),
                      "runs": runs, "speedup_2_workers": speedups}))


if __name__ == "__main__":
    main()
