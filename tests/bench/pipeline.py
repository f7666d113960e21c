"""Pipeline throughput benchmark: `python -m tests.bench.pipeline [--frames N] [--stages ...]`.

`--stages` picks stages (default: all): decode, pipeline, pipeline+rerun, live,
live+rerun, columnar+rerun,
mf4+rerun, and the log readers alone, read-log, read-asc, read-blf, read-mf4
(`monitor.columnar.read_chunks` on the same frames as candump .log, Vector .asc and .blf,
the latter two written and read by python-can, and an ASAM MDF4 .mf4 written by asammdf),
read-mf4-python-can (python-can's `MF4Reader` alone on that .mf4, message by message),
e.g. ``--frames 10000000 --stages decode,columnar+rerun`` for the memory over 10^7 frames.

live and live+rerun are the daemon's receive loop with a backlog in its socket (what it
can sustain): receives of `RECEIVE_BATCH` frames, each handed to `BacklogFeed` as
`motor-monitor run` hands it (a backlog to the columnar engine on the pipeline's state),
the timeouts checked between receives; pipeline and pipeline+rerun feed every frame one by
one (the path of a frame at low load, whose latency `tests.bench.latency` measures).

The columnar replay (`monitor.columnar.replay_file`, with Rerun on) runs in the same run on
the same frames written to a candump .log (the file read is part of its time), beside the
per-frame pipeline and cantools' per-frame decoding; its memory is sampled at every chunk.
mf4+rerun is the same replay of the same frames written to an .mf4 (asammdf's columns read
a chunk at a time), beside read-mf4-python-can, python-can's reader of that file alone.

Frames per second in replay through decode, estimation, diagnosis and Rerun batching,
side by side in one run with cantools decoding alone and with the pipeline without Rerun,
all on the same frames (a virtual ECU's fault-outage-recovery run: current and truth at
100 Hz, voltage at 20 Hz, repeated with shifted timestamps; the repeat length is a
multiple of 16 samples so the alive counters stay consistent). Compared with the physical
limit of a saturated 1 Mbit/s bus: a standard 8-byte frame is 111 bits plus up to 24
stuff bits, so about 9,000 frames/s. Resident memory is sampled every 10 % of the run (the
columnar replay: every chunk) to show whether it stays flat: the growth from the samples'
second quarter (by then the readers' buffers, the compiled kernels and the allocators' pools
are in place) to their last, in MB per 10^6 frames. The recordings are written
as `motor-monitor replay --rrd` writes them (`REPLAY_BATCH_SIZE` rows a chunk). Last line
JSON.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import can
import numpy as np

from monitor.app.daemon import RECEIVE_BATCH
from monitor.bus.codec import MotorDatabase, load_database
from monitor.columnar import read_chunks, replay_file
from monitor.columnar.live import BacklogFeed
from monitor.pipeline import MonitorConfig, MonitorPipeline
from monitor.pipeline.feed import TICK_S
from monitor.sinks.base import FanOut, Sink
from monitor.sinks.rerun import REPLAY_BATCH_SIZE, REPLAY_PART_BYTES, RerunSink, recording_parts
from sim_ecu.ecu import VirtualECU
from sim_ecu.scenario import load_scenario
from tests.support.log_readers import write_mf4

BUS_LIMIT_FPS = 1_000_000 / 111  # 8-byte standard frames, no stuff bits: the upper bound
STAGES = ("decode", "pipeline", "pipeline+rerun", "live", "live+rerun", "columnar+rerun",
          "mf4+rerun", "read-log", "read-asc", "read-blf", "read-mf4", "read-mf4-python-can")
MF4_TARGET_FPS = 200_000


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        pages = int(f.read().split()[1])
    return pages * 4096 / 2**20


def _slope_mb_per_1e6(rss: list[float], frames: int) -> float:
    """Memory growth from the second quarter of a run's evenly spaced samples to the last
    (medians: one sample taken while a chunk's arrays were alive, or after the last one was
    freed, does not tip it)."""
    if len(rss) < 8:
        return float("nan")
    q = len(rss) // 4
    second, last = np.median(rss[q:2 * q]), np.median(rss[-q:])
    return float((last - second) / (frames * 0.5 / 1e6))


def _stream(base: list[can.Message], period: float, n: int) -> Iterator[can.Message]:
    k = 0
    rep = 0
    while True:
        shift = rep * period
        for m in base:
            if k >= n:
                return
            yield can.Message(timestamp=m.timestamp + shift, arbitration_id=m.arbitration_id,
                              data=m.data, is_extended_id=False, channel=m.channel)
            k += 1
        rep += 1


def _write_log(base: list[can.Message], period: float, n: int, path: Path) -> None:
    """The benchmark's frames as a candump -L log."""
    with path.open("w") as f:
        lines = []
        for m in _stream(base, period, n):
            data = m.data.hex().upper()
            lines.append(f"({m.timestamp:.6f}) can0 {m.arbitration_id:03X}#{data}\n")
            if len(lines) >= 65536:
                f.writelines(lines)
                lines = []
        f.writelines(lines)


