"""Replay many logs: `replay_one` for one log (what a worker runs), `run_archive` for the
whole run (serially in this process, on local cores, or on a Dask cluster), its summary
table and its fleet overview.

Parallel runs use the executors' own scheduling, one task per log: the standard library's
`ProcessPoolExecutor` for `--jobs N` (forked from a fresh server process: no state of this
one is copied),
and `distributed.Client.get_executor()` for `--cluster ADDRESS`, the same
`concurrent.futures` interface on a Dask cluster (the `archive` extra). Workers open the
logs and write the outputs by the paths this process gives them (absolute paths): on a
cluster, logs, rig files and the output directory must be at the same paths on every
worker (a shared file system), and each worker needs this project installed (the same
virtual environment).
"""

from __future__ import annotations

import logging
import multiprocessing
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor, Future, ProcessPoolExecutor, as_completed
from contextlib import contextmanager, suppress
from dataclasses import dataclass, replace
from pathlib import Path

from monitor.archive.engine import (
    FrameProgress,
    MonitorSetup,
    PerFileEngine,
    columnar_engine,
    monitor_setup,
)
from monitor.archive.inputs import LogInput
from monitor.archive.progress import EXTRA_HINT, ProgressBar, progress_bar
from monitor.archive.result import LogResult, failed_result, log_result
from monitor.archive.summary import summary_rows, write_csv, write_parquet
from monitor.errors import MonitorError, UsageError, one_line
from monitor.setup import MonitorSettings, event_lines, fault_unit, recording_sink
from monitor.sinks.base import Sink
from monitor.sinks.rerun import recording_parts

__all__ = ["CONNECT_TIMEOUT_S", "FLEET_PNG", "SUMMARY_CSV", "SUMMARY_PARQUET",
           "WORKER_TIMEOUT_S", "ArchiveRun", "cluster_client", "replay_one",
           "require_cluster_extra", "run_archive", "write_summary"]

_log = logging.getLogger("monitor.archive")

SUMMARY_PARQUET = "summary.parquet"
SUMMARY_CSV = "summary.csv"
FLEET_PNG = "fleet.png"
CONNECT_TIMEOUT_S = 10.0
"""How long to wait for the scheduler to answer."""
WORKER_TIMEOUT_S = 60.0
"""How long to wait for the cluster's first worker."""


def _open_outputs(events: Path | None, rrd: Path | None,
                  setup: MonitorSetup) -> Callable[[], list[Sink]]:
    """The engine's `open_sinks`: the log's JSON lines and recording, each if asked for."""
    def open_sinks() -> list[Sink]:
        sinks: list[Sink] = []
        try:
            if events is not None:
                events.parent.mkdir(parents=True, exist_ok=True)
                events.unlink(missing_ok=True)  # event_lines appends: start this run's file
                sink = event_lines(events, to_stdout=False,
                                   fault_unit=fault_unit(setup.rig, setup.cfg))
                if sink is not None:
                    sinks.append(sink)
            if rrd is not None:
                rrd.parent.mkdir(parents=True, exist_ok=True)
                recording = recording_sink(setup.cfg, setup.rig, rrd=rrd, replay=True)
                if recording is not None:
                    sinks.append(recording)
        except BaseException:
            for s in sinks:
                with suppress(Exception):
                    s.close()
            raise
        return sinks
    return open_sinks


def replay_one(path: Path, settings: MonitorSettings, *, events: Path | None = None,
               rrd: Path | None = None, engine: PerFileEngine = columnar_engine,
               progress: FrameProgress | None = None) -> LogResult:
    """One log through `engine`: its events as JSON lines to `events`, its recording to
    `rrd` (each if given). Never raises for the log: a log that cannot be read (missing,
    unsupported, empty, damaged before its first frame), or a setup that fails on this
    worker, gives a failed result with the reason (and no outputs of this log left
    behind); a log damaged after its first frame, or of which nothing was decoded, gives a
    failed result with the reason and what was read (its outputs kept)."""
    t0 = time.perf_counter()
    try:
        setup = monitor_setup(settings)
        run = engine(path, setup, _open_outputs(events, rrd, setup), progress)
    except Exception as exc:
        for p in (events, *(recording_parts(rrd) if rrd is not None else ())):
            if p is not None:
                with suppress(OSError):
                    p.unlink(missing_ok=True)
        reason = (one_line(exc) if isinstance(exc, MonitorError | OSError)
                  else f"internal error: {type(exc).__name__}: {one_line(exc)}")
        return failed_result(str(path), reason, wall_s=time.perf_counter() - t0)
    return log_result(str(path), run, wall_s=time.perf_counter() - t0,
                      events=None if events is None else str(events),
                      rrd=None if rrd is None else str(rrd),
                      rrd_parts=0 if rrd is None else len(recording_parts(rrd)))


