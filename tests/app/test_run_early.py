"""`motor-monitor run` opens its bus before it loads the estimator: the frames received
meanwhile reach the raw bus log whole and in order, also when a stop signal comes before
the loop's first receive (python-can's virtual interface; on vcan the daemon tests run it)."""

from __future__ import annotations

import threading
import time
import uuid
from pathlib import Path

import can

from monitor.app import daemon
from monitor.app.cli import build_parser
from monitor.runtime.livebus import LiveBus, open_early
from monitor.runtime.signals import StopOnSignals


def test_frames_received_while_loading_reach_the_raw_log_despite_an_early_stop(
        tmp_path: Path) -> None:
    channel = f"early-run-{uuid.uuid4().hex}"
    args = build_parser("run").parse_args(
        ["run", "--interface", "virtual", "--channel", channel, "--raw-dir", str(tmp_path),
         "--raw-format", "log"])
    live = LiveBus("virtual", channel, None)
    early = open_early(live)
    assert early is not None
    sender = can.Bus(interface="virtual", channel=channel)
    try:
        sent = [can.Message(arbitration_id=0x7A0, data=i.to_bytes(2, "little"),
                            is_extended_id=False) for i in range(200)]
        for msg in sent:
            sender.send(msg)
        time.sleep(0.3)  # received by the early thread
        stop = StopOnSignals(threading.Event())
        stop.event.set()  # SIGTERM while the daemon was loading
        assert daemon.serve(args, stop, live, early) == 0
    finally:
        sender.shutdown()
        live.drop()
    logs = sorted(tmp_path.glob("*.log"))
    assert logs, list(tmp_path.iterdir())
    got = [m for p in logs for m in can.LogReader(p)]
    assert [int.from_bytes(m.data, "little") for m in got] == list(range(200))
