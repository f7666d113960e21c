"""The monitor's data path: CAN frames -> decoded samples -> estimator -> diagnosis -> sinks.

`MonitorPipeline.feed(msg)` takes every frame from any source (a live bus, a log file) and
never raises on what the frame holds: each frame ends in exactly one counted outcome.

* Rejected by the codec (unknown ID, wrong length, bad CRC, out of range, malformed,
  remote, error or extended frame): counted under `rejected/<reason>`, logged (rate
  limited), never fed to the estimator.
* Alive counter repeated (a replay or duplicate): counted `e2e/repeated`, dropped.
  Counter jump (lost frames): counted `e2e/lost_frames` by the number lost; the sample is
  used and the estimator predicts through the gap (dt = k T from the timestamps).
* A timestamp that does not advance: counted `time/non_monotonic`, dropped.
* A current sample before any voltage command of its node: `samples/no_voltage`, dropped.
* Frames of nodes not monitored: `ignored/node`. Our own or another monitor's
  MonitorDiagnosis frames: `ignored/diagnosis`.
* SocketCAN error frames: `bus/error_frames` and one `bus/errors/<condition>` per
  condition they report (bus_off, controller/rx_overflow, controller/rx_error_passive,
  restarted, ...), logged and recorded as bus events.

Voltage and current are aligned by taking, for each current sample, the latest voltage
command of its node received before it (the ECU holds the command between its 20 Hz
frames). Timestamps are the frames' own (kernel timestamps on SocketCAN). The number k of
sample periods since the previous current sample comes from the alive counter (lost + 1),
so bus or queue jitter cannot fake a missed sample; the timestamps only decide how many
times the 4-bit counter wrapped in a long gap. k > 1 means missed samples that the
estimator predicts through.

A node whose current frames stop for `silence_timeout_s` turns to `no_data` (see `tick`).
`MonitorDiagnosis` is published on every state change and at a steady rate.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from typing import Any

import can

from monitor.bus.faults import describe_error_frame
from monitor.bus.codec import CounterOutcome, CounterTracker, Decoded, MotorDatabase, Rejected
from monitor.diagnosis import DEFAULT_THRESHOLDS, HealthState, OnlineClassifier, Thresholds
from monitor.estimation.fuzzy_ukf import FuzzyUKF, FuzzyUKFConfig
from monitor.estimation.model import DCMotorParameters, DiscreteModel, dc_motor
from monitor.sinks.rerun import NullSink, Sink

__all__ = ["BUS_EVENTS", "DiagnosisEvent", "MonitorConfig", "MonitorPipeline", "NodeMonitor"]

BUS_EVENTS = -1  # the node number under which bus-level events (error frames, outages) go

log = logging.getLogger("motor_monitor")


@dataclass(frozen=True)
class MonitorConfig:
    """What the monitor watches and how.

    nodes: node numbers to monitor, or None for every node that sends valid frames.
    rate: nominal current-sample rate of the ECUs (Hz).
    """

    nodes: tuple[int, ...] | None = None
    rate: float = 100.0
    thresholds: Thresholds = DEFAULT_THRESHOLDS
    dwell_s: float = 0.03
    hysteresis: float = 0.02
    silence_timeout_s: float = 0.5
    publish_period_s: float = 0.1
    max_gap_s: float = 5.0
    counters_period_s: float = 1.0
    motor: DCMotorParameters = field(default_factory=DCMotorParameters)
    process_noise: float = 1.44
    current_sigma: float = 0.5
    estimator: FuzzyUKFConfig = field(default_factory=FuzzyUKFConfig)


@dataclass(frozen=True)
class DiagnosisEvent:
    """A change of a node's health state (also written as a JSON line by `replay`)."""

    t: float
    node: int
    state: str
    previous: str
    gamma: float
    fault_volts: float
    rules: int
    cause: str  # "estimate" or "silence"

    def to_json(self) -> str:
        return json.dumps(asdict(self), separators=(",", ":"))


