"""Where a backlog pays off in columns: `python -m tests.bench.backlog [--frames N]`.

The same frames (a virtual ECU's fault-outage-recovery run on our bus, node 0) fed to a
fresh `MonitorPipeline` one by one (`pipe.feed`), and through the `ColumnarEngine` on a
pipeline in chunks of 1, 3, 10, 30, 100 and 1,000 frames: microseconds per frame and per
chunk of each, side by side in one run. The live daemon's threshold
(`monitor.columnar.live.COLUMNAR_MIN_FRAMES`) sits above the chunk size where the columnar
engine's per-frame cost falls below the per-frame engine's. Last line JSON.
"""

from __future__ import annotations

import argparse
import json
import time

from monitor.bus.codec import load_database
from monitor.columnar.chunk import chunk_from_messages
from monitor.columnar.live import COLUMNAR_MIN_FRAMES
from monitor.columnar.replay import ColumnarEngine
from monitor.pipeline import MonitorConfig, MonitorPipeline
from sim_ecu.ecu import VirtualECU
from sim_ecu.scenario import load_scenario

SIZES = (1, 3, 10, 30, 100, 1000)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=6000)
    args = ap.parse_args()
    db = load_database()
    ecu = VirtualECU(None, db, 0, load_scenario("fault-outage-recovery"), seed=1)
    frames = list(ecu.frames(start_time=1.7e9))[:args.frames]
    cfg = MonitorConfig(nodes=(0,))
    pipe = MonitorPipeline(db, cfg)  # the kernels loaded before any timing
    ColumnarEngine(pipe).chunk(chunk_from_messages(frames[:200]))
    results: dict[str, float] = {}
    pipe = MonitorPipeline(load_database(), cfg)
    t0 = time.perf_counter()
    for m in frames:
        pipe.feed(m)
    per_frame = (time.perf_counter() - t0) / len(frames) * 1e6
    results["per_frame_us"] = per_frame
    print(f"{'path':24s} {'us/frame':>9s} {'us/chunk':>9s} {'/ per-frame':>11s}")
    print(f"{'per-frame engine':24s} {per_frame:9.1f} {'':>9s} {1.0:11.2f}")
    for size in SIZES:
        chunks = [chunk_from_messages(frames[i:i + size]) for i in range(0, len(frames), size)]
        engine = ColumnarEngine(MonitorPipeline(load_database(), cfg), ticks=False)
        t0 = time.perf_counter()
        for c in chunks:
            engine.chunk(c)
        el = time.perf_counter() - t0
        us = el / len(frames) * 1e6
        results[f"columnar_{size}_us"] = us
        print(f"{'columnar, chunks of ' + str(size):24s} {us:9.1f} {el / len(chunks) * 1e6:9.0f} "
              f"{us / per_frame:11.2f}")
    print(f"threshold in the daemon: {COLUMNAR_MIN_FRAMES} frames")
    print(json.dumps({"benchmark": "backlog", "frames": len(frames),
                      "threshold": COLUMNAR_MIN_FRAMES, "results": results}))


if __name__ == "__main__":
    main()
