"""`motor-monitor replay PATH...`: recorded buses (candump .log, Vector .asc or .blf), run
through the same pipeline as a live one, as fast as it goes.

One log file: its diagnosis events go to standard output as JSON lines (or to --events),
its recording to --rrd FILE, every estimated sample to --samples FILE (.parquet or .csv,
`monitor.sinks.samples`). Several logs, a directory or a glob pattern, or --out DIR:
the archive replay of `monitor.archive` (each log's events and, with --rrd, recording under
--out, a summary table and a fleet overview; --jobs N local processes or --cluster ADDRESS,
a Dask cluster). Exit status: 0 every log replayed, 1 some log could not be (its row in the
summary says why), 2 a mistake in the command line or the configuration.

Every output (--events, --rrd, --samples, each file under --out) is checked before the first
frame is read (`monitor.runtime.paths`): none is a log or a configuration file the replay reads,
and a file motor-monitor did not write is replaced only with --force.
"""

from __future__ import annotations

import argparse
import glob
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from monitor.app import options, outputs
from monitor.archive.engine import ENGINES
from monitor.archive.inputs import LogInput, find_logs
from monitor.archive.result import diagnosis_lines, log_result
from monitor.archive.run import (
    FLEET_PNG,
    SUMMARY_CSV,
    SUMMARY_PARQUET,
    require_cluster_extra,
    run_archive,
)
from monitor.bus.logfile import LogDamaged, suffix_list
from monitor.errors import ERROR_LINE_LIMIT, UsageError, one_line
from monitor.files import shown_path
from monitor.pipeline import counters as C
from monitor.rig import Rig
from monitor.runtime.argtypes import add_monitor_options
from monitor.runtime.paths import Kind, Output, check_directory, check_outputs, monitor_inputs
from monitor.setup import monitor_setup
from monitor.sinks.base import Sink
from monitor.sinks.log import LogSink
from monitor.sinks.rerun import recording_parts

__all__ = ["add_command", "run_replay"]


def _is_one_log(args: argparse.Namespace) -> bool:
    """One file named, no --out: today's single replay (stdout, --events, --rrd FILE)."""
    if args.out is not None or len(args.paths) != 1:
        return False
    path = args.paths[0]
    return not glob.has_magic(path) and not os.path.isdir(path)


def run_replay(args: argparse.Namespace) -> int:
    if _is_one_log(args):
        return _replay_one_log(args)
    return _replay_archive(args)


def _replay_one_log(args: argparse.Namespace) -> int:
    if args.rrd is True:
        raise UsageError("--rrd: give the recording's file name (or --out DIR for one "
                         "recording per log)")
    if args.jobs is not None or args.cluster is not None:
        raise UsageError("--jobs and --cluster replay logs into --out DIR: give --out DIR")
    samples = _samples_path(args.samples)
    setup = monitor_setup(options.settings(args))
    log_path = Path(args.paths[0])
    outs: list[Output] = []
    if args.events:
        outs.append(Output("--events", Path(args.events), "events"))
    if args.rrd:
        outs += [Output("--rrd", p, "rrd") for p in _recording_files(Path(args.rrd))]
    if samples is not None:
        outs.append(Output("--samples", samples, _SAMPLE_KINDS[samples.suffix.lower()]))
    check_outputs([("PATH", log_path), *monitor_inputs(setup.rig, args)], outs,
                  force=args.force)

    def open_sinks() -> list[Sink]:
        sinks: list[Sink] = [LogSink()]
        recording = outputs.rerun_sink(args, setup.cfg, replay=True, rig=setup.rig)
        events = outputs.event_lines(args.events, to_stdout=True, append=False,
                                     fault_unit=outputs.fault_unit(setup.rig, setup.cfg))
        table = (None if samples is None
                 else outputs.samples_sink(samples, setup.rig, setup.cfg))
        return sinks + [s for s in (recording, events, table) if s is not None]

    try:
        run = ENGINES[args.engine](log_path, setup, open_sinks)
    except LogDamaged as exc:  # empty, or damaged before its first frame: exit 1, not 2
        print(f"motor-monitor: error: {one_line(exc, limit=ERROR_LINE_LIMIT)}", file=sys.stderr)
        return 1
    # damaged after its first frame (what was read is written), or nothing decoded
    if run.failure is not None:
        print(f"motor-monitor: error: {one_line(run.failure, limit=ERROR_LINE_LIMIT)}",
              file=sys.stderr)
        return 1
    n, el = run.frames, run.feed_s
    c = C.Counters(run.counters)
    for line in diagnosis_lines(log_result(str(log_path), run, wall_s=el, events=None,
                                           rrd=None)):
        print(line, file=sys.stderr)
    print(f"motor-monitor: replayed {n} frames in {el:.2f} s ({n / max(el, 1e-9):.0f} frames/s): "
          f"{c.get(C.SAMPLES_ESTIMATED, 0)} estimated, {c.rejected_total()} rejected",
          file=sys.stderr)
    return 0


