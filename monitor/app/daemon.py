"""`motor-monitor run` (a live bus) and `motor-monitor replay LOG` (a recorded one).

Both build the same `MonitorPipeline`; they differ in where frames come from and where
the diagnosis goes (the bus, or JSON lines).

Live: frames come from a python-can bus (`--interface/--channel`, or python-can's own
configuration: CAN_INTERFACE / CAN_CHANNEL / CAN_CONFIG and its config file). An
interface that fails (deleted, down) is closed and reopened with back-off while the
pipeline keeps its state; the outage is counted and logged. SIGINT and SIGTERM stop the
loop; the recording is flushed and closed so that `rerun rrd verify` passes.
"""

from __future__ import annotations

import argparse
import logging
import math
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import suppress
from pathlib import Path
from struct import error as StructError
from types import FrameType
from typing import IO, Any

import can

from monitor.bus.faults import socket_drops
from monitor.bus.codec import MotorDatabase, load_database
from monitor.diagnosis import DEFAULT_THRESHOLDS, Thresholds, load_thresholds
from monitor.app.notify import Notifier
from monitor.pipeline import BUS_EVENTS, DiagnosisEvent, MonitorConfig, MonitorPipeline
from monitor.sinks.rerun import NullSink, RerunSink, RotatingRerunSink, Sink
from monitor.bus.secoc import load_key

__all__ = ["BusError", "add_commands", "open_bus", "read_log"]

log = logging.getLogger("motor_monitor")

LOG_SUFFIXES = (".log", ".asc", ".blf")


class BusError(Exception):
    """The CAN interface cannot be opened; the message is one line."""


def open_bus(interface: str | None, channel: str | None, bitrate: int | None = None) -> can.BusABC:
    """A python-can bus; missing interface/channel come from python-can's configuration."""
    kwargs: dict[str, Any] = {}
    if interface:
        kwargs["interface"] = interface
    if channel:
        kwargs["channel"] = channel
    if bitrate:
        kwargs["bitrate"] = bitrate
    can_log = logging.getLogger("can")
    level = can_log.level
    if not log.isEnabledFor(logging.DEBUG):  # its ERROR record would be a second line
        can_log.setLevel(logging.CRITICAL + 1)
    try:
        return can.Bus(**kwargs)
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as exc:
        where = f"{interface or '<config>'}:{channel or '<config>'}"
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise BusError(f"cannot open CAN interface {where}: {msg}") from None
    finally:
        can_log.setLevel(level)


