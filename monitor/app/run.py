"""`motor-monitor run`: the daemon on a live bus.

Frames come from a python-can bus (`--interface/--channel`, or python-can's own
configuration). The bus is opened first, before the rig, the estimator and the sinks are
built (`monitor.runtime.livebus`): a thread receives on it meanwhile, so a start-up of a
few seconds (a small ARM computer, a cold disk) loses no frame; a bus that cannot be opened
yet is opened again after the configuration is checked, and its failure reported then. The
daemon itself is `monitor.app.daemon`, imported once the socket receives: it brings the
numerical libraries and the compiled kernels.
"""

from __future__ import annotations

import argparse
from typing import Any

from monitor.runtime.argtypes import add_monitor_options, positive_float, positive_int
from monitor.runtime.livebus import LiveBus, open_early
from monitor.runtime.signals import StopOnSignals

__all__ = ["add_command", "run_live"]


def run_live(args: argparse.Namespace) -> int:
    """The daemon: `monitor.app.daemon.serve` on a bus opened before its imports."""
    with StopOnSignals() as stop:
        live = LiveBus(args.interface, args.channel, args.bitrate, args.receive_buffer_kib)
        early = open_early(live)
        try:
            # the estimator's libraries load while the bus is received on
            from monitor.app import daemon

            return daemon.serve(args, stop, live, early)
        finally:
            if early is not None:
                early.handover()
            live.drop()

def add_command(sub: argparse._SubParsersAction[Any]) -> None:
    r = sub.add_parser("run", help="monitor a live CAN bus")
    r.add_argument("--interface", default=None, help="python-can interface (e.g. socketcan)")
    r.add_argument("--channel", default=None, help="channel (e.g. vcan0)")
    r.add_argument("--bitrate", type=int, default=None)
    r.add_argument("--events", default=None, help="append diagnosis events as JSON lines")
    r.add_argument("--record-dir", default=None, metavar="DIR",
                   help="record to rotating .rrd files in DIR (for unattended runs)")
    r.add_argument("--rotate-mb", type=positive_float, default=256.0,
                   help="start a new file past this size, MiB (default 256)")
    r.add_argument("--rotate-minutes", type=positive_float, default=60.0,
                   help="start a new file after this long, minutes (default 60)")
    r.add_argument("--keep", type=int, default=4000,
                   help="recordings kept in DIR, oldest deleted first (default 4000: a week "
                   "of a full 16-node bus in 256 MiB files; docs/operations.md, 'Recording "
                   "size and retention')")
    r.add_argument("--secoc-state", default=None, metavar="FILE",
                   help="persist SecOC freshness here (with --key): restarts resume at once")
    r.add_argument("--max-total-gb", type=positive_float, default=128.0,
                   help="recordings in DIR never exceed this, GiB (default 128: a week of a "
                   "full 16-node bus with a third to spare; the same for the raw logs in "
                   "--raw-dir; lower it on a small disk)")
    r.add_argument("--raw-dir", default=None, metavar="DIR",
                   help="write every received frame to rotating bus logs in DIR (the lossless "
                   "record: replay re-diagnoses them), same rotation and retention")
    r.add_argument("--raw-format", choices=("blf", "log"), default="blf",
                   help="raw bus log format: Vector BLF (default) or candump .log")
    r.add_argument("--record-flush-s", type=positive_float, default=None,
                   metavar="SECONDS",
                   help="hand the recording's buffers to the .rrd file (and --connect's "
                   "viewer) this often: what a SIGKILL can lose from it (default 0.1; above "
                   "0.25 only with --raw-dir, whose raw log keeps every frame; e.g. 2: larger "
                   "batches, files ~3.5x smaller before compaction)")
    r.add_argument("--receive-buffer-kib", type=positive_int, default=None,
                   metavar="KIB",
                   help="the socket's receive buffer (default: the kernel's, "
                   "net.core.rmem_default, a few hundred frames): larger, a daemon held up "
                   "for a moment catches up later instead of losing frames; above "
                   "net.core.rmem_max only with CAP_NET_ADMIN")
    r.add_argument("--metrics", default=None, metavar="FILE.prom",
                   help="write Prometheus metrics here every 5 s (node_exporter's textfile "
                   "collector directory); `motor-monitor status` reads them")
    r.add_argument("--nominal-bitrate", type=int, default=500_000,
                   help="the bus's bit rate for the bus-load figure when --bitrate is not "
                   "given (default 500000; vcan has none)")
    r.add_argument("--force", action="store_true",
                   help="write --events (appending), --rrd and --metrics even where a file "
                   "motor-monitor did not write is (without it, only its own files are "
                   "written over; an output is never one of the inputs)")
    r.add_argument("--data-bitrate", type=positive_float, default=None,
                   metavar="BITS_PER_S",
                   help="a CAN FD bus's data-phase bit rate, for the bus-load figure: FD frames "
                   "that switch rates (BRS) send their data at it (default: the nominal rate)")
    add_monitor_options(r)
    r.set_defaults(func=run_live)
