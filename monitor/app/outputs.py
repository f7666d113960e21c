"""The sinks a command's options ask for: the Rerun recording (--rrd, --record-dir) or live
viewer (--connect), JSON lines of the events (--events), every sample to a file
(--samples), the log. The options are checked here; the sinks are built from their values
by `monitor.setup`."""

from __future__ import annotations

import argparse
from collections.abc import MutableMapping
from pathlib import Path
from typing import TYPE_CHECKING

from monitor.errors import UsageError
from monitor.pipeline import MonitorConfig
from monitor.setup import (
    Rotation,
    event_lines,
    fault_unit,
    plant_signals,
    recording_sink,
    samples_sink,
)
from monitor.sinks.base import Sink
from monitor.sinks.outlet import DEFAULT_FLUSH_INTERVAL_S

if TYPE_CHECKING:
    from monitor.rig import Rig

__all__ = ["MAX_UNBACKED_FLUSH_S", "count_compactions", "event_lines", "fault_unit",
           "plant_signals", "record_flush_s", "records", "rerun_sink", "samples_sink"]

MAX_UNBACKED_FLUSH_S = 0.25
"""The longest recording flush interval without the raw bus log: what a SIGKILL may lose."""


def record_flush_s(args: argparse.Namespace) -> float:
    """``--record-flush-s`` (0.1 s by default, `DEFAULT_FLUSH_INTERVAL_S`). Longer than
    `MAX_UNBACKED_FLUSH_S` only with ``--raw-dir``, whose raw bus log then bounds what a kill
    loses; only with a file to write (``--rrd``/``--record-dir``)."""
    given = getattr(args, "record_flush_s", None)
    if given is None:
        return DEFAULT_FLUSH_INTERVAL_S
    if not (args.rrd or getattr(args, "record_dir", None)):
        raise UsageError("--record-flush-s: there is no recording file to flush (give --rrd "
                         "or --record-dir)")
    if given > MAX_UNBACKED_FLUSH_S and not getattr(args, "raw_dir", None):
        raise UsageError(f"--record-flush-s: {given:g} s needs --raw-dir (without the raw bus "
                         f"log a kill may lose at most {MAX_UNBACKED_FLUSH_S:g} s of the "
                         f"recording)")
    return float(given)


def count_compactions(recording: Sink | None, counters: MutableMapping[str, int]) -> None:
    """Mirror the rotated files' compactions into `counters` (``recording/compacted``,
    ``recording/compaction_failed``, once they happen), from the thread that owns them."""
    compactor = getattr(recording, "compactor", None)
    if compactor is None:
        return
    stats = compactor.stats
    for name, value in (("recording/compacted", stats.compacted),
                        ("recording/compaction_failed", stats.failed)):
        if value:
            counters[name] = value


def records(args: argparse.Namespace) -> bool:
    """Whether the options ask for a recording: one file (--rrd), rotating files
    (--record-dir, the daemon's) or a live viewer (--connect)."""
    return bool(args.rrd or args.connect or getattr(args, "record_dir", None))


def rerun_sink(args: argparse.Namespace, cfg: MonitorConfig, *,
               replay: bool = False, rig: Rig | None = None) -> Sink | None:
    """Rotating files (--record-dir), one file (--rrd) and/or a live viewer (--connect), or
    None when none is asked for (`monitor.setup.recording_sink`), its entities named after
    `rig`'s signals (our bus's without one). A `replay` records in chunks, into parts."""
    record_dir = getattr(args, "record_dir", None)
    if args.rrd and record_dir:
        raise UsageError("--rrd and --record-dir exclude each other (one file, or rotating files)")
    flush_interval_s = record_flush_s(args)
    if not records(args):
        return None
    if args.rrd:
        parent = Path(args.rrd).parent
        if not parent.is_dir():
            raise UsageError(f"--rrd: directory {parent} does not exist")
    rotation = None
    if record_dir:
        if not Path(record_dir).is_dir():
            raise UsageError(f"--record-dir: directory {record_dir} does not exist")
        rotation = Rotation(record_dir, max_bytes=int(args.rotate_mb * 2**20),
                            max_age_s=args.rotate_minutes * 60.0, keep=args.keep,
                            max_total_bytes=int(args.max_total_gb * 2**30))
    return recording_sink(cfg, rig, rrd=None if rotation else args.rrd,
                          connect=args.connect, rotation=rotation,
                          flush_interval_s=flush_interval_s, replay=replay)