def _positive(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (v > 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"must be positive: {text!r}")
    return v


def _rate(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid float value: {text!r}") from None
    if not (math.isfinite(v) and 0.0 < v <= 100_000.0):
        raise argparse.ArgumentTypeError(f"must be a rate in Hz, 0 < rate <= 100000: {text!r}")
    return v


def _thresholds(path: str | None) -> Thresholds:
    return load_thresholds(path) if path else DEFAULT_THRESHOLDS


def _nodes(text: str) -> tuple[int, ...] | None:
    if text == "all":
        return None
    try:
        nodes = tuple(sorted({int(x) for x in text.split(",") if x.strip()}))
    except ValueError:
        raise argparse.ArgumentTypeError(f"nodes must be 'all' or e.g. 0,1,2: {text!r}") from None
    if not nodes or any(not 0 <= n <= 15 for n in nodes):
        raise argparse.ArgumentTypeError(f"node numbers must lie in 0..15: {text!r}")
    return nodes


def _make_sink(args: argparse.Namespace, cfg: MonitorConfig) -> Sink:
    """Where the live streams go: rotating files (--record-dir), one file (--rrd) and/or a
    live viewer (--connect), or nowhere."""
    record_dir = getattr(args, "record_dir", None)
    if args.rrd and record_dir:
        raise BusError("--rrd and --record-dir exclude each other (one file, or rotating files)")
    if not (args.rrd or args.connect or record_dir):
        return NullSink()
    if args.rrd:
        parent = Path(args.rrd).parent
        if not parent.is_dir():
            raise BusError(f"--rrd: directory {parent} does not exist")
    common: dict[str, Any] = {"nodes": cfg.nodes or (), "f1": cfg.thresholds.f1,
                              "f2": cfg.thresholds.f2, "connect_url": args.connect}
    try:
        if record_dir:
            if not Path(record_dir).is_dir():
                raise BusError(f"--record-dir: directory {record_dir} does not exist")
            return RotatingRerunSink(record_dir, max_bytes=int(args.rotate_mb * 2**20),
                                     max_age_s=args.rotate_minutes * 60.0, keep=args.keep,
                                     max_total_bytes=int(args.max_total_gb * 2**30), **common)
        return RerunSink(rrd_path=args.rrd, **common)
    except (ValueError, RuntimeError, OSError) as exc:
        raise BusError(f"cannot start the Rerun recording: {exc}") from None


def _config(args: argparse.Namespace) -> MonitorConfig:
    return MonitorConfig(nodes=args.nodes, rate=args.rate, thresholds=_thresholds(args.thresholds))


def _event_writer(path: str | None, default: IO[str] | None) -> tuple[
        Callable[[DiagnosisEvent], None] | None, IO[str] | None]:
    fh: IO[str] | None = open(path, "a", encoding="utf-8") if path else default  # noqa: SIM115
    if fh is None:
        return None, None
    out = fh

    def write(ev: DiagnosisEvent) -> None:
        out.write(ev.to_json() + "\n")
        out.flush()

    return write, (fh if path else None)


class _Stop:
    """SIGINT/SIGTERM set an event; the main loop ends at its next turn."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signal: int | None = None

    def install(self) -> None:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._handler)

    def _handler(self, signum: int, frame: FrameType | None) -> None:
        self.signal = signum
        self.event.set()


def _database(args: argparse.Namespace) -> MotorDatabase:
    """The DBC, with SecOC verification when --key is given (a key file only we can read)."""
    key = load_key(args.key) if args.key else None
    return load_database(args.dbc, secoc_key=key)


class _FreshnessStore:
    """SecOC freshness persisted to --secoc-state, so a restarted monitor resumes verification
    at once and an old recorded sync cannot roll its freshness back."""

    PERIOD_S = 5.0

    def __init__(self, db: MotorDatabase, path: str | None) -> None:
        self.secoc = db.secoc
        self.path = path
        self.last = time.monotonic()
        if path is None:
            return
        if self.secoc is None:
            raise BusError("--secoc-state needs --key (there is no freshness without SecOC)")
        restored = self.secoc.load_state(path)
        log.warning("SecOC freshness: %s", "fresh start, first sync trusted" if restored is None
                    else f"{restored} counters restored from {path}")

    def maybe_save(self, now_monotonic: float, force: bool = False) -> None:
        if self.path is None or self.secoc is None:
            return
        if not force and now_monotonic - self.last < self.PERIOD_S:
            return
        self.last = now_monotonic
        try:
            self.secoc.save_state(self.path)
        except ValueError as exc:  # SecOCError: logged, the monitor keeps running
            log.error("cannot save SecOC freshness: %s", exc)


def run_live(args: argparse.Namespace) -> int:
    db = _database(args)
    fresh = _FreshnessStore(db, args.secoc_state)
    cfg = _config(args)
    stop = _Stop()
    stop.install()
    # Load the compiled estimator before the socket opens: frames arriving meanwhile
    # would pile up in the kernel's buffer and be dropped.
    MonitorPipeline(db, cfg)
    bus = open_bus(args.interface, args.channel, args.bitrate)
    holder: dict[str, can.BusABC | None] = {"bus": bus}

    def publish(msg: can.Message) -> None:
        b = holder["bus"]
        if b is None:
            raise can.CanOperationError("interface is down")
        b.send(msg, timeout=0.01)

    try:
        sink = _make_sink(args, cfg)
        on_event, events_fh = _event_writer(args.events, None)
        pipe = MonitorPipeline(db, cfg, sink=sink, publish=publish, on_event=on_event)
    except BaseException:
        bus.shutdown()
        raise
    where = f"{args.interface or '<config>'}:{args.channel or '<config>'}"
    log.warning("monitoring %s, nodes %s", where, "all" if cfg.nodes is None else cfg.nodes)
    notifier = Notifier.from_environment()
    notifier.ready(f"monitoring {where}")
    last_status = 0.0
    last_tick = 0.0
    dropped_before = 0  # socket drops of sockets closed before the current one
    backoff = 0.1
    down_since: float | None = None
    try:
        while not stop.event.is_set():
            mono = time.monotonic()
            notifier.maybe_ping(mono)
            now = time.time()
            if now - last_tick >= 0.05:  # also while the bus is down: silence, flushing
                last_tick = now
                pipe.tick(now)
                sink.maybe_flush(mono)
                fresh.maybe_save(mono)
                b = holder["bus"]
                drops = None if b is None else socket_drops(b)
                if drops is not None:  # the kernel's count for this socket, since it opened
                    pipe.counters["bus/socket_drops"] = dropped_before + drops
            if mono - last_status >= 1.0:
                last_status = mono
                notifier.status(_status_line(pipe, holder["bus"] is not None))
            b = holder["bus"]
            if b is None:
                if stop.event.wait(backoff):
                    break
                try:
                    holder["bus"] = open_bus(args.interface, args.channel, args.bitrate)
                except BusError as exc:
                    backoff = min(2.0, backoff * 2)
                    log.debug("still down: %s", exc)
                continue  # back only once a receive succeeds (a down link binds fine)
            try:
                msg = b.recv(timeout=0.05)
            except (can.CanError, OSError) as exc:
                dropped_before = pipe.counters.get("bus/socket_drops", 0)
                with suppress(Exception):
                    b.shutdown()
                holder["bus"] = None
                if down_since is None:  # a new outage
                    pipe.counters.inc("bus/outages")
                    log.warning("CAN interface failed: %s; reconnecting", exc)
                    sink.log_event(BUS_EVENTS, time.time(), f"CAN interface failed: {exc}",
                                   "ERROR")
                    down_since = time.monotonic()
                else:  # reopened, but still down (e.g. ENETDOWN on a link set down)
                    backoff = min(2.0, backoff * 2)
                    log.debug("still down: %s", exc)
                continue
            if down_since is not None:
                outage = time.monotonic() - down_since
                pipe.counters.inc("bus/reconnects")
                log.warning("CAN interface back after %.1f s", outage)
                sink.log_event(BUS_EVENTS, time.time(), f"CAN interface back after {outage:.1f} s",
                               "WARN")
                backoff = 0.1
                down_since = None
            if msg is not None:
                pipe.feed(msg)
    finally:
        notifier.stopping("flushing the recording")
        fresh.maybe_save(time.monotonic(), force=True)
        pipe.log_counters(time.time())  # the last second's counters, into the recording
        sink.close()
        b = holder["bus"]
        if b is not None:
            with suppress(Exception):
                b.shutdown()
        if events_fh is not None:
            events_fh.close()
        c = pipe.counters
        why = f"signal {stop.signal}" if stop.signal else "end"
        print(f"motor-monitor: stopped ({why}): {c.get('frames/received', 0)} frames, "
              f"{c.get('samples/estimated', 0)} estimated, "
              f"{sum(v for k, v in c.items() if k.startswith('rejected/'))} rejected, "
              f"{c.get('publish/sent', 0)} diagnosis frames sent", file=sys.stderr)
    return 0


def _status_line(pipe: MonitorPipeline, bus_up: bool) -> str:
    """One line for systemctl status: traffic, rejections and each node's state."""
    c = pipe.counters
    rejected = sum(v for k, v in c.items() if k.startswith("rejected/"))
    nodes = " ".join(f"{n}={nm.state.label}" for n, nm in sorted(pipe.nodes.items()))
    return (f"{'bus up' if bus_up else 'bus DOWN, reconnecting'}; "
            f"{c.get('frames/received', 0)} frames, {c.get('samples/estimated', 0)} estimated, "
            f"{rejected} rejected, {c.get('e2e/lost_frames', 0)} lost, "
            f"{c.get('bus/error_frames', 0)} error frames; nodes {nodes or 'none yet'}")


def read_log(path: Path) -> Iterator[can.Message]:
    """Frames of a candump .log, Vector .asc or .blf file, through python-can's readers.

    Not a generator itself: a bad path raises `BusError` here, before the caller opens
    any output (--rrd, --events) that an error must not create or overwrite.
    """
    if path.suffix.lower() not in LOG_SUFFIXES:
        raise BusError(f"{path}: unsupported log format (use {', '.join(LOG_SUFFIXES)})")
    if not path.is_file():
        raise BusError(f"{path}: no such file")
    try:
        reader = can.LogReader(str(path))
    except (OSError, ValueError) as exc:
        raise BusError(f"{path}: cannot read log ({exc})") from None
    return _frames(path, reader)


def _frames(path: Path, reader: can.io.generic.MessageReader) -> Iterator[can.Message]:
    try:
        yield from reader
    except (ValueError, IndexError, OSError, StructError) as exc:
        raise BusError(f"{path}: malformed log ({exc})") from None
    finally:
        with suppress(Exception):
            reader.stop()


def run_replay(args: argparse.Namespace) -> int:
    db = _database(args)
    cfg = _config(args)
    path = Path(args.log)
    frames = read_log(path)
    sink = _make_sink(args, cfg)
    on_event, events_fh = _event_writer(args.events, sys.stdout)
    pipe = MonitorPipeline(db, cfg, sink=sink, publish=None, on_event=on_event)
    t0 = time.perf_counter()
    last_tick = -math.inf
    n = 0
    try:
        for msg in frames:
            pipe.feed(msg)
            n += 1
            ts = msg.timestamp
            if ts - last_tick >= 0.05:
                last_tick = ts
                pipe.tick(ts)
    finally:
        sink.close()
        if events_fh is not None:
            events_fh.close()
    el = time.perf_counter() - t0
    c = pipe.counters
    print(f"motor-monitor: replayed {n} frames in {el:.2f} s ({n / max(el, 1e-9):.0f} frames/s): "
          f"{c.get('samples/estimated', 0)} estimated, "
          f"{sum(v for k, v in c.items() if k.startswith('rejected/'))} rejected", file=sys.stderr)
    return 0


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dbc", default=None, help="DBC file (default: the one shipped)")
    p.add_argument("--nodes", type=_nodes, default=None,
                   help="nodes to monitor, e.g. 0,3 (default: all that send)")
    p.add_argument("--rate", type=_rate, default=100.0, help="ECU current-sample rate, Hz")
    p.add_argument("--thresholds", default=None, help="thresholds TOML (motor-monitor calibrate)")
    p.add_argument("--key", default=None, metavar="FILE",
                   help="SecOC key (32 or 64 hex digits, mode 0600): reject unauthenticated frames")
    p.add_argument("--rrd", default=None, help="record to this .rrd file")
    p.add_argument("--connect", default=None, metavar="URL",
                   help="stream to a Rerun viewer, e.g. rerun+http://127.0.0.1:9876/proxy")


def add_commands(sub: argparse._SubParsersAction[Any]) -> None:
    r = sub.add_parser("run", help="monitor a live CAN bus")
    r.add_argument("--interface", default=None, help="python-can interface (e.g. socketcan)")
    r.add_argument("--channel", default=None, help="channel (e.g. vcan0)")
    r.add_argument("--bitrate", type=int, default=None)
    r.add_argument("--events", default=None, help="append diagnosis events as JSON lines")
    r.add_argument("--record-dir", default=None, metavar="DIR",
                   help="record to rotating .rrd files in DIR (for unattended runs)")
    r.add_argument("--rotate-mb", type=_positive, default=256.0,
                   help="start a new file past this size, MiB (default 256)")
    r.add_argument("--rotate-minutes", type=_positive, default=60.0,
                   help="start a new file after this long, minutes (default 60)")
    r.add_argument("--keep", type=int, default=168,
                   help="recordings kept in DIR, oldest deleted first (default 168)")
    r.add_argument("--secoc-state", default=None, metavar="FILE",
                   help="persist SecOC freshness here (with --key): restarts resume at once")
    r.add_argument("--max-total-gb", type=_positive, default=20.0,
                   help="recordings in DIR never exceed this, GiB (default 20)")
    _common(r)
    r.set_defaults(func=run_live)

    p = sub.add_parser("replay", help="run a candump .log, .asc or .blf file as fast as possible")
    p.add_argument("log", help="log file")
    p.add_argument("--events", default=None, help="JSON lines to this file (default: stdout)")
    _common(p)
    p.set_defaults(func=run_replay)