def require_cluster_extra() -> None:
    """One line naming the extra when `distributed` is missing."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        raise UsageError(f"--cluster needs Dask distributed, the archive extra: "
                         f"{EXTRA_HINT}") from None


@contextmanager
def cluster_client(address: str) -> Iterator[Executor]:
    """A `concurrent.futures` executor on the Dask cluster whose scheduler is at `address`
    (`tcp://host:port`), once it has a worker."""
    require_cluster_extra()
    from distributed import Client

    try:
        client = Client(address, timeout=f"{CONNECT_TIMEOUT_S}s", set_as_default=False)
    except (OSError, TimeoutError, ValueError, TypeError) as exc:
        raise UsageError(f"--cluster: cannot reach a Dask scheduler at {address} "
                         f"({one_line(exc)})") from None
    try:
        try:
            client.wait_for_workers(1, timeout=WORKER_TIMEOUT_S)
        except (TimeoutError, OSError) as exc:
            raise UsageError(f"--cluster: the Dask scheduler at {address} has no worker "
                             f"(start one: dask worker {address}) ({one_line(exc)})") from None
        with client.get_executor(pure=False) as executor:
            yield executor
    finally:
        client.close()


@contextmanager
def _executor(jobs: int, cluster: str | None) -> Iterator[Executor]:
    if cluster is not None:
        with cluster_client(cluster) as ex:
            yield ex
    else:
        # Forked from a server that has imported the monitor once: no state of this
        # process (threads, open files) is copied, and N workers do not import it N times.
        context = multiprocessing.get_context("forkserver")
        context.set_forkserver_preload([__name__])
        with ProcessPoolExecutor(max_workers=jobs, mp_context=context) as ex:
            yield ex


@dataclass(frozen=True)
class ArchiveRun:
    """The logs' results in the order they were named, and the files the run wrote."""

    results: list[LogResult]
    written: list[Path]

    @property
    def failed(self) -> list[LogResult]:
        return [r for r in self.results if not r.ok]

    @property
    def frames(self) -> int:
        return sum(r.frames for r in self.results)


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


def run_archive(logs: Sequence[LogInput], settings: MonitorSettings, out: Path, *,
                rrd: bool = False, jobs: int = 1, cluster: str | None = None,
                engine: PerFileEngine = columnar_engine, show_progress: bool | None = None,
                fleet_png: bool = True) -> ArchiveRun:
    """Every log of `logs`, each with its events (and recording with `rrd`) under `out`,
    then the summary (Parquet, CSV) and the fleet PNG in `out`. `jobs` > 1 runs on as many
    local processes, `cluster` on a Dask cluster; otherwise in this process. A log that
    cannot be replayed is a failed row, logged once; the run goes on."""
    out = out.absolute()
    out.mkdir(parents=True, exist_ok=True)
    results: dict[int, LogResult] = {}
    sizes = {i: _size(log.path) for i, log in enumerate(logs)}

    def done(i: int, result: LogResult, bar: ProgressBar, *, counted: bool = False) -> None:
        # named as found, also in the reason (the worker was given the absolute path)
        result = replace(result, log=logs[i].log,
                         reason=result.reason.replace(str(logs[i].path), logs[i].log))
        results[i] = result
        bar.log_done(sizes[i], result.frames, counted=counted)
        if not result.ok:
            _log.warning("log failed: %s", result.reason)

    def task(log: LogInput) -> tuple[Path, MonitorSettings, Path, Path | None]:
        return (log.path, settings, log.events_path(out),
                log.rrd_path(out) if rrd else None)

    todo = [i for i, log in enumerate(logs) if log.problem is None]
    with progress_bar(len(logs), sum(sizes.values()), enabled=show_progress) as bar:
        for i, log in enumerate(logs):
            if log.problem is not None:
                done(i, failed_result(log.log, log.problem), bar)
        if cluster is None and jobs <= 1:
            for i in todo:
                path, s, ev, rec = task(logs[i])
                bar.start_log(sizes[i], path.suffix)
                done(i, replay_one(path, s, events=ev, rrd=rec, engine=engine,
                                   progress=bar.add_frames), bar, counted=True)
        elif todo:
            with _executor(jobs, cluster) as ex:
                futures: dict[Future[LogResult], int] = {}
                for i in todo:
                    path, s, ev, rec = task(logs[i])
                    futures[ex.submit(replay_one, path, s, events=ev, rrd=rec,
                                      engine=engine)] = i
                for f in as_completed(futures):
                    i = futures[f]
                    try:
                        result = f.result()
                    except Exception as exc:  # the worker died or could not run the task
                        result = failed_result(logs[i].log, f"worker failed: "
                                               f"{type(exc).__name__}: {one_line(exc)}")
                    done(i, result, bar)
    ordered = [results[i] for i in range(len(logs))]
    return ArchiveRun(ordered, write_summary(ordered, out, fleet_png=fleet_png))


def write_summary(results: Sequence[LogResult], out: Path, *,
                  fleet_png: bool = True) -> list[Path]:
    """The summary table (Parquet, CSV) and, with matplotlib, the fleet PNG in `out`."""
    rows, counters = summary_rows(results, out)
    written = [out / SUMMARY_PARQUET, out / SUMMARY_CSV]
    write_parquet(written[0], rows, counters)
    write_csv(written[1], rows, counters)
    if fleet_png:
        from monitor.archive.fleet import write_fleet_png

        try:
            write_fleet_png(out / FLEET_PNG, results)
            written.append(out / FLEET_PNG)
        except ImportError:
            _log.warning("no %s without matplotlib, the archive extra (%s)", FLEET_PNG,
                         EXTRA_HINT)
    return written
