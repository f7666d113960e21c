"""Live latency, from a frame on the bus to the MonitorDiagnosis it makes due:
`python -m tests.bench.latency [--seconds S] [--load-nodes N]`.

`motor-monitor run` (another process, as deployed) watches node 0 on a bus this bench
drives itself. The bench is node 0's ECU: it sends each 100 Hz sample's frames (the virtual
ECU's own, `sim_ecu.ecu.VirtualECU.frames`, healthy) and then listens on the same bus until
the next sample is due. A MonitorDiagnosis of node 0 arriving in that window was made due
by that sample's output frame (the daemon publishes a node's diagnosis at the sample at
which its publication period has passed, `monitor.diagnosis.rules.report`): its latency is
its receive time minus the frame's send time, both on this process's clock. That spans the
bus twice (to the daemon and back), the daemon's receive, decode, admission, estimator step,
diagnosis rules, and the bus publisher's send: what a rig that reads MonitorDiagnosis
waits. A diagnosis that comes after the next sample was sent is counted `late` (its frame
is ambiguous) and not in the percentiles.

``--load-nodes N`` adds a `sim-ecu` process per node 1..N on the same bus, and the daemon
monitors them too (`--nodes 0,1,...`): the latency of node 0 under that load. The first
`--warm-up` seconds are not measured (the daemon's start). Side by side in one run: no
load, then the load. The bus: python-can's ``udp_multicast`` on a random IPv4 group, or
``--interface socketcan --channel vcan0``. Last line JSON.
"""

from __future__ import annotations

import argparse
import json
import math
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import can
import numpy as np

from monitor.bus.codec import load_database
from sim_ecu.ecu import VirtualECU
from sim_ecu.scenario import BUILTIN_SCENARIOS
from tests.support import BIN

RATE = 100.0


def _frame_id(kind: str, node: int) -> int:
    """The arbitration ID of our bus's message `kind` of `node` (dbc/motor.dbc)."""
    return next(r.frame_id for r in load_database().routes if r.kind == kind and r.node == node)


def _daemon(interface: str, channel: str, nodes: list[int], work: Path
            ) -> subprocess.Popen[bytes]:
    err = (work / "daemon.err").open("w")
    return subprocess.Popen(
        [str(BIN / "motor-monitor"), "run", "--interface", interface, "--channel", channel,
         "--nodes", ",".join(map(str, nodes))],
        stdout=subprocess.DEVNULL, stderr=err)


def _load(interface: str, channel: str, node: int) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [str(BIN / "sim-ecu"), "--interface", interface, "--channel", channel, "--node",
         str(node), "--scenario", "healthy", "--duration", "0", "--seed", str(node)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _stop(proc: subprocess.Popen[bytes]) -> None:
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def measure(interface: str, channel: str, seconds: float, warm_up: float, load_nodes: int,
            work: Path) -> dict[str, Any]:
    """One daemon, node 0 driven by this bench (and `load_nodes` sim-ecu processes)."""
    nodes = list(range(load_nodes + 1))
    loads = [_load(interface, channel, n) for n in nodes[1:]]
    daemon = _daemon(interface, channel, nodes, work)
    bus = can.Bus(interface=interface, channel=channel, receive_own_messages=False)
    ecu = VirtualECU(None, load_database(), 0, BUILTIN_SCENARIOS["healthy"], rate=RATE,
                     truth=False)
    frames = ecu.frames(duration=math.inf)
    output_id, diagnosis_id = _frame_id("current", 0), _frame_id("diagnosis", 0)
    latencies: list[float] = []
    late = 0
    diagnoses = 0
    try:
        t0 = time.monotonic()
        first: float | None = None  # when the daemon's first diagnosis came
        k = 0
        pending: float | None = None  # send time of the last output frame
        while first is None or time.monotonic() - first < warm_up + seconds:
            if daemon.poll() is not None or (first is None and time.monotonic() - t0 > 300):
                raise SystemExit("latency bench: no diagnosis from the daemon: "
                                 + (work / "daemon.err").read_text()[-500:])
            measuring = first is not None and time.monotonic() - first >= warm_up
            sample = []
            while True:  # one sample's frames: up to and with its output (current) frame
                msg = next(frames)
                sample.append(msg)
                if msg.arbitration_id == output_id:
                    break
            for msg in sample:
                msg.timestamp = time.time()
                bus.send(msg)
            pending = time.monotonic()
            k += 1
            due = t0 + k / RATE
            while True:
                left = due - time.monotonic()
                if left <= 0:
                    break
                got = bus.recv(left)
                if got is None or got.arbitration_id != diagnosis_id:
                    continue
                diagnoses += 1
                if first is None:
                    first = time.monotonic()
                if measuring and pending is not None:
                    latencies.append(time.monotonic() - pending)
                    pending = None
                elif measuring:
                    late += 1
            # a diagnosis still in the socket belongs to an earlier frame: drain, count late
            while (got := bus.recv(0)) is not None:
                if got.arbitration_id == diagnosis_id:
                    diagnoses += 1
                    late += measuring
    finally:
        bus.shutdown()
        _stop(daemon)
        for p in loads:
            _stop(p)
    lat = np.array(latencies) * 1e3
    return {
        "load_nodes": load_nodes,
        "diagnoses": len(lat),
        "late": late,
        "p50_ms": round(float(np.percentile(lat, 50)), 3) if len(lat) else None,
        "p99_ms": round(float(np.percentile(lat, 99)), 3) if len(lat) else None,
        "max_ms": round(float(lat.max()), 3) if len(lat) else None,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=30.0, help="measured seconds per case")
    ap.add_argument("--warm-up", type=float, default=5.0,
                    help="seconds not measured after the first diagnosis")
    ap.add_argument("--load-nodes", type=int, default=7,
                    help="sim-ecu nodes beside node 0 in the loaded case (0: none)")
    ap.add_argument("--interface", default="udp_multicast")
    ap.add_argument("--channel", default=None)
    args = ap.parse_args(argv)
    channel = args.channel or (f"239.{random.randint(0, 255)}.{random.randint(0, 255)}."
                               f"{random.randint(1, 254)}")
    work = Path(tempfile.mkdtemp(prefix="latency-bench-"))
    cases = [0] + ([args.load_nodes] if args.load_nodes > 0 else [])
    results = [measure(args.interface, channel, args.seconds, args.warm_up, n, work)
               for n in cases]
    print(f"{'nodes':>5} {'diagnoses':>9} {'late':>5} {'p50 ms':>8} {'p99 ms':>8} "
          f"{'max ms':>8}")
    for r in results:
        print(f"{r['load_nodes'] + 1:>5} {r['diagnoses']:>9} {r['late']:>5} "
              f"{r['p50_ms']!s:>8} {r['p99_ms']!s:>8} {r['max_ms']!s:>8}")
    print(json.dumps({"benchmark": "latency", "interface": args.interface,
                      "seconds": args.seconds, "results": results}))
    return 0 if all(r["diagnoses"] for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