def _write_mf4(base: list[can.Message], period: float, n: int, path: Path) -> None:
    """The benchmark's frames as an MF4 file written by asammdf, column by column (the
    frames of `_stream`: the base run repeated, shifted by `period`)."""
    reps = -(-n // len(base))
    shift = np.repeat(np.arange(reps) * period, len(base))[:n]
    t = np.tile([m.timestamp - base[0].timestamp for m in base], reps)[:n] + shift
    ids = np.tile([m.arbitration_id for m in base], reps)[:n]
    length = np.tile([len(m.data) for m in base], reps)[:n]
    payload = np.zeros((len(base), 8), np.uint8)
    for i, m in enumerate(base):
        payload[i, :len(m.data)] = np.frombuffer(bytes(m.data), np.uint8)
    write_mf4(path, t, ids, np.tile(payload, (reps, 1))[:n], length)


def _python_can_mf4(path: Path, n: int) -> dict[str, object]:
    """python-can's MF4Reader alone: frames per second as messages."""
    rss = [_rss_mb()]
    t0 = time.perf_counter()
    frames = 0
    with can.io.MF4Reader(str(path)) as reader:
        for _ in reader:
            frames += 1
            if frames % 100_000 == 0:
                rss.append(_rss_mb())
    el = time.perf_counter() - t0
    rss.append(_rss_mb())
    assert frames == n, (path, frames, n)
    return {"fps": n / el, "rss_mb": rss, "file_mb": path.stat().st_size / 2**20}


class _RSS(Sink):
    """Samples resident memory whenever counters arrive (once per chunk)."""

    def __init__(self) -> None:
        self.rss: list[float] = []

    def on_counters(self, t: float, counters: object) -> None:
        self.rss.append(_rss_mb())


def _columnar(db: MotorDatabase, log: Path, n: int, tmp: Path) -> dict[str, object]:
    probe = _RSS()
    probe.rss.append(_rss_mb())
    rerun = RerunSink(rrd_path=tmp / "columnar.rrd", nodes=(0,), batch_size=REPLAY_BATCH_SIZE,
                      part_bytes=REPLAY_PART_BYTES)
    t0 = time.perf_counter()
    res = replay_file(log, db, MonitorConfig(nodes=(0,)), FanOut([rerun, probe]))
    rerun.close()
    el = time.perf_counter() - t0
    assert res.frames == n and res.columnar
    return {"fps": n / el, "rss_mb": probe.rss,
            "estimated": res.counters.get("samples/estimated", 0),
            "transitions": sum(v for k, v in res.counters.items()
                               if k.startswith("transitions/")),
            "rrd_mb": sum(p.stat().st_size for p in recording_parts(tmp / "columnar.rrd"))
            / 2**20}


def _read(log: Path, n: int) -> dict[str, object]:
    """The reader alone: frames per second into chunks of arrays."""
    rss = [_rss_mb()]
    t0 = time.perf_counter()
    frames = 0
    for chunk in read_chunks(log):
        frames += len(chunk.t)
        rss.append(_rss_mb())
    el = time.perf_counter() - t0
    assert frames == n, (log, frames, n)
    return {"fps": n / el, "rss_mb": rss, "file_mb": log.stat().st_size / 2**20}


def _write_with_python_can(base: list[can.Message], period: float, n: int,
                           path: Path) -> None:
    with can.Logger(str(path)) as writer:
        for m in _stream(base, period, n):
            writer.on_message_received(m)


def _run(kind: str, db: MotorDatabase, base: list[can.Message], period: float, n: int,
         tmp: Path) -> dict[str, object]:
    rss: list[float] = []
    step = max(1, n // 10)
    if kind == "decode":
        t0 = time.perf_counter()
        for i, m in enumerate(_stream(base, period, n)):
            db.decode_can(m)
            if i % step == 0:
                rss.append(_rss_mb())
        el = time.perf_counter() - t0
        return {"fps": n / el, "rss_mb": rss}
    sink = None
    if kind.endswith("+rerun"):
        sink = RerunSink(rrd_path=tmp / "bench.rrd", nodes=(0,), batch_size=REPLAY_BATCH_SIZE)
    pipe = MonitorPipeline(db, MonitorConfig(nodes=(0,)), sink=sink)
    last = 0.0
    t0 = time.perf_counter()
    if kind.startswith("live"):
        # the live loop with a backlog in the socket: receives of RECEIVE_BATCH frames, each
        # handed to BacklogFeed (the columnar engine on the pipeline's state), the timeouts
        # checked between receives
        feed = BacklogFeed(pipe)
        batch: list[can.Message] = []
        for i, m in enumerate(_stream(base, period, n)):
            batch.append(m)
            if len(batch) == RECEIVE_BATCH:
                feed.feed(batch)
                batch = []
                ts = m.timestamp
                if ts - last >= TICK_S:
                    last = ts
                    pipe.tick(ts)
            if i % step == 0:
                rss.append(_rss_mb())
        feed.feed(batch)
    else:
        for i, m in enumerate(_stream(base, period, n)):
            pipe.feed(m)
            ts = m.timestamp
            if ts - last >= TICK_S:  # what replay does: timeouts every 50 ms of bus time
                last = ts
                pipe.tick(ts)
            if i % step == 0:
                rss.append(_rss_mb())
    if sink is not None:
        sink.close()
    el = time.perf_counter() - t0
    out: dict[str, object] = {"fps": n / el, "rss_mb": rss,
                              "estimated": pipe.counters.get("samples/estimated", 0),
                              "transitions": sum(v for k, v in pipe.counters.items()
                                                 if k.startswith("transitions/"))}
    if sink is not None:
        out["rrd_mb"] = (tmp / "bench.rrd").stat().st_size / 2**20
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=1_000_000)
    ap.add_argument("--stages", default=",".join(STAGES),
                    help=f"comma-separated, from {', '.join(STAGES)} (default: all)")
    args = ap.parse_args()
    stages = [x.strip() for x in args.stages.split(",") if x.strip()]
    unknown = sorted(set(stages) - set(STAGES))
    if unknown or "decode" not in stages:
        ap.error(f"--stages: unknown {', '.join(unknown)}" if unknown
                 else "--stages: decode is the reference every ratio needs")
    db = load_database()
    ecu = VirtualECU(None, db, 0, load_scenario("fault-outage-recovery"), seed=1)
    base = list(ecu.frames(start_time=1.7e9))
    period = 16.0  # seconds of the scenario; 1600 samples = 100 x 16 counter values
    results = {}
    with tempfile.TemporaryDirectory() as td:
        log = Path(td) / "bench.log"
        _write_log(base, period, args.frames, log)
        # warm up the compiled kernels (numba's cache) outside the timing
        head = Path(td) / "head.log"
        _write_log(base, period, 5000, head)
        replay_file(head, db, MonitorConfig(nodes=(0,)))
        for kind in stages:
            if kind in ("decode", "pipeline", "pipeline+rerun", "live", "live+rerun"):
                results[kind] = _run(kind, db, base, period, args.frames, Path(td))
            elif kind == "columnar+rerun":
                results[kind] = _columnar(db, log, args.frames, Path(td))
            elif kind in ("mf4+rerun", "read-mf4", "read-mf4-python-can"):
                mf4 = Path(td) / "bench.mf4"
                if not mf4.exists():
                    _write_mf4(base, period, args.frames, mf4)
                    replay_file(head, db, MonitorConfig(nodes=(0,)))  # asammdf imported
                if kind == "mf4+rerun":
                    results[kind] = _columnar(db, mf4, args.frames, Path(td))
                elif kind == "read-mf4":
                    results[kind] = _read(mf4, args.frames)
                else:
                    results[kind] = _python_can_mf4(mf4, args.frames)
            elif kind == "read-log":
                results[kind] = _read(log, args.frames)
            else:
                other = Path(td) / f"bench.{kind.removeprefix('read-')}"
                _write_with_python_can(base, period, args.frames, other)
                results[kind] = _read(other, args.frames)
                other.unlink()
    dec = float(results["decode"]["fps"])  # type: ignore[arg-type]
    print(f"{'stage':22s} {'frames/s':>10s} {'x bus limit':>12s} {'x decode':>9s} "
          f"{'RSS MB first->last (max)':>26s} {'MB/1e6 frames':>17s}")
    for kind, r in results.items():
        fps = float(r["fps"])  # type: ignore[arg-type]
        rss = r["rss_mb"]
        assert isinstance(rss, list)
        growth = _slope_mb_per_1e6(rss, args.frames)
        r["rss_growth_mb_per_1e6"] = growth
        print(f"{kind:22s} {fps:10.0f} {fps / BUS_LIMIT_FPS:12.2f} {fps / dec:9.2f} "
              f"{rss[0]:9.1f} -> {rss[-1]:.1f} ({max(rss):.1f}) {growth:17.2f}")
    ratios: dict[str, object] = {}
    if "columnar+rerun" in results:
        col = float(results["columnar+rerun"]["fps"])  # type: ignore[arg-type]
        ratios.update(columnar_over_decode=col / dec, columnar_target_fps=300_000,
                      columnar_meets_target=col >= 300_000)
        print(f"columnar/cantools decode {col / dec:.2f}x")
        if "pipeline+rerun" in results:
            per = float(results["pipeline+rerun"]["fps"])  # type: ignore[arg-type]
            ratios["columnar_over_per_frame"] = col / per
            print(f"columnar/per-frame {col / per:.2f}x")
    if "live+rerun" in results:
        live = float(results["live+rerun"]["fps"])  # type: ignore[arg-type]
        ratios.update(live_over_decode=live / dec, live_meets_target=live >= dec)
        print(f"live (backlog) with Rerun/cantools decode {live / dec:.2f}x (target >= 1.0)")
    if "mf4+rerun" in results:
        mf4_fps = float(results["mf4+rerun"]["fps"])  # type: ignore[arg-type]
        ratios.update(mf4_target_fps=MF4_TARGET_FPS, mf4_meets_target=mf4_fps >= MF4_TARGET_FPS)
        if "read-mf4-python-can" in results:
            alone = float(results["read-mf4-python-can"]["fps"])  # type: ignore[arg-type]
            ratios["mf4_replay_over_python_can_reader"] = mf4_fps / alone
            print(f"mf4 replay/python-can's MF4Reader alone {mf4_fps / alone:.2f}x")
    print(json.dumps({"benchmark": "pipeline", "frames": args.frames,
                      "bus_limit_fps": BUS_LIMIT_FPS, "ratios": ratios, "results": results}))


if __name__ == "__main__":
    main()
