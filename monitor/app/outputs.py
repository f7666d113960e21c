"""The sinks a command's options ask for: the Rerun recording (--rrd, --record-dir) or live
viewer (--connect), JSON lines of the events (--events), every sample to a file
(--samples), the log."""

from __future__ import annotations

import argparse
import sys
from collections.abc import MutableMapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from monitor.errors import MonitorError, UsageError
from monitor.pipeline import MonitorConfig, PlantSignals
from monitor.sinks.base import Sink
from monitor.sinks.compact import Compactor
from monitor.sinks.jsonl import JsonLinesSink
from monitor.sinks.rerun import (
    DEFAULT_FLUSH_INTERVAL_S,
    REPLAY_BATCH_SIZE,
    REPLAY_PART_BYTES,
    RerunSink,
)
from monitor.sinks.rotation import RotatingRerunSink

if TYPE_CHECKING:
    from monitor.rig import Rig

__all__ = ["MAX_UNBACKED_FLUSH_S", "count_compactions", "event_lines", "fault_unit",
           "plant_signals", "record_flush_s", "rerun_sink", "samples_sink"]

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


def plant_signals(rig: Rig | None) -> PlantSignals:
    """The names and units of the rig's inputs and outputs, as the outlets name them (units
    by `monitor.rig.check.signal_units`); our bus's without a rig."""
    if rig is None:
        return PlantSignals()
    from monitor.rig.check import signal_units

    units_in, units_out = signal_units(rig)
    return PlantSignals(
        inputs=tuple((r.signal, u) for r, u in zip(rig.inputs, units_in, strict=True)),
        outputs=tuple((r.signal, u) for r, u in zip(rig.outputs, units_out, strict=True)))


def fault_unit(rig: Rig | None, cfg: MonitorConfig) -> str | None:
    """The unit of the events' `fault_input` (`PlantSignals.fault_unit` of the model's
    fault inputs)."""
    return plant_signals(rig).fault_unit(cfg.plant().faults)


def rerun_sink(args: argparse.Namespace, cfg: MonitorConfig, *,
               replay: bool = False, rig: Rig | None = None) -> Sink | None:
    """Rotating files (--record-dir), one file (--rrd) and/or a live viewer (--connect), or
    None when none is asked for, its entities named after `rig`'s signals (our bus's
    without one). Rotated files are compacted in the background (`monitor.sinks.compact`).
    A `replay` records in chunks of `REPLAY_BATCH_SIZE` rows, into parts of
    `REPLAY_PART_BYTES`."""
    record_dir = getattr(args, "record_dir", None)
    if args.rrd and record_dir:
        raise UsageError("--rrd and --record-dir exclude each other (one file, or rotating files)")
    flush_interval_s = record_flush_s(args)
    if not (args.rrd or args.connect or record_dir):
        return None
    if args.rrd:
        parent = Path(args.rrd).parent
        if not parent.is_dir():
            raise UsageError(f"--rrd: directory {parent} does not exist")
    common: dict[str, Any] = {"nodes": cfg.nodes or (), "f1": cfg.thresholds.f1,
                              "f2": cfg.thresholds.f2, "connect_url": args.connect,
                              "flush_interval_s": flush_interval_s,
                              "signals": plant_signals(rig)}
    if replay:
        common["batch_size"] = REPLAY_BATCH_SIZE
        if args.rrd and not args.connect:
            common["part_bytes"] = REPLAY_PART_BYTES
    try:
        if record_dir:
            if not Path(record_dir).is_dir():
                raise UsageError(f"--record-dir: directory {record_dir} does not exist")
            return RotatingRerunSink(record_dir, max_bytes=int(args.rotate_mb * 2**20),
                                     max_age_s=args.rotate_minutes * 60.0, keep=args.keep,
                                     max_total_bytes=int(args.max_total_gb * 2**30),
                                     compactor=Compactor(), **common)
        return RerunSink(rrd_path=args.rrd, **common)
    except (ValueError, RuntimeError, OSError) as exc:
        raise MonitorError(f"cannot start the Rerun recording: {exc}") from None


def event_lines(path: str | None, *, to_stdout: bool, append: bool = True,
                fault_unit: str | None = None) -> Sink | None:
    """JSON lines of the diagnosis events to `path` (appended to it, or with `append`
    False replacing it), else to standard output if `to_stdout`, else none; `fault_unit`
    the unit of their `fault_input` (`fault_unit`). The caller has checked `path`
    (`monitor.app.paths.check_outputs`)."""
    if path:
        return JsonLinesSink(open(path, "a" if append else "w", encoding="utf-8"), owned=True,
                             fault_unit=fault_unit)
    return JsonLinesSink(sys.stdout, fault_unit=fault_unit) if to_stdout else None


def samples_sink(path: str | Path, rig: Rig, cfg: MonitorConfig) -> Sink:
    """Every estimated sample to `path` (.parquet or .csv: `monitor.sinks.samples`), its
    columns named after the rig's signals and units. The caller has checked `path`
    (`monitor.app.paths.check_outputs`) and its suffix."""
    from monitor.sinks.samples import SamplesFileSink, SampleTable

    signals = plant_signals(rig)
    table = SampleTable(inputs=signals.inputs, outputs=signals.outputs,
                        fault_inputs=cfg.plant().faults)
    return SamplesFileSink(path, table)
