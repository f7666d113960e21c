"""The monitor's setup from plain values: the rig (a rig file or the built-in one, its DBC
files replaced by another), the frame decoder (verifying SecOC when a key file is given),
the configuration (the rig's, with the nodes, the rate and the thresholds overridden) and
the outlets built from them (the Rerun recording, JSON lines of the events, every sample to
a table).

The command line turns its options into these arguments (`monitor.app.options`,
`monitor.app.outputs`); the archive replay's worker processes rebuild the same setup from
`MonitorSettings`, plain values that travel to another process or machine. A bad rig, DBC,
thresholds or key file is one `MonitorError` line, as on the command line.
"""

from __future__ import annotations

import importlib
import sys
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path
from typing import Any

from monitor.bus.codec import MotorDatabase
from monitor.bus.rigcodec import RigCodec
from monitor.bus.secoc import load_key
from monitor.diagnosis import Thresholds, load_thresholds
from monitor.errors import MonitorError, UsageError
from monitor.estimation.fuzzy_ukf import FuzzyUKFConfig
from monitor.pipeline import MonitorConfig, PlantSignals
from monitor.rig import Rig, build_decoder, build_model, builtin_rig, load_rig, model_of
from monitor.rig.check import signal_units
from monitor.sinks.base import Sink
from monitor.sinks.compact import Compactor
from monitor.sinks.jsonl import JsonLinesSink
from monitor.sinks.outlet import DEFAULT_FLUSH_INTERVAL_S, REPLAY_BATCH_SIZE, REPLAY_PART_BYTES

__all__ = ["MonitorSettings", "MonitorSetup", "Rotation", "event_lines", "fault_unit",
           "frame_decoder", "load_recording", "monitor_config", "monitor_setup", "plant_signals",
           "recording_sink", "samples_sink", "setup_rig"]


@dataclass(frozen=True)
class MonitorSettings:
    """The options that configure the monitor (`--rig`, `--dbc`, `--nodes`, `--rate`,
    `--thresholds`, `--key`), as plain values a worker process can rebuild the monitor
    from. File names must name the same files on every worker."""

    rig: str | None = None
    dbc: str | None = None
    nodes: tuple[int, ...] | None = None
    rate: float | None = None
    thresholds: str | None = None
    key: str | None = None


def setup_rig(rig_file: str | Path | None, *, dbc: str | Path | None = None,
              model_optional: bool = False) -> Rig:
    """The rig file at `rig_file`, else the built-in rig; `dbc` replaces its DBC files.
    `model_optional`: a rig file without [model] is taken (`load_rig`), for the command that
    learns one."""
    found = load_rig(rig_file, model_optional=model_optional) if rig_file else builtin_rig()
    if dbc and found.canopen is not None:
        raise UsageError(f"--dbc {dbc}: the rig {found.source} is a CANopen rig, described "
                         "by its EDS or DCF ([bus] eds / dcf), not by a DBC")
    return replace(found, dbc=(Path(dbc),)) if dbc else found


def frame_decoder(rig: Rig, key: str | Path | None = None) -> MotorDatabase | RigCodec:
    """The rig's frame decoder, verifying SecOC with the key file at `key` when given (a
    file only we can read; our own bus, or a rig whose messages have SecOC)."""
    return build_decoder(rig, secoc_key=load_key(key) if key else None)


def monitor_config(rig: Rig, *, nodes: tuple[int, ...] | None = None,
                   rate: float | None = None,
                   thresholds: str | Path | None = None) -> MonitorConfig:
    """The monitor's configuration: the rig's, with `nodes`, `rate` and the thresholds file
    at `thresholds` instead of the rig's where given."""
    spec, rig_rate = model_of(rig)  # a rig still without a model: one line, identify first
    d = rig.diagnosis
    return MonitorConfig(
        nodes=nodes if nodes is not None else rig.nodes,
        rate=rate if rate is not None else rig_rate,
        thresholds=load_thresholds(thresholds) if thresholds else Thresholds(d.f1, d.f2),
        dwell_s=d.dwell_s, hysteresis=d.hysteresis, significance=d.significance,
        silence_timeout_s=d.silence_timeout_s, model=build_model(rig),
        mismatch_window_s=d.mismatch_window_s, mismatch_dwell_s=d.mismatch_dwell_s,
        withhold_alarms_on_mismatch=d.withhold_alarms_on_mismatch,
        input_delay=spec.input_delay, input_window=spec.input_window,
        estimator=FuzzyUKFConfig(adaptive_noise=spec.adaptive_noise,
                                 noise_window=spec.noise_window_s, bias=spec.bias))


@dataclass(frozen=True)
class MonitorSetup:
    """What the settings build: the rig and the monitor's configuration, shared by every log
    of a process, and each log's decoder."""

    settings: MonitorSettings
    rig: Rig
    cfg: MonitorConfig
    shared_decoder: MotorDatabase | RigCodec | None = None
    """Without a SecOC key a decoder keeps no state between frames beyond its DBC: one
    serves every log (parsing the DBC takes longer than a short log)."""

    def decoder(self) -> MotorDatabase | RigCodec:
        """The decoder for the next log: the shared one, or with a key a fresh one (SecOC
        freshness must not carry from one log into another)."""
        if self.shared_decoder is not None:
            return self.shared_decoder
        return frame_decoder(self.rig, self.settings.key)


