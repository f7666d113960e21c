"""The daemon of `motor-monitor run` (`monitor.app.run`, which opens the bus first) on a
live bus.

An interface that fails (deleted, down) is closed and reopened with back-off while the
pipeline keeps its state; the outage is counted and logged. SIGINT and SIGTERM stop the
loop; the sinks are flushed and closed so that `rerun rrd verify` passes on the recording.
Under systemd (Type=notify) the loop reports READY, STATUS, WATCHDOG and STOPPING
(`monitor.runtime.notify`).

The wiring: bus -> `MonitorPipeline` -> `FanOut` of sinks (the log, the bus publisher, the
Rerun recording, JSON lines). This module owns the sinks' life (periodic flush, close); the
pipeline only hands them events. Every output is checked before anything is written
(`_check_outputs`).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Callable
from pathlib import Path

import can

from monitor.app import options, outputs
from monitor.bus.codec import MotorDatabase
from monitor.bus.faults import socket_drops
from monitor.bus.rawlog import RotatingBusLog
from monitor.bus.rigcodec import RigCodec
from monitor.bus.stats import BusStats
from monitor.columnar.live import BacklogFeed
from monitor.errors import UsageError
from monitor.pipeline import Counters, MonitorPipeline
from monitor.pipeline import counters as C
from monitor.pipeline.counters import DecodeWatch
from monitor.pipeline.feed import TICK_S
from monitor.rig import Rig
from monitor.runtime.canbus import BusError, frames_waiting, receive_batch
from monitor.runtime.freshness import FreshnessSaver
from monitor.runtime.livebus import EarlyReceiver, LiveBus
from monitor.runtime.notify import Notifier
from monitor.runtime.paths import Output, check_directory, check_outputs, monitor_inputs
from monitor.runtime.signals import StopOnSignals
from monitor.setup import load_recording
from monitor.sinks.base import FanOut, Sink
from monitor.sinks.journal import JournalSink, journal_available
from monitor.sinks.log import LogSink
from monitor.sinks.metrics import MetricsSink
from monitor.sinks.publisher import BusPublisher

__all__ = ["RECEIVE_BATCH", "serve"]

log = logging.getLogger("motor_monitor")

FRESHNESS_SAVE_PERIOD_S = 5.0
RECEIVE_BATCH = 512  # frames per receive at most: the clocks are read between batches
# (a backlog goes to the columnar engine in one call: 512 frames there take ~5 ms)
#: Waits between reopens of a failed interface: doubling from the first to the last, which
#: bounds how long after a link comes back its frames are still missed (a reopen is a socket
#: and a bind: cheap enough to try four times a second through a long outage).
REOPEN_FIRST_S = 0.05
REOPEN_MAX_S = 0.25
DRAIN_LIMIT_S = 2.0  # at most this long taking a backlog at stop (inside systemd's stop timeout)


def _freshness(db: MotorDatabase | RigCodec, path: str | None) -> FreshnessSaver | None:
    """--secoc-state: restore the receive counters, then save them periodically, so a
    restarted monitor resumes verification at once and an old recorded sync cannot roll its
    freshness back."""
    if path is None:
        return None
    if db.secoc is None:
        raise UsageError("--secoc-state needs --key (there is no freshness without SecOC)")
    restored = db.secoc.load_state(path)
    log.warning("SecOC freshness: %s", "fresh start, first sync trusted" if restored is None
                else f"{restored} counters restored from {path}")
    return FreshnessSaver(db.secoc, path, FRESHNESS_SAVE_PERIOD_S)


def _raw_log(args: argparse.Namespace) -> RotatingBusLog | None:
    if not args.raw_dir:
        return None
    if not Path(args.raw_dir).is_dir():
        raise UsageError(f"--raw-dir: directory {args.raw_dir} does not exist")
    try:
        return RotatingBusLog(args.raw_dir, suffix=f".{args.raw_format}",
                              max_bytes=int(args.rotate_mb * 2**20),
                              max_age_s=args.rotate_minutes * 60.0, keep=args.keep,
                              max_total_bytes=int(args.max_total_gb * 2**30))
    except (OSError, ValueError) as exc:
        raise UsageError(f"--raw-dir: cannot start the raw bus log: {exc}") from None


def _check_outputs(args: argparse.Namespace, rig: Rig) -> None:
    """Every file and directory the run writes, before anything is opened: none is a
    configuration file it reads (`monitor.runtime.paths`), and a file motor-monitor did not
    write is written only with --force (--events is appended to: a restarted daemon goes
    on with its own file). The SecOC state is read before it is written: its reader
    refuses a file that is not one."""
    inputs = monitor_inputs(rig, args)
    outs: list[Output] = []
    if args.events:
        outs.append(Output("--events", Path(args.events), "events", append=True))
    if args.rrd:
        outs.append(Output("--rrd", Path(args.rrd), "rrd"))
    if args.metrics:
        outs.append(Output("--metrics", Path(args.metrics), "metrics"))
    if args.secoc_state:
        outs.append(Output("--secoc-state", Path(args.secoc_state), None))
    check_outputs(inputs, outs, force=args.force)
    for option, directory in (("--record-dir", args.record_dir), ("--raw-dir", args.raw_dir)):
        if directory:
            check_directory(option, directory, inputs, rotated=True)


def serve(args: argparse.Namespace, stop: StopOnSignals, live: LiveBus,
          early: EarlyReceiver | None) -> int:
    """The daemon on `live` (opened here where it could not be before), whose `early`
    receiver holds the frames received while this was loading; returns at a stop signal."""
    rig = options.rig(args)
    _check_outputs(args, rig)
    db = options.database(args, rig)
    fresh = _freshness(db, args.secoc_state)
    cfg = options.monitor_config(args, rig)
    outputs.record_flush_s(args)  # its mistakes before anything opens
    # Load the compiled estimator, and the recording's library when it records, before a
    # socket opens that no thread receives on: frames arriving meanwhile would pile up in
    # the kernel's buffer and be dropped.
    MonitorPipeline(db, cfg)
    if outputs.records(args):
        load_recording()
    if live.bus is None:
        live.reopen()
    try:
        raw = _raw_log(args)
        recording = outputs.rerun_sink(args, cfg, rig=rig)
        events = outputs.event_lines(args.events, to_stdout=False,
                                     fault_unit=outputs.fault_unit(rig, cfg))
    except BaseException:
        live.drop()
        raise
    counters = Counters()
    bus_stats = BusStats(bitrate=float(args.bitrate or args.nominal_bitrate),
                         data_bitrate=args.data_bitrate)
    watch = DecodeWatch(cfg.nodes, cfg.silence_timeout_s, time.monotonic())
    sinks: list[Sink] = [LogSink()]
    if journal_available():
        sinks.append(JournalSink())
    if args.metrics:
        try:
            sinks.append(MetricsSink(args.metrics, bus=bus_stats, watch=watch,
                                     signals=outputs.plant_signals(rig)))
        except ValueError as exc:
            live.drop()
            raise UsageError(f"--metrics: {exc}") from None
    if isinstance(db, MotorDatabase):  # MonitorDiagnosis frames exist on our bus only
        sinks.append(BusPublisher(db, live.send, counters))
    sinks += [s for s in (recording, events) if s is not None]
    sink = FanOut(sinks)
    pipe = MonitorPipeline(db, cfg, sink=sink, counters=counters)
    try:
        _loop(args, pipe, sink, live, early, fresh, stop, raw, bus_stats, recording, watch)
    finally:
        if raw is not None:
            raw.stop()
        if fresh is not None:
            failed = fresh.final()
            if failed is not None:
                log.error("%s", failed)
        pipe.emit_counters(time.time())  # the last second's counters, into the recording
        sink.close()
        live.drop()
        c = pipe.counters
        why = f"signal {stop.signum}" if stop.signum else "end"
        print(f"motor-monitor: stopped ({why}): {c.get(C.FRAMES_RECEIVED, 0)} frames, "
              f"{c.get(C.SAMPLES_ESTIMATED, 0)} estimated, {c.rejected_total()} rejected, "
              f"{c.get(C.PUBLISH_SENT, 0)} diagnosis frames sent", file=sys.stderr)
    return 0


def _loop(args: argparse.Namespace, pipe: MonitorPipeline, sink: Sink, live: LiveBus,
          early: EarlyReceiver | None, fresh: FreshnessSaver | None, stop: StopOnSignals,
          raw: RotatingBusLog | None, bus_stats: BusStats, recording: Sink | None,
          watch: DecodeWatch) -> None:
    where = f"{args.interface or '<config>'}:{args.channel or '<config>'}"
    log.warning("monitoring %s, nodes %s", where,
                "all" if pipe.cfg.nodes is None else pipe.cfg.nodes)
    notifier = Notifier.from_environment()
    notifier.ready(f"monitoring {where}")
    last_status = 0.0
    last_tick = 0.0
    drained = True  # the last receive found the socket empty
    newest = last_clock = 0.0  # the newest frame's time stamp; the time last ticked at
    dropped_before = 0  # socket drops of sockets closed before the current one
    backoff = REOPEN_FIRST_S
    down_since: float | None = None

    feed = BacklogFeed(pipe)  # a few frames one by one, a backlog in one call

    def take(msgs: list[can.Message]) -> None:
        for msg in msgs:
            if raw is not None:
                raw(msg)  # every frame, whatever the pipeline makes of it
            bus_stats(msg)
        feed.feed(msgs)

    clock_due = True  # read the clocks (system calls) before the next receive
    batches = 0  # since the clocks were last read
    try:
        while not stop.event.is_set():
            if clock_due:
                batches = 0
                mono = time.monotonic()
                notifier.maybe_ping(mono)
                now = time.time()
                if now - last_tick >= TICK_S:
                    last_tick = now
                    # Timeouts are judged where the reading is: while a backlog waits in the
                    # socket (a daemon held up for a moment), the time is that of the newest
                    # frame read, so the daemon's own lag never looks like a silent node.
                    # Drained at the last receive is not enough: a daemon held up since (a busy
                    # CPU, a long batch) has frames waiting, and the wall clock would find
                    # their node silent. The socket is asked again, without waiting.
                    waiting = live.bus is not None and frames_waiting(live.bus)
                    last_clock = now if drained and not waiting else max(newest, last_clock)
                    pipe.tick(last_clock)
                    # nothing decoded since the silence timeout: said once (and a metric)
                    said = watch.check(mono, pipe.counters,
                                       {n: nm.samples for n, nm in pipe.nodes.items()})
                    if said is not None:
                        log.warning("nothing decoded: %s", said)
                    sink.maybe_flush(mono)
                    outputs.count_compactions(recording, pipe.counters)
                    if raw is not None:
                        raw.maybe_flush(mono)
                    if fresh is not None:
                        fresh.maybe_write(mono)
                    drops = None if live.bus is None else socket_drops(live.bus)
                    if drops is not None:  # the kernel's count for this socket, since it opened
                        pipe.socket_drops(dropped_before + drops)
                if mono - last_status >= 1.0:
                    last_status = mono
                    notifier.status(status_line(pipe, live.bus is not None))
            bus = live.bus
            if bus is None:
                clock_due = True
                if stop.event.wait(backoff):
                    break
                try:
                    live.reopen()
                except BusError as exc:
                    backoff = min(REOPEN_MAX_S, backoff * 2)
                    log.debug("still down: %s", exc)
                continue  # back only once a receive succeeds (a down link binds fine)
            msgs: list[can.Message] = []
            try:
                if early is not None:  # first what was received while the daemon loaded
                    msgs, failure = early.handover()
                    early = None
                    if failure is not None:
                        raise failure
                else:
                    receive_batch(bus, TICK_S, RECEIVE_BATCH, msgs)
            except (can.CanError, OSError) as exc:
                if msgs:  # read before the failure: kept like every other
                    newest = max(newest, max(m.timestamp for m in msgs))
                    take(msgs)
                clock_due = True
                dropped_before = pipe.counters.get(C.BUS_SOCKET_DROPS, 0)
                live.drop()
                if down_since is None:  # a new outage
                    log.warning("CAN interface failed: %s; reconnecting", exc)
                    pipe.interface_failed(time.time(), str(exc))
                    down_since = time.monotonic()
                else:  # reopened, but still down (e.g. ENETDOWN on a link set down)
                    backoff = min(REOPEN_MAX_S, backoff * 2)
                    log.debug("still down: %s", exc)
                continue
            if down_since is not None:
                outage = time.monotonic() - down_since
                log.warning("CAN interface back after %.1f s", outage)
                pipe.interface_back(time.time(), outage)
                backoff = REOPEN_FIRST_S
                down_since = None
            drained = len(msgs) < RECEIVE_BATCH
            if msgs:
                newest = max(newest, max(m.timestamp for m in msgs))
                take(msgs)
            # The clocks are read after a quiet wait, once the frames' own (kernel) time
            # stamps pass the next tick, and every few batches whatever the time stamps say.
            batches += 1
            clock_due = not msgs or newest - last_tick >= TICK_S or batches >= 8
        if early is not None:  # a stop signal came while the daemon loaded: its frames too
            take(early.handover()[0])
        if live.bus is not None:
            _drain(live.bus, take, time.time())
    finally:
        notifier.stopping("flushing the recording")


def _drain(bus: can.BusABC, take: Callable[[list[can.Message]], None], stopped: float
           ) -> None:
    """On a stop signal, take what the socket already holds: the frames received before
    the signal (a daemon behind its bus has a backlog), up to the first batch that reaches
    past it or `DRAIN_LIMIT_S` of work, so no frame the kernel had before the stop is
    missing from the recording."""
    deadline = time.monotonic() + DRAIN_LIMIT_S
    n = 0
    while time.monotonic() < deadline:
        msgs: list[can.Message] = []
        failure: Exception | None = None
        try:
            receive_batch(bus, 0.0, RECEIVE_BATCH, msgs)
        except (can.CanError, OSError) as exc:
            failure = exc
        if msgs:  # also those read before a failure
            take(msgs)
        n += len(msgs)
        if failure is not None:
            log.debug("draining the socket at stop: %s", failure)
            break
        if not msgs or msgs[-1].timestamp > stopped:
            break
    if n:
        log.info("took %d frame(s) left in the socket at stop", n)


def status_line(pipe: MonitorPipeline, bus_up: bool) -> str:
    """One line for systemctl status: traffic, rejections and each node's state."""
    c = pipe.counters
    nodes = " ".join(f"{n}={nm.state.label}" for n, nm in sorted(pipe.nodes.items()))
    return (f"{'bus up' if bus_up else 'bus DOWN, reconnecting'}; "
            f"{c.get(C.FRAMES_RECEIVED, 0)} frames, {c.get(C.SAMPLES_ESTIMATED, 0)} estimated, "
            f"{c.rejected_total()} rejected, {c.get(C.E2E_LOST_FRAMES, 0)} lost, "
            f"{c.get(C.BUS_ERROR_FRAMES, 0)} error frames; nodes {nodes or 'none yet'}")


