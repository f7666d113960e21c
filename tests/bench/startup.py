"""Start-up to the first received frame: `python -m tests.bench.startup [--runs N] [--uml]`.

`motor-monitor run` is started against a bus on which a virtual ECU (`sim-ecu`, another
process, started first) already sends, and timed from its launch to

* READY: its sd_notify READY=1 (a NOTIFY_SOCKET of this bench), sent once the bus is open;
* the first frame it received: the first line of its raw bus log (`--raw-dir`,
  `--raw-format log`), whose time stamp is the kernel's receive time on the daemon's own
  socket. Frames sent before its socket opened are not its to receive.

Side by side in one run, interleaved (the same machine load for each):

* ``cold``: an empty numba cache (NUMBA_CACHE_DIR): every kernel compiled at start, as on
  a fresh install whose kernels were not made at install, or on another CPU;
* ``install``: the cache warmed as scripts/setup-venv.sh warms it
  (`python -m monitor.runtime.warm`, whose time is printed too);
* ``aot``: NUMBA_DISABLE_JIT=1, the hardened unit's mode (the ahead-of-time step kernel,
  no numba; "interpreted" is printed when that module is missing or stale).

The bus: python-can's ``udp_multicast`` interface on a random IPv4 group (the two processes
are apart as on a real bus; concurrent runs do not mix), or ``--interface socketcan
--channel vcan0``. ``--uml`` runs this bench inside a User-Mode Linux guest on vcan0
(tests/support/vcan_harness.py), where the vcan tests run the monitor: the host's virtual
environment and source through hostfs, so its cached kernels are the host's. On a loaded
machine every figure grows; compare the modes of one run. Last line JSON.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import random
import re
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import can

from tests.support import BIN

MODES = ("cold", "install", "aot")
#: Seconds a daemon may take to its first frame before the run counts as failed.
LIMIT_S = 300.0
RAW_LINE = re.compile(r"^\((\d+\.\d+)\)")


def _ecu(interface: str, channel: str) -> subprocess.Popen[bytes]:
    """The virtual ECU, sending node 0 until stopped; returned once its frames arrive."""
    proc = subprocess.Popen(
        [str(BIN / "sim-ecu"), "--interface", interface, "--channel", channel, "--node", "0",
         "--scenario", "healthy", "--duration", "0"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    bus = can.Bus(interface=interface, channel=channel)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            if bus.recv(0.5) is not None:
                return proc
    finally:
        bus.shutdown()
    proc.kill()
    _, err = proc.communicate()
    raise SystemExit(f"startup bench: sim-ecu sent nothing on {interface}:{channel}: "
                     f"{err.decode(errors='replace')[-500:]}")


def _stop(proc: subprocess.Popen[bytes], sig: signal.Signals, timeout: float) -> None:
    """Send `sig`; kill the process if it has not ended within `timeout` seconds."""
    proc.send_signal(sig)
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _first_frame(raw_dir: Path) -> float | None:
    """The receive time of the first frame in the daemon's raw bus log, if one is written."""
    for path in sorted(raw_dir.glob("*.log")):
        with path.open() as f:
            for line in f:
                m = RAW_LINE.match(line)
                if m:
                    return float(m.group(1))
    return None


def _start_once(mode: str, interface: str, channel: str, cache: Path,
                work: Path) -> dict[str, Any]:
    """One daemon start in `mode`: seconds to READY and to its first received frame."""
    raw_dir = work / f"raw-{mode}-{time.monotonic_ns()}"
    raw_dir.mkdir()
    addr = str(work / "notify.sock")
    with contextlib.suppress(FileNotFoundError):
        os.unlink(addr)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(addr)
    env = dict(os.environ, NOTIFY_SOCKET=addr, NUMBA_CACHE_DIR=str(cache),
               NUMBA_DISABLE_JIT="1" if mode == "aot" else "0")
    env.pop("MOTOR_MONITOR_KERNEL", None)
    err_path = work / f"{mode}.err"
    t0 = time.time()
    with err_path.open("w") as err:
        proc = subprocess.Popen(
            [str(BIN / "motor-monitor"), "run", "--interface", interface, "--channel", channel,
             "--nodes", "0", "--raw-dir", str(raw_dir), "--raw-format", "log"],
            env=env, stdout=subprocess.DEVNULL, stderr=err)
    ready: float | None = None
    first: float | None = None
    try:
        sock.settimeout(0.05)
        while time.time() - t0 < LIMIT_S and proc.poll() is None:
            with contextlib.suppress(TimeoutError):
                if b"READY=1" in sock.recv(4096) and ready is None:
                    ready = time.time() - t0
            first = _first_frame(raw_dir)
            if first is not None:
                break
        # the daemon writes its first frames after READY: that datagram may still wait
        sock.settimeout(0.5)
        while ready is None:
            try:
                got = sock.recv(4096)
            except TimeoutError:
                break
            if b"READY=1" in got:
                ready = time.time() - t0
    finally:
        _stop(proc, signal.SIGTERM, 60)
        sock.close()
    first = _first_frame(raw_dir)  # written at the latest when the daemon stopped
    log = err_path.read_text(errors="replace")
    kernel = "jit" if mode != "aot" else "interpreted" if "runs interpreted" in log else "aot"
    return {"mode": mode, "kernel": kernel,
            "ready_s": None if ready is None else round(ready, 3),
            "first_frame_s": None if first is None else round(first - t0, 3),
            "error": None if first is not None else log.strip().splitlines()[-1:]}