def _replay_archive(args: argparse.Namespace) -> int:
    if args.out is None:
        raise UsageError("several logs (a directory or a pattern) need --out DIR for their "
                         "events, recordings and summary")
    if args.events is not None:
        raise UsageError("--events names one file: with --out DIR each log's events go to "
                         "DIR/<log>.events.jsonl")
    if args.connect is not None:
        raise UsageError("--connect streams one log to a viewer: with --out DIR give --rrd "
                         "for one recording per log")
    if args.rrd is not None and args.rrd is not True:
        raise UsageError(f"--rrd takes no file name with --out DIR (each log gets its own "
                         f"DIR/<log>.rrd): {args.rrd!r}")
    if args.samples is not None:
        raise UsageError("--samples writes one log's samples: replay that log alone, "
                         "without --out")
    if args.jobs is not None and args.cluster is not None:
        raise UsageError("--jobs and --cluster exclude each other (local processes, or the "
                         "cluster's workers)")
    if args.cluster is not None:
        require_cluster_extra()
    out = Path(args.out)
    check_directory("--out", out, create=True)
    settings = options.settings(args)
    setup = monitor_setup(settings)  # a bad rig, DBC, threshold or key file: one line now
    setup.decoder()
    logs = find_logs(args.paths)
    _check_archive_outputs(args, setup.rig, logs, out)
    t0 = time.perf_counter()
    done = run_archive(logs, settings, out, rrd=args.rrd is True, jobs=args.jobs or 1,
                       cluster=args.cluster, engine=ENGINES[args.engine])
    el = time.perf_counter() - t0
    n, failed = done.frames, len(done.failed)
    print(f"motor-monitor: replayed {len(done.results) - failed} of {len(done.results)} logs "
          f"({failed} failed), {n} frames in {el:.2f} s ({n / max(el, 1e-9):.0f} frames/s); "
          f"summary: {', '.join(str(p) for p in done.written)}", file=sys.stderr)
    return 1 if failed else 0


_SAMPLE_KINDS: dict[str, Kind] = {".parquet": "samples-parquet", ".csv": "samples-csv"}


def _samples_path(given: str | bool | None) -> Path | None:
    """--samples FILE, its suffix checked (one `UsageError` line), or None."""
    if given is None:
        return None
    if given is True:
        raise UsageError("--samples: give the file's name (FILE.parquet or FILE.csv)")
    path = Path(str(given))
    if path.suffix.lower() not in _SAMPLE_KINDS:
        raise UsageError(f"--samples {shown_path(path)}: the file's name must end in "
                         ".parquet or .csv (the format)")
    return path


def _recording_files(rrd: Path) -> list[Path]:
    """The files a replay's recording to `rrd` writes or deletes: `rrd` and the parts an
    earlier recording split off beside it (`RerunSink` deletes them at start)."""
    return [rrd, *(p for p in recording_parts(rrd) if p != rrd)]


def _check_archive_outputs(args: argparse.Namespace, rig: Rig, logs: Sequence[LogInput],
                           out: Path) -> None:
    """Every file the archive replay writes under `out` (each log's events and recording,
    the summary, the fleet PNG), checked against every log and configuration file it reads
    (`check_outputs`)."""
    found = [log for log in logs if log.problem is None]
    outs: list[Output] = []
    for log in found:
        outs.append(Output("--out", log.events_path(out), "events", makes_directories=True))
        if args.rrd is True:
            outs += [Output("--out", p, "rrd", makes_directories=True)
                     for p in _recording_files(log.rrd_path(out))]
    outs += [Output("--out", out / SUMMARY_PARQUET, "summary-parquet", makes_directories=True),
             Output("--out", out / SUMMARY_CSV, "summary-csv", makes_directories=True),
             Output("--out", out / FLEET_PNG, "png", makes_directories=True)]
    check_outputs([*(("PATH", log.path) for log in found), *monitor_inputs(rig, args)], outs,
                  force=args.force)


def add_command(sub: argparse._SubParsersAction[Any]) -> None:
    p = sub.add_parser("replay", conflict_handler="resolve",
                       help="run bus logs (candump, ASC, BLF, TRC, MF4, gzip-compressed text "
                       "logs; or directories, or patterns of them) as fast as possible")
    p.add_argument("paths", nargs="+", metavar="PATH",
                   help=f"a log file ({suffix_list()}); several, directories (their logs, "
                   "recursively) or glob patterns replay the archive into --out DIR")
    p.add_argument("--events", default=None,
                   help="one log: JSON lines to this file, replaced (default: stdout)")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="each log's events (and recording) under DIR, named after the log's "
                   "path, and the summary (summary.parquet, summary.csv, fleet.png)")
    p.add_argument("--engine", choices=("columnar", "per-frame"), default="columnar",
                   help="columnar (default): each log read, decoded and estimated in chunks of "
                   "arrays, the same diagnosis and counters several times faster; per-frame: "
                   "frame by frame through the live daemon's pipeline")
    p.add_argument("--jobs", type=options.positive_int, default=None, metavar="N",
                   help="replay N logs at once in local processes (default 1)")
    p.add_argument("--cluster", default=None, metavar="ADDRESS",
                   help="replay on the Dask cluster whose scheduler is at ADDRESS, e.g. "
                   "tcp://10.0.0.5:8786 (the archive extra; workers share the paths)")
    add_monitor_options(p)
    # replaces the option's file-only form: with --out, a bare --rrd records every log
    p.add_argument("--rrd", nargs="?", const=True, default=None, metavar="FILE",
                   help="one log: record to this .rrd file; with --out: --rrd alone records "
                   "each log to DIR/<log>.rrd")
    p.add_argument("--samples", nargs="?", const=True, default=None, metavar="FILE",
                   help="one log: every estimated sample (time, node, inputs, outputs, "
                   "predicted outputs, gamma^ and f^ per faulty input, NIS, health state) to "
                   "FILE.parquet or FILE.csv, columns named after the rig's signals and units, "
                   "replaced")
    p.add_argument("--force", action="store_true",
                   help="replace --events, --rrd, --samples and the files under --out even if "
                   "motor-monitor did not write them (without it, only files it wrote are "
                   "replaced; an output is never one of the inputs)")
    p.set_defaults(func=run_replay)