@lru_cache(maxsize=4)
def monitor_setup(settings: MonitorSettings) -> MonitorSetup:
    """The setup of `settings`, built once per process (raises `MonitorError` on a bad
    file, as the command line does)."""
    rig = setup_rig(settings.rig, dbc=settings.dbc)
    cfg = monitor_config(rig, nodes=settings.nodes, rate=settings.rate,
                         thresholds=settings.thresholds)
    shared = frame_decoder(rig) if settings.key is None else None
    return MonitorSetup(settings, rig, cfg, shared)


# -- outlets -------------------------------------------------------------------------------


def plant_signals(rig: Rig | None) -> PlantSignals:
    """The names and units of the rig's inputs and outputs, as the outlets name them (units
    by `monitor.rig.check.signal_units`); our bus's without a rig."""
    if rig is None:
        return PlantSignals()
    units_in, units_out = signal_units(rig)
    return PlantSignals(
        inputs=tuple((r.signal, u) for r, u in zip(rig.inputs, units_in, strict=True)),
        outputs=tuple((r.signal, u) for r, u in zip(rig.outputs, units_out, strict=True)))


def fault_unit(rig: Rig | None, cfg: MonitorConfig) -> str | None:
    """The unit of the events' `fault_input` (`PlantSignals.fault_unit` of the model's
    fault inputs)."""
    return plant_signals(rig).fault_unit(cfg.plant().faults)


@dataclass(frozen=True)
class Rotation:
    """Rotating recording files: the directory and when a file is closed and the oldest
    deleted (`monitor.sinks.rotation.RotatingRerunSink`)."""

    directory: str | Path
    max_bytes: int
    max_age_s: float
    keep: int
    max_total_bytes: int


def load_recording() -> None:
    """Import the Rerun sinks: rerun-sdk and the pandas its first archetype imports, half a
    second here, seconds in a slow guest, paid only by a monitor that records. The daemon
    calls it before its socket opens, so that no frame waits in the kernel's buffer (and
    overflows it) while it loads."""
    importlib.import_module("monitor.sinks.rerun")
    importlib.import_module("monitor.sinks.rotation")


def recording_sink(cfg: MonitorConfig, rig: Rig | None, *, rrd: str | Path | None = None,
                   connect: str | None = None, rotation: Rotation | None = None,
                   flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
                   replay: bool = False) -> Sink | None:
    """Rotating files (`rotation`), one file (`rrd`) and/or a live viewer (`connect`), or
    None when none is asked for, its entities named after `rig`'s signals (our bus's
    without one). Rotated files are compacted in the background (`monitor.sinks.compact`).
    A `replay` records in chunks of `REPLAY_BATCH_SIZE` rows, into parts of
    `REPLAY_PART_BYTES`. The caller has checked the file or directory; the recording that
    cannot start is one `MonitorError` line."""
    if not (rrd or connect or rotation):
        return None
    load_recording()
    from monitor.sinks.rerun import RerunSink
    from monitor.sinks.rotation import RotatingRerunSink

    common: dict[str, Any] = {"nodes": cfg.nodes or (), "f1": cfg.thresholds.f1,
                              "f2": cfg.thresholds.f2, "connect_url": connect,
                              "flush_interval_s": flush_interval_s,
                              "signals": plant_signals(rig)}
    if replay:
        common["batch_size"] = REPLAY_BATCH_SIZE
        if rrd and not connect:
            common["part_bytes"] = REPLAY_PART_BYTES
    try:
        if rotation is not None:
            return RotatingRerunSink(rotation.directory, max_bytes=rotation.max_bytes,
                                     max_age_s=rotation.max_age_s, keep=rotation.keep,
                                     max_total_bytes=rotation.max_total_bytes,
                                     compactor=Compactor(), **common)
        return RerunSink(rrd_path=None if rrd is None else str(rrd), **common)
    except (ValueError, RuntimeError, OSError) as exc:
        raise MonitorError(f"cannot start the Rerun recording: {exc}") from None


def event_lines(path: str | Path | None, *, to_stdout: bool, append: bool = True,
                fault_unit: str | None = None) -> Sink | None:
    """JSON lines of the diagnosis events to `path` (appended to it, or with `append`
    False replacing it), else to standard output if `to_stdout`, else none; `fault_unit`
    the unit of their `fault_input` (`fault_unit`). The caller has checked `path`
    (`monitor.runtime.paths.check_outputs`)."""
    if path:
        return JsonLinesSink(open(path, "a" if append else "w", encoding="utf-8"), owned=True,
                             fault_unit=fault_unit)
    return JsonLinesSink(sys.stdout, fault_unit=fault_unit) if to_stdout else None


def samples_sink(path: str | Path, rig: Rig, cfg: MonitorConfig) -> Sink:
    """Every estimated sample to `path` (.parquet or .csv: `monitor.sinks.samples`), its
    columns named after the rig's signals and units. The caller has checked `path`
    (`monitor.runtime.paths.check_outputs`) and its suffix."""
    from monitor.sinks.samples import SamplesFileSink, SampleTable  # pyarrow: only when asked

    signals = plant_signals(rig)
    table = SampleTable(inputs=signals.inputs, outputs=signals.outputs,
                        fault_inputs=cfg.plant().faults)
    return SamplesFileSink(path, table)