def _warm(cache: Path) -> float:
    """Warm `cache` as the install does; its seconds. Run outside the checkout, so that
    `-m` imports the package the daemon imports (a PYTHONPATH, or else the install)."""
    t0 = time.monotonic()
    proc = subprocess.run(
        [sys.executable, "-m", "monitor.runtime.warm", "--quiet"],
        env=dict(os.environ, NUMBA_CACHE_DIR=str(cache), NUMBA_DISABLE_JIT="0"),
        cwd=cache, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise SystemExit(f"startup bench: warming the cache failed: {proc.stderr.strip()}")
    return time.monotonic() - t0


def bench(interface: str, channel: str | None, runs: int,
          modes: tuple[str, ...] = MODES) -> dict[str, Any]:
    if channel is None:  # a group of the organisation-local scope, new for every run
        channel = f"239.{random.randint(0, 255)}.{random.randint(0, 255)}.{random.randint(1, 254)}"
    work = Path(tempfile.mkdtemp(prefix="startup-bench-"))
    ecu = _ecu(interface, channel)
    results: list[dict[str, Any]] = []
    warm_s: list[float] = []
    try:
        for i in range(runs):
            for mode in modes:
                cache = work / f"cache-{mode}-{i}"
                cache.mkdir()
                if mode == "install":
                    warm_s.append(_warm(cache))
                r = _start_once(mode, interface, channel, cache, work)
                results.append(r)
                print(f"run {i + 1} {mode:8s} ({r['kernel']}): READY {r['ready_s']} s, "
                      f"first frame {r['first_frame_s']} s"
                      + (f"  {r['error']}" if r["error"] else ""), flush=True)
    finally:
        _stop(ecu, signal.SIGINT, 30)
        shutil.rmtree(work, ignore_errors=True)
    summary: dict[str, Any] = {}
    for mode in modes:
        firsts = [r["first_frame_s"] for r in results
                  if r["mode"] == mode and r["first_frame_s"] is not None]
        readies = [r["ready_s"] for r in results if r["mode"] == mode and r["ready_s"]]
        summary[mode] = {
            "first_frame_s": round(statistics.median(firsts), 2) if firsts else None,
            "ready_s": round(statistics.median(readies), 2) if readies else None,
            "kernel": sorted({r["kernel"] for r in results if r["mode"] == mode}),
            "failed": sum(r["first_frame_s"] is None for r in results if r["mode"] == mode),
        }
    return {"benchmark": "startup", "interface": interface, "runs": runs,
            "cpus": os.cpu_count(), "load_1min": round(os.getloadavg()[0], 2),
            "install_warm_s": round(statistics.median(warm_s), 1) if warm_s else None,
            **summary}


def _in_uml(runs: int, modes: tuple[str, ...]) -> dict[str, Any]:
    from tests.support.paths import ROOT
    from tests.support.vcan_harness import run_on_vcan

    res = run_on_vcan(f"python -m tests.bench.startup --interface socketcan --channel vcan0 "
                      f"--runs {runs} --modes {','.join(modes)}",
                      timeout=runs * len(modes) * LIMIT_S, cwd=str(ROOT))
    print(res.stdout, end="")
    lines = res.stdout.strip().splitlines()
    if res.returncode != 0 or not lines:
        raise SystemExit(f"startup bench in UML ({res.backend}) failed: rc {res.returncode}\n"
                         f"{res.stderr[-2000:]}")
    return {**json.loads(lines[-1]), "where": f"{res.backend} guest"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=1, help="starts per mode (default 1)")
    ap.add_argument("--interface", default="udp_multicast")
    ap.add_argument("--channel", default=None,
                    help="default: a random IPv4 multicast group (udp_multicast)")
    ap.add_argument("--uml", action="store_true",
                    help="inside a User-Mode Linux guest, on vcan0 (tests/support/vcan_harness.py)")
    ap.add_argument("--modes", default=",".join(MODES),
                    help=f"which of {', '.join(MODES)} (default: all)")
    args = ap.parse_args()
    modes = tuple(m for m in args.modes.split(",") if m)
    if not modes or set(modes) - set(MODES):
        ap.error(f"--modes: each of {', '.join(MODES)}, comma-separated, got {args.modes!r}")
    out = _in_uml(args.runs, modes) if args.uml else {
        **bench(args.interface, args.channel, args.runs, modes), "where": "host"}
    print(json.dumps(out))
    if any(out[m]["failed"] for m in modes):
        sys.exit(1)


if __name__ == "__main__":
    main()