class Counters(dict[str, int]):
    """Named event counters: every frame's outcome lands in exactly one of them."""

    def inc(self, name: str, n: int = 1) -> None:
        self[name] = self.get(name, 0) + n


class _RateLimitedLog:
    """Logs the first occurrence of a kind of problem, then at most once per period."""

    def __init__(self, period_s: float = 10.0) -> None:
        self.period_s = period_s
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def warn(self, key: str, message: str) -> None:
        now = time.monotonic()
        last = self._last.get(key)
        if last is not None and now - last < self.period_s:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return
        n = self._suppressed.pop(key, 0)
        self._last[key] = now
        log.warning("%s%s", message, f" (+{n} similar suppressed)" if n else "")


class NodeMonitor:
    """Estimator, classifier and alignment state of one motor ECU."""

    def __init__(self, node: int, model: DiscreteModel, cfg: MonitorConfig) -> None:
        self.node = node
        self.cfg = cfg
        self.T = 1.0 / cfg.rate
        self.model = model
        self.estimator = FuzzyUKF(model, cfg.estimator)
        self.classifier = OnlineClassifier(cfg.thresholds, dwell_s=cfg.dwell_s,
                                           hysteresis=cfg.hysteresis)
        self.voltage: float | None = None
        self.last_t: float | None = None
        self.last_publish: float = -math.inf
        self.truth_gamma: float | None = None
        self.diag_counter = 0
        self.samples = 0
        self.started = False

    def restart(self) -> None:
        """Forget the estimate (after a gap too long to predict through)."""
        self.estimator = FuzzyUKF(self.model, self.cfg.estimator)
        self.started = False

    @property
    def state(self) -> HealthState:
        return self.classifier.state


