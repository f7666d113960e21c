"""Recording size benchmark: `python -m tests.bench.recording_size [--minutes 60] [--flush-s 2]`.

Bytes per hour for one node of standard traffic, the virtual ECU of sim_ecu at 100 Hz
(current 100 Hz, voltage 20 Hz, truth 100 Hz: 220 frames/s), in every form the daemon keeps:

* the raw bus log (`monitor.bus.rawlog.RotatingBusLog`, flushed every 0.1 s as the daemon
  does), candump ``.log`` and Vector ``.blf``;
* the live ``.rrd`` (`RerunSink`, fed by `MonitorPipeline`, ``maybe_flush`` every 50 ms of a
  simulated clock, as the daemon's loop calls it) at the default 0.1 s flush and at the
  larger one the daemon uses with ``--raw-dir`` (``--flush-s``);
* each of them compacted with `monitor.sinks.compact.compact_rrd` (``rerun rrd optimize``,
  what `RotatingRerunSink` does to every file it closes), with its time and the optimiser's
  peak memory.

The ECU runs the fault-outage-recovery pattern over and over (4 s fault-free, 4 s of 40 %
loss, 3 s outage, 5 s recovered: three state changes every 16 s), one continuous
simulation, so no value repeats that a real bus would not repeat. Frame time stamps are
what a kernel gives: the sample's nominal time plus a random delay (0-200 us), the frames of
one sample 222 us apart (a 111-bit frame at 500 kbit/s), to the microsecond. All files
hold the whole run as one file (rotation every ``--minutes``: the per-file costs, store info,
blueprint, static styles and the footer, are counted once per run).

A table, then the figures as JSON on the last line.
"""

from __future__ import annotations

import argparse
import json
import random
import resource
import shutil
import struct
import tempfile
import time
import warnings
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import can

from monitor.bus.codec import load_database
from monitor.bus.rawlog import RotatingBusLog
from monitor.pipeline import MonitorConfig, MonitorPipeline
from monitor.pipeline.feed import feed_log
from monitor.sinks.base import FanOut
from monitor.sinks.compact import compact_rrd
from monitor.sinks.rerun import DEFAULT_FLUSH_INTERVAL_S, RerunSink
from sim_ecu.ecu import VirtualECU
from sim_ecu.scenario import Scenario, scenario_from_dict

T0 = 1.7e9
RAW_FLUSH_S = 0.1  # the raw log's flush interval in the daemon
FRAME_S = 222e-6  # one 8-byte standard frame at 500 kbit/s
CYCLE_S = 16.0


def scenario(duration: float) -> Scenario:
    """fault-outage-recovery, repeated for `duration` seconds."""
    faults: list[dict[str, float]] = []
    start = 0.0
    while start + 4.0 < duration:
        faults.append({"start": start + 4.0, "end": min(start + 8.0, duration), "gamma": 0.4})
        if start + 8.0 < duration:
            faults.append({"start": start + 8.0, "end": min(start + 11.0, duration),
                           "gamma": 1.0})
        start += CYCLE_S
    return scenario_from_dict({"name": "fault-outage-recovery-repeated", "duration": duration,
                               "fault": faults})


def frames(duration: float, seed: int) -> Iterator[can.Message]:
    """The ECU's frames with kernel-like time stamps (see the module docstring)."""
    db = load_database()
    ecu = VirtualECU(None, db, 0, scenario(duration), seed=seed)
    rng = random.Random(seed)
    nominal = None
    delay = 0.0
    i = 0
    for m in ecu.frames(start_time=T0):
        if m.timestamp != nominal:
            nominal = m.timestamp
            delay = rng.uniform(0.0, 200e-6)
            i = 0
        m.timestamp = round(nominal + delay + i * FRAME_S, 6)
        m.channel = "can0"
        i += 1
        yield m


def logged(msgs: Iterable[can.Message], logs: Sequence[RotatingBusLog]
           ) -> Iterator[can.Message]:
    """`msgs`, each written to `logs` before it is handed on; the logs flushed every
    `RAW_FLUSH_S` of bus time, once the pipeline has taken the frame."""
    last_raw = T0
    for msg in msgs:
        for log in logs:
            log(msg)
        yield msg
        if msg.timestamp - last_raw >= RAW_FLUSH_S:
            last_raw = msg.timestamp
            for log in logs:
                log.flush()


def rrd_layout(path: Path) -> dict[str, int]:
    """Messages of an .rrd file by kind (the framing `monitor.sinks.salvage` walks): chunks
    (Arrow messages), their bytes, the footer's bytes."""
    data = path.read_bytes()
    off = 12
    count: Counter[int] = Counter()
    size: Counter[int] = Counter()
    while off + 16 <= len(data):
        kind, length = struct.unpack_from("<QQ", data, off)
        count[kind] += 1
        size[kind] += 16 + length
        off += 16 + length
        if kind == 0:
            break
    return {"chunks": count[2], "chunk_bytes": size[2], "footer_bytes": size[0] + 32}


def rrd_rows(path: Path) -> dict[str, int]:
    """Temporal rows per entity (the strict reader: the file must be whole)."""
    from rerun.chunk import RrdReader

    rows: Counter[str] = Counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for chunk in RrdReader(path).stream():
            if not chunk.is_static:
                rows[chunk.entity_path] += chunk.num_rows
    return dict(rows)


