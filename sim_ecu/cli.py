"""``sim-ecu``: run one virtual motor ECU node on a CAN bus in real time.

Every configuration mistake is one ``sim-ecu: error: ...`` line on stderr and exit code 2;
a run that ends (its duration, SIGINT or SIGTERM) prints a one-line summary on stderr and
exits 0.

With ``--key`` the ECU signs its frames and sends SecOC sync frames (at start and once per
second). ``--secoc-state FILE`` keeps its freshness counters across runs: loaded at start
(a missing file starts at 0) and skipped ahead by `STATE_MARGIN_S` seconds of frames (it
may have signed that many after its last save before a crash: no freshness value is ever
reused), saved every second and at exit. Without it every run restarts its counters, and a
monitor that already accepted higher values rejects the new run's frames and syncs as
replays until the counters pass them (or the monitor starts without state).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

from monitor.bus.codec import N_NODES, MotorDatabase
from monitor.bus.secoc import load_key
from monitor.errors import ERROR_LINE_LIMIT, MonitorError, UsageError, one_line
from monitor.estimation.model import DCMotorParameters
from monitor.rig import Rig, build_decoder, builtin_rig, load_rig, model_of
from monitor.runtime.argtypes import OneLineParser
from monitor.runtime.canbus import open_bus
from monitor.runtime.freshness import FreshnessSaver
from monitor.runtime.paths import Output, check_outputs, monitor_inputs
from monitor.runtime.signals import StopOnSignals
from sim_ecu.ecu import DEFAULT_MAX_CATCH_UP, ECUStats, VirtualECU, load_motor_parameters
from sim_ecu.rig_ecu import RigECU
from sim_ecu.scenario import BUILTIN_SCENARIOS, load_scenario

__all__ = ["build_parser", "main"]

PROG = "sim-ecu"
EXIT_USAGE = 2
STATE_MARGIN_S = 60.0
"""A restarted ECU continues its freshness this many seconds of frames past its saved state."""
STATE_SAVE_PERIOD_S = 1.0

log = logging.getLogger("sim_ecu")


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog=PROG,
        description="Virtual DC-motor ECU: sends MotorCurrent, MotorVoltage and SimTruth "
        "frames of one node for a fault scenario, paced in real time.",
    )
    p.add_argument(
        "--interface",
        help="python-can interface (socketcan, virtual, ...); default: python-can's "
        "configuration (CAN_INTERFACE, ~/.canrc, ...)",
    )
    p.add_argument(
        "--channel",
        help="channel, e.g. vcan0; default: python-can's configuration (CAN_CHANNEL, ...)",
    )
    p.add_argument("--node", type=int, required=True, help=f"node number 0..{N_NODES - 1}")
    p.add_argument(
        "--scenario",
        required=True,
        metavar="NAME|FILE.toml",
        help=f"built-in ({', '.join(BUILTIN_SCENARIOS)}) or a scenario TOML file "
        "(optionally with a [motor] table: J, b, Ke, Ki, Ra, La)",
    )
    p.add_argument("--rate", type=float, default=None,
                   help="sample rate in Hz (default: the rig's, 100 on our bus)")
    p.add_argument("--rig", metavar="FILE", help="rig file: simulate its model and speak its DBC "
                   "and node layout (a virtual twin of your ECU; default: our bus and motor)")
    p.add_argument(
        "--host",
        choices=("self", "external"),
        default="self",
        help="with a CANopen --rig: who is the CANopen master. self (default): the twin is its "
        "own host too (NMT start, SYNC and the scenario's targets in the RPDOs); external: "
        "the twin is the CiA 402 drive only, for your PLC or master on the bus: it waits in "
        "pre-operational for NMT start, answers each SYNC with its synchronous TPDOs, takes "
        "its inputs and controlword from the master's RPDOs (the scenario gives the fault "
        "only) and --duration counts SYNCs (duration x rate)",
    )
    p.add_argument(
        "--voltage-rate",
        type=float,
        default=20.0,
        help="MotorVoltage frame rate in Hz (default 20; also sent at every command change)",
    )
    p.add_argument(
        "--duration",
        type=float,
        help="run length in s (default: the scenario's; 0: until stopped). Past the "
        "scenario's end its last inputs hold",
    )
    p.add_argument(
        "--max-catch-up",
        type=int,
        default=DEFAULT_MAX_CATCH_UP,
        metavar="N",
        help=f"late samples sent back to back when the process falls behind schedule "
        f"(default {DEFAULT_MAX_CATCH_UP}); further behind, the missed samples are skipped "
        "(their alive counters advance, as a real ECU's would) and counted as overruns. A "
        "large N sends every sample, late, on a loaded machine",
    )
    p.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    p.add_argument("--no-truth", action="store_true", help="do not send SimTruth frames")
    p.add_argument("--dbc", metavar="PATH", help="DBC file (default: the packaged motor.dbc)")
    p.add_argument(
        "--key",
        metavar="FILE",
        help="sign MotorCurrent and MotorVoltage (with --rig: the rig's messages that have "
        "SecOC) with SecOC (truncated AES-CMAC and freshness counter) and send sync frames, "
        "under the AES-128/256 key in FILE: 32 or 64 hex digits or 16/32 raw bytes, "
        "accessible by its owner only (chmod 600)",
    )
    p.add_argument(
        "--secoc-state",
        metavar="FILE",
        help="with --key: keep the SecOC freshness counters in FILE (written atomically, mode "
        "0600): loaded at start (missing: start at 0), saved every second and at exit, so "
        "a restarted ECU never reuses a freshness value",
    )
    p.add_argument("--bitrate", type=int, help="bitrate passed to the interface")
    p.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    return p


def _check_args(args: argparse.Namespace) -> float | None:
    """Validate numbers argparse cannot; returns the run duration (None: scenario's)."""
    if args.rig is None and not 0 <= args.node < N_NODES:
        raise UsageError(f"--node must be in 0..{N_NODES - 1}, got {args.node}")
    for flag, value in (("--rate", 1.0 if args.rate is None else args.rate),
                        ("--voltage-rate", args.voltage_rate)):
        if not (math.isfinite(value) and value > 0):
            raise UsageError(f"{flag} must be a positive number of Hz, got {value:g}")
    if args.max_catch_up < 1:
        raise UsageError(f"--max-catch-up must be a positive number of samples, "
                         f"got {args.max_catch_up}")
    if args.seed < 0:
        raise UsageError(f"--seed must be >= 0, got {args.seed}")
    if args.bitrate is not None and args.bitrate <= 0:
        raise UsageError(f"--bitrate must be positive, got {args.bitrate}")
    if args.secoc_state is not None and args.key is None:
        raise UsageError("--secoc-state needs --key (the counters of SecOC-signed frames)")
    if args.duration is None:
        return None
    if not (math.isfinite(args.duration) and args.duration >= 0):
        raise UsageError(f"--duration must be >= 0 seconds (0: forever), got {args.duration:g}")
    return math.inf if args.duration == 0 else float(args.duration)


def _rig_motor(rig: Rig) -> DCMotorParameters | None:
    """The DC motor a rig on our own bus describes (None: the model is not a DC motor)."""
    spec, _ = model_of(rig)
    if spec.kind != "dc_motor":
        return None
    return replace(DCMotorParameters(), **spec.motor)


def _run_in_worker(ecu: VirtualECU | RigECU, duration: float | None, stop: threading.Event,
                   every_second: Callable[[], object] | None = None) -> ECUStats:
    """ecu.run in a worker thread; the main thread stays free to run signal handlers.

    (Setting an Event from a signal handler that interrupted the same thread inside
    Event.wait can deadlock on the Event's internal lock, so the waiting happens elsewhere.)
    `every_second`, if given, runs in the calling thread about once per second meanwhile.
    """
    result: list[ECUStats] = []
    failure: list[BaseException] = []

    def target() -> None:
        try:
            result.append(ecu.run(duration, stop))
        except BaseException as exc:
            failure.append(exc)

    worker = threading.Thread(target=target, name="sim-ecu-run", daemon=True)
    worker.start()
    next_call = time.monotonic() + STATE_SAVE_PERIOD_S
    while worker.is_alive():
        worker.join(0.25)
        if every_second is not None and time.monotonic() >= next_call:
            next_call += STATE_SAVE_PERIOD_S
            every_second()
    if failure:
        raise failure[0]
    return result[0]


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or a usage error (2, already printed)
        return exc.code if isinstance(exc.code, int) else EXIT_USAGE
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format=f"{PROG}: %(levelname)s: %(message)s",
        stream=sys.stderr,
    )
    stop = threading.Event()
    saver: FreshnessSaver | None = None
    with StopOnSignals(stop) as signals:
        try:
            duration = _check_args(args)
            scenario = load_scenario(args.scenario)
            motor = load_motor_parameters(args.scenario)
            key = None if args.key is None else load_key(args.key)
            rig = load_rig(args.rig) if args.rig else builtin_rig()
            if args.dbc:
                rig = replace(rig, dbc=(Path(args.dbc),))
            if args.host != "self" and rig.canopen is None:
                raise UsageError(f"--host {args.host} needs a CANopen rig ([bus] protocol = "
                                 "\"canopen\" in --rig)")
            if args.secoc_state is not None:  # written every second: never one of the inputs
                check_outputs([*monitor_inputs(rig, args), ("--scenario", args.scenario)],
                              [Output("--secoc-state", Path(args.secoc_state), None)])
            if args.rate is None:
                args.rate = rig.rate
            decoder = build_decoder(rig, secoc_key=key)
            if isinstance(decoder, MotorDatabase) and motor is None and args.rig:
                motor = _rig_motor(rig)
            db = decoder
            if args.secoc_state is not None and db.secoc is not None:
                margin = math.ceil(STATE_MARGIN_S * max(args.rate, args.voltage_rate))
                restored = db.secoc.load_state(args.secoc_state, tx_margin=margin)
                log.info("SecOC state %s: %s", args.secoc_state,
                         "none yet, counters start at 0" if restored is None
                         else f"{restored} counter(s) restored, {margin} ahead")
                # the skipped-ahead counters are on disk before the first frame is signed
                db.secoc.save_state(args.secoc_state)
                saver = FreshnessSaver(db.secoc, args.secoc_state, STATE_SAVE_PERIOD_S)
            bus = open_bus(args.interface, args.channel, args.bitrate, quiet=not args.verbose)
        except MonitorError as exc:
            print(f"{PROG}: error: {one_line(exc, limit=ERROR_LINE_LIMIT)}", file=sys.stderr)
            return EXIT_USAGE
        try:
            try:
                ecu: VirtualECU | RigECU
                if isinstance(db, MotorDatabase):
                    ecu = VirtualECU(
                        bus,
                        db,
                        args.node,
                        scenario,
                        rate=args.rate,
                        voltage_rate=args.voltage_rate,
                        seed=args.seed,
                        truth=not args.no_truth,
                        motor=motor,
                        max_catch_up=args.max_catch_up,
                    )
                elif rig.canopen is not None:  # a CiA 402 drive (and its host: --host)
                    from sim_ecu.cia402 import Cia402ECU

                    ecu = Cia402ECU(bus, db, rig, args.node, scenario, seed=args.seed,
                                    max_catch_up=args.max_catch_up, host=args.host)
                else:
                    ecu = RigECU(bus, db, rig, args.node, scenario, seed=args.seed,
                                 input_rate=args.voltage_rate,
                                 max_catch_up=args.max_catch_up)
            except MonitorError as exc:
                print(f"{PROG}: error: {one_line(exc, limit=ERROR_LINE_LIMIT)}", file=sys.stderr)
                return EXIT_USAGE
            length = "until stopped" if duration == math.inf else (
                f"{scenario.duration if duration is None else duration:g} s"
            )
            log.info(
                "running node %d, scenario %s, %g Hz (voltage %g Hz), seed %d, %s%s",
                args.node, scenario.name, ecu.rate, ecu.voltage_rate, args.seed, length,
                "" if db.secoc is None else f", SecOC AES-{db.secoc.key_bits}-CMAC",
            )
            try:
                stats = _run_in_worker(ecu, duration, stop,
                                       None if saver is None else saver.write)
            except Exception as exc:
                log.debug("run failed", exc_info=True)
                print(f"{PROG}: error: run failed: {one_line(exc, limit=ERROR_LINE_LIMIT)}",
                      file=sys.stderr)
                if saver is not None:
                    saver.final()  # best effort; the run's failure is the error reported
                return 1
        finally:
            bus.shutdown()
        failed = None if saver is None else saver.final()
        if failed is not None:
            print(f"{PROG}: error: {failed}", file=sys.stderr)
            return 1
    how = f"stopped by {signals.received}" if signals.received else "done"
    print(
        f"{PROG}: {how}: node {args.node}, scenario {scenario.name}: {stats.summary()}",
        file=sys.stderr,
    )
    return 0