class MonitorPipeline:
    """Frames in, diagnosis out. See the module docstring for every frame's outcome."""

    def __init__(
        self,
        db: MotorDatabase,
        cfg: MonitorConfig | None = None,
        *,
        sink: Sink | None = None,
        publish: Callable[[can.Message], None] | None = None,
        on_event: Callable[[DiagnosisEvent], None] | None = None,
    ) -> None:
        self.db = db
        self.cfg = cfg or MonitorConfig()
        self.sink: Sink = sink if sink is not None else NullSink()
        self.publish = publish
        self.on_event = on_event
        self.counters = Counters()
        self.nodes: dict[int, NodeMonitor] = {}
        self._warn = _RateLimitedLog()
        self._last_counters_t = -math.inf
        self._model = dc_motor(self.cfg.motor, q=self.cfg.process_noise,
                               r=self.cfg.current_sigma**2).discretize(1.0 / self.cfg.rate)
        self.tracker = CounterTracker()
        self.sink.set_thresholds(self.cfg.thresholds.f1, self.cfg.thresholds.f2)
        # Load the compiled kernels now, not on the first frame of a live bus.
        FuzzyUKF(self._model, self.cfg.estimator).step(0.0, 0.0, 1.0 / self.cfg.rate)
        for n in self.cfg.nodes or ():
            self._node(n)

    # ------------------------------------------------------------------ frames in

    def _node(self, n: int) -> NodeMonitor:
        nm = self.nodes.get(n)
        if nm is None:
            nm = NodeMonitor(n, self._model, self.cfg)
            self.nodes[n] = nm
        return nm

    def feed_many(self, msgs: Iterable[can.Message]) -> None:
        for msg in msgs:
            self.feed(msg)

    def feed(self, msg: can.Message) -> None:
        """One frame from the bus or a log; never raises on the frame's content."""
        self.counters.inc("frames/received")
        if msg.is_error_frame:
            self._on_error_frame(msg)
            return
        res = self.db.decode_can(msg)
        if isinstance(res, Rejected):
            reason = str(res.reason)
            self.counters.inc(f"rejected/{reason}")
            self._warn.warn(reason, f"frame rejected ({reason}, id 0x{res.arbitration_id:X}): "
                                    f"{res.detail}")
            return
        self._dispatch(res)

    def _on_error_frame(self, msg: can.Message) -> None:
        """A SocketCAN error frame: counted per condition, logged, shown in the recording."""
        self.counters.inc("bus/error_frames")
        names = describe_error_frame(msg)
        for name in names:
            self.counters.inc(f"bus/errors/{name}")
        text = "CAN error frame: " + ", ".join(names)
        severe = any(n in ("bus_off", "controller/rx_overflow") or n.endswith("error_passive")
                     for n in names)
        self._warn.warn("errframe-" + ",".join(names), text)
        self.sink.log_event(BUS_EVENTS, float(msg.timestamp), text, "ERROR" if severe else "WARN")

    def _dispatch(self, d: Decoded) -> None:
        kind = d.kind
        if kind == "diagnosis":
            self.counters.inc("ignored/diagnosis")
            return
        if kind == "sync":  # SecOC freshness sync: the codec has applied it (with a key)
            self.counters.inc("samples/secoc_sync" if self.db.secoc_enabled
                              else "ignored/secoc_sync")
            return
        wanted = self.cfg.nodes
        if wanted is not None and d.node not in wanted:
            self.counters.inc("ignored/node")
            return
        nm = self._node(d.node)
        lost = self._check_counter(d)
        if lost is None:
            return
        if kind == "current":
            self._on_current(nm, d.timestamp, d.value, lost)
        elif kind == "voltage":
            nm.voltage = d.value
            self.counters.inc("samples/voltage")
            self.sink.add_voltage(d.node, d.timestamp, d.value)
        else:  # truth: shown beside the estimate, never read by the estimator
            nm.truth_gamma = d.value
            self.counters.inc("samples/truth")

    def _check_counter(self, d: Decoded) -> int | None:
        """Frames lost before this one by its alive counter (0 if none), None to drop it."""
        check = self.tracker.observe(d)
        if check is None or check.outcome == CounterOutcome.OK:
            return 0
        if check.outcome == CounterOutcome.REPEATED:
            self.counters.inc("e2e/repeated")
            self._warn.warn(f"repeat-{d.kind}-{d.node}", f"node {d.node}: repeated {d.kind} "
                            f"alive counter {d.counter} (replay or duplicate)")
            return None
        self.counters.inc("e2e/counter_jumps")
        self.counters.inc("e2e/lost_frames", check.lost)
        return check.lost

    def _on_current(self, nm: NodeMonitor, t: float, amps: float, lost: int) -> None:
        if nm.voltage is None:
            self.counters.inc("samples/no_voltage")
            return
        last = nm.last_t
        if last is None:
            k = 1
        else:
            dt = t - last
            if not dt > 0.0:
                self.counters.inc("time/non_monotonic")
                return
            if dt > self.cfg.max_gap_s:
                self.counters.inc("estimator/restarts")
                nm.restart()
                k = 1
            else:
                k = self._periods(dt, lost)
                if k > 1:
                    self.counters.inc("samples/predicted_through", k - 1)
        nm.last_t = t
        est = nm.estimator
        out = est.step(nm.voltage, amps, k * nm.T)
        nm.samples += 1
        self.counters.inc("samples/estimated")
        g = float(out.gamma[0])
        if g != g:  # NaN can only come from a numerical failure: count, restart
            self.counters.inc("estimator/nan")
            nm.restart()
            return
        if out.structure_event:
            self.counters.inc("estimator/structure_events")
        prev = nm.classifier.state
        new = nm.classifier.update(t, g)
        if new is not None:
            self._transition(nm, t, prev, new, g, out.rules, "estimate")
        elif t - nm.last_publish >= self.cfg.publish_period_s:
            self._publish(nm, t)
        self.sink.add_sample(nm.node, t, amps, float(out.y_est[0]), g, out.rules,
                             int(nm.classifier.state), float(out.nis), nm.truth_gamma)
        if t - self._last_counters_t >= self.cfg.counters_period_s:
            self.log_counters(t)

    def _periods(self, dt: float, lost: int) -> int:
        """Sample periods since the previous current sample.

        The alive counter says it exactly, modulo 16 (lost + 1): a frame delayed on the
        bus or in a driver queue does not make a missed sample. The timestamps only pick
        the multiple of 16 when a gap is longer than the counter can tell.
        """
        k_counter = lost + 1
        k_time = dt * self.cfg.rate
        if k_time < 12.0:
            return k_counter
        return k_counter + 16 * max(0, round((k_time - k_counter) / 16.0))

    # ------------------------------------------------------------------ diagnosis out

    def _transition(self, nm: NodeMonitor, t: float, prev: HealthState, new: HealthState,
                    gamma: float, rules: int, cause: str) -> None:
        volts = nm.voltage or 0.0
        ev = DiagnosisEvent(t=t, node=nm.node, state=new.label, previous=prev.label,
                            gamma=gamma, fault_volts=gamma * volts, rules=rules, cause=cause)
        self.counters.inc(f"transitions/{new.label}")
        level = "INFO" if new == HealthState.FAULT_FREE else "WARN"
        text = f"{prev.label} -> {new.label} (gamma^ = {gamma:.3f}, {rules} rules, {cause})"
        log.info("node %d: %s", nm.node, text)
        self.sink.log_event(nm.node, t, text, level)
        if self.on_event is not None:
            self.on_event(ev)
        self._publish(nm, t)

    def _publish(self, nm: NodeMonitor, t: float) -> None:
        nm.last_publish = t
        if self.publish is None:
            return
        out = nm.estimator.out
        g = float(out.gamma[0])
        fault = max(-999.0, min(999.0, g * (nm.voltage or 0.0)))
        try:
            data = self.db.encode_diagnosis(nm.node, int(nm.classifier.state), g, fault,
                                            min(out.rules, 255), nm.diag_counter)
        except ValueError as exc:  # a value the DBC cannot carry: count, never crash
            self.counters.inc("publish/encode_errors")
            self._warn.warn("encode", f"node {nm.node}: cannot encode diagnosis: {exc}")
            return
        nm.diag_counter = (nm.diag_counter + 1) % 16
        msg = can.Message(arbitration_id=self.db.frame_id("diagnosis", nm.node), data=data,
                          is_extended_id=False, timestamp=t)
        try:
            self.publish(msg)
            self.counters.inc("publish/sent")
        except can.CanError as exc:
            self.counters.inc("publish/errors")
            self._warn.warn("publish", f"cannot send diagnosis: {exc}")

    def tick(self, now: float) -> None:
        """Timeouts and steady publication, at bus time `now` (no frame needed)."""
        for nm in self.nodes.values():
            silent = nm.last_t is None or now - nm.last_t >= self.cfg.silence_timeout_s
            if silent and nm.classifier.state != HealthState.NO_DATA:
                prev = nm.classifier.state
                nm.classifier.mark_no_data(now)
                self.counters.inc("nodes/silent")
                self._transition(nm, now, prev, HealthState.NO_DATA,
                                 float(nm.estimator.out.gamma[0]), nm.estimator.out.rules,
                                 "silence")
            elif silent and now - nm.last_publish >= self.cfg.publish_period_s:
                self._publish(nm, now)
        # Counters go with estimated samples (at their time stamps); when none come (a
        # silent bus, error frames, an outage) they still reach the recording.
        if now - self._last_counters_t >= 2.0 * self.cfg.counters_period_s:
            self.log_counters(now)

    def log_counters(self, t: float) -> None:
        """Log every counter into the sink at time `t` (also called on exit)."""
        self._last_counters_t = t
        self.sink.log_counters(t, self.counters)

    def summary(self) -> dict[str, Any]:
        return {
            "counters": dict(sorted(self.counters.items())),
            "nodes": {
                n: {"state": nm.state.label, "gamma": float(nm.estimator.out.gamma[0]),
                    "rules": nm.estimator.out.rules, "samples": nm.samples}
                for n, nm in sorted(self.nodes.items())
            },
        }