def record(out: Path, minutes: float, flush_s: float, seed: int) -> dict[str, Any]:
    """One run of the ECU through the pipeline into the raw logs and two recordings."""
    duration = minutes * 60.0
    db = load_database()
    raw_log = RotatingBusLog(out / "log", suffix=".log", max_bytes=None, max_age_s=None)
    raw_blf = RotatingBusLog(out / "blf", suffix=".blf", max_bytes=None, max_age_s=None)
    fast = RerunSink(rrd_path=out / "flush-fast.rrd", nodes=(0,),
                     flush_interval_s=DEFAULT_FLUSH_INTERVAL_S)
    slow = RerunSink(rrd_path=out / "flush-slow.rrd", nodes=(0,), flush_interval_s=flush_s)
    sink = FanOut([fast, slow])
    pipe = MonitorPipeline(db, MonitorConfig(nodes=(0,)), sink=sink)
    # The simulated monotonic clock: bus time, shifted to start where the sinks' clocks did.
    mono0 = time.monotonic()
    last_tick = T0

    def on_tick(ts: float) -> None:
        nonlocal last_tick
        last_tick = ts
        sink.maybe_flush(mono0 + (ts - T0))

    started = time.perf_counter()
    n = feed_log(pipe, logged(frames(duration, seed), (raw_log, raw_blf)), on_tick)
    pipe.emit_counters(last_tick)
    sink.close()
    raw_log.stop()
    raw_blf.stop()
    elapsed = time.perf_counter() - started
    (log_file,) = raw_log.files()
    (blf_file,) = raw_blf.files()
    return {"frames": n, "seconds": duration, "elapsed_s": elapsed,
            "estimated": pipe.counters.get("samples/estimated", 0),
            "files": {"raw .log": log_file, "raw .blf": blf_file,
                      "rrd live 0.1 s": out / "flush-fast.rrd",
                      f"rrd live {flush_s:g} s": out / "flush-slow.rrd"}}


def compact(src: Path, dst: Path) -> dict[str, float]:
    shutil.copyfile(src, dst)
    started = time.perf_counter()
    compact_rrd(dst)
    return {"seconds": time.perf_counter() - started,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=60.0, help="bus time simulated")
    ap.add_argument("--flush-s", type=float, default=2.0,
                    help="the larger flush interval (run --record-flush-s; 2 s with --raw-dir)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as td:
        out = Path(td)
        run = record(out, args.minutes, args.flush_s, args.seed)
        files: dict[str, Path] = run["files"]
        per_hour = 3600.0 / run["seconds"]
        compaction: dict[str, dict[str, float]] = {}
        # the smaller input first: the children's peak RSS is a running maximum
        for live in (f"rrd live {args.flush_s:g} s", "rrd live 0.1 s"):
            name = live.replace("live", "compacted from")
            files[name] = out / f"compacted-{len(compaction)}.rrd"
            compaction[name] = compact(files[live], files[name])
        rows_live = rrd_rows(files[f"rrd live {args.flush_s:g} s"])
        rows_compact = rrd_rows(files[f"rrd compacted from {args.flush_s:g} s"])
        candump = files["raw .log"].stat().st_size
        results: dict[str, dict[str, Any]] = {}
        for name, path in files.items():
            size = path.stat().st_size
            r: dict[str, Any] = {"bytes": size, "bytes_per_hour": size * per_hour,
                                 "x_candump": size / candump}
            if path.suffix == ".rrd":
                r.update(rrd_layout(path))
            if name in compaction:
                r.update({f"compaction_{k}": v for k, v in compaction[name].items()})
            results[name] = r
    print(f"one node, {run['frames']} frames ({run['frames'] / run['seconds']:.0f}/s) over "
          f"{args.minutes:g} min of bus time, {run['estimated']} samples estimated; "
          f"recorded in {run['elapsed_s']:.0f} s")
    print(f"{'file':28s} {'MB/hour':>9s} {'x candump':>10s} {'chunks':>7s} "
          f"{'footer kB':>10s} {'compaction':>18s}")
    for name, r in results.items():
        chunks = f"{r['chunks']:7d}" if "chunks" in r else f"{'-':>7s}"
        footer = f"{r['footer_bytes'] / 1e3:10.0f}" if "footer_bytes" in r else f"{'-':>10s}"
        comp = (f"{r['compaction_seconds']:5.1f} s {r['compaction_peak_rss_mb']:5.0f} MB"
                if "compaction_seconds" in r else "")
        print(f"{name:28s} {r['bytes_per_hour'] / 1e6:9.1f} {r['x_candump']:10.2f} {chunks} "
              f"{footer} {comp:>18s}")
    same = rows_live == rows_compact
    print(f"rows: {sum(rows_live.values())} in the live file, {sum(rows_compact.values())} "
          f"compacted ({'the same per entity' if same else 'DIFFERENT'}); per second: "
          + ", ".join(f"{e.removeprefix('/node/0/')} {rows_live[e] / run['seconds']:.1f}"
                      for e in sorted(rows_live) if e.startswith("/node/0/")))
    print(json.dumps({"benchmark": "recording_size", "minutes": args.minutes,
                      "flush_s": args.flush_s, "frames": run["frames"],
                      "estimated": run["estimated"], "rows_same_after_compaction": same,
                      "rows": rows_live, "results": results}))


if __name__ == "__main__":
    main()
