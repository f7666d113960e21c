"""The monitor's data path: CAN frames -> decoded samples -> estimator -> diagnosis -> sinks.

`MonitorPipeline.feed(msg)` takes every frame from any source (a live bus, a log file) and
never raises on what the frame holds: each frame ends in exactly one counted outcome.

* Rejected by the codec (unknown ID, wrong length, bad CRC, out of range, malformed,
  remote, error or extended frame, a CAN FD frame where the DBC has a classic message or
  the reverse): counted under `rejected/<reason>`, logged (rate limited), never fed to
  the estimator.

Besides its outcome, a CAN FD frame is counted in `frames/fd` (and, when its error state
indicator is set, `frames/fd_esi`): sub-counts of `frames/received`, not outcomes.
* Alive counter repeated (a replay or duplicate): counted `e2e/repeated`, dropped; but
  an output-only frame due 16 or more periods after the previous sample, within the
  silence timeout, is 16 m periods on: 16 m - 1 lost (`monitor.pipeline.periods.wrapped`).
  Counter jump (lost frames): counted `e2e/lost_frames` by the number lost; the sample is
  used and the estimator predicts through the gap (dt = k T from the timestamps).
* A timestamp that does not advance: counted `time/non_monotonic`, dropped.
* An output sample before any input of its node: `samples/no_input`, dropped.
* Frames of nodes not monitored: `ignored/node`. Our own or another monitor's
  MonitorDiagnosis frames: `ignored/diagnosis`.
* SocketCAN error frames: `bus/error_frames` and one `bus/errors/<condition>` per
  condition they report (bus_off, controller/rx_overflow, controller/rx_error_passive,
  restarted, ...), logged and recorded as bus events.

Inputs and outputs are aligned by taking, for each output sample, the latest value of each
input of its node received before it or in its frame (an ECU holds a command between its
frames, which may come at another rate), and the estimator steps the held input of
`input_delay` samples before (`monitor.pipeline.samples`, the rule `identify` fits by).
Timestamps are the frames' own (kernel timestamps on SocketCAN). The number k of sample
periods since the previous output sample comes from the alive counter (lost + 1), so bus
or queue jitter cannot fake a missed sample; the timestamps only decide how many times the
4-bit counter wrapped in a long gap: the whole wraps that fit, so a frame up to
15 periods late is not taken for 16 lost (`monitor.pipeline.periods`). k > 1 means missed
samples that the estimator predicts through.

A node whose output frames stop for `silence_timeout_s` turns to `no_data` (see `tick`).
A node's `Diagnosis` is due on every change of its state or of its model-mismatch flag
(`MismatchDetector`, a flag beside the state, never replacing it; `DiagnosisEvent` says how
both are reported) and at a steady rate (the bus publisher sink turns it into a
MonitorDiagnosis frame).

What comes out goes to one `monitor.pipeline.sink.Sink` (a `FanOut` for several): typed events
from `monitor.pipeline.events`, never Rerun calls or CAN frames. Interface outages and
kernel socket drops are reported to the pipeline by the application (`interface_failed`,
`interface_back`, `socket_drops`), so every counter is written here.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

import can
import numpy as np
from numpy.typing import NDArray

from monitor.bus.cia402 import (
    IGNORED_NOT_OPERATIONAL,
    IGNORED_PROTOCOL,
    DriveReport,
    drive_watch,
    report_counter,
)
from monitor.bus.codec import Decoded, Rejected, RejectReason
from monitor.bus.counters import CounterTracker
from monitor.diagnosis import DEFAULT_THRESHOLDS, DiagnosisSpec, HealthState, Thresholds, rules
from monitor.estimation.fuzzy_ukf import FuzzyUKF, FuzzyUKFConfig
from monitor.estimation.model import (
    ContinuousDescriptor,
    DCMotorParameters,
    DiscreteModel,
    dc_motor,
)
from monitor.pipeline import counters as C
from monitor.pipeline.admission import (
    ADMITTED,
    DROP,
    NO_COUNTER,
    REFUSED,
    REPEATED,
    RESUME,
    admit,
    alive_verdict,
    new_state,
    not_read,
    rate_event,
    warm_up,
)
from monitor.pipeline.counters import Counters
from monitor.pipeline.events import (
    HEALTH,
    MODEL_MISMATCH,
    BusEvent,
    Diagnosis,
    DiagnosisEvent,
    InputSample,
    Sample,
    drive_event,
    error_frame_event,
)
from monitor.pipeline.samples import (
    HeldInputs,
    delayed,
    input_delay_problem,
    input_window_problem,
    no_past,
)
from monitor.pipeline.sink import Sink

__all__ = ["FrameDecoder", "MonitorConfig", "MonitorPipeline", "NodeMonitor"]

log = logging.getLogger("motor_monitor")
_RESTART = np.ones(1, np.bool_)  # `delayed`'s restart flag of one sample
_STATES = tuple(HealthState)
_WARMED: set[tuple[int, int, int, str]] = set()  # estimators whose kernels this process loaded


class FrameDecoder(Protocol):
    """What the pipeline needs of a bus codec: `MotorDatabase` (our bus) or `RigCodec`."""

    @property
    def secoc_enabled(self) -> bool: ...

    def decode_can(self, msg: can.Message) -> Decoded | Rejected: ...


_DIAGNOSIS = DiagnosisSpec()
"""The defaults of the diagnosis' debouncing and timeouts, a rig file's as well."""


@dataclass(frozen=True)
class MonitorConfig:
    """What the monitor watches and how.

    nodes: node numbers to monitor, or None for every node that sends valid frames.
    rate: nominal output-sample rate of the ECUs (Hz).
    model: the plant of every node; None: the DC motor of `motor`, `process_noise` and
    `current_sigma` (the paper's Table 1 by default).
    withhold_alarms_on_mismatch: while a node's model-mismatch flag is up, hold a change
    to fault or outage until the flag falls (`monitor.diagnosis.reported_state`); off by
    default: a fault the estimator sees is reported, mismatch or not.
    input_delay: the estimator's step for output sample k applies the input held at
    output sample k - input_delay (`monitor.pipeline.samples`; the rig's `[model]`).
    input_window: an input frame received less than this share of a period before an
    output frame is held from the next sample on (`monitor.pipeline.samples`, rule 1).
    """

    nodes: tuple[int, ...] | None = None
    rate: float = 100.0
    thresholds: Thresholds = DEFAULT_THRESHOLDS
    dwell_s: float = _DIAGNOSIS.dwell_s
    hysteresis: float = _DIAGNOSIS.hysteresis
    significance: float = _DIAGNOSIS.significance
    silence_timeout_s: float = _DIAGNOSIS.silence_timeout_s
    publish_period_s: float = 0.1
    max_gap_s: float = 5.0
    counters_period_s: float = 1.0
    motor: DCMotorParameters = field(default_factory=DCMotorParameters)
    process_noise: float = 1.44
    current_sigma: float = 0.5
    estimator: FuzzyUKFConfig = field(default_factory=FuzzyUKFConfig)
    model: ContinuousDescriptor | None = None
    mismatch_window_s: float = _DIAGNOSIS.mismatch_window_s
    mismatch_dwell_s: float = _DIAGNOSIS.mismatch_dwell_s
    withhold_alarms_on_mismatch: bool = _DIAGNOSIS.withhold_alarms_on_mismatch
    jitter_fraction: float = 0.25  # of a period: counted as time/jitter (no counter)
    input_delay: int = 0
    input_window: float = 0.0

    def __post_init__(self) -> None:
        problem = input_delay_problem(self.input_delay)
        if problem is not None:
            raise ValueError(f"input_delay {problem}")
        problem = input_window_problem(self.input_window)
        if problem is not None:
            raise ValueError(f"input_window {problem}")

    def plant(self) -> ContinuousDescriptor:
        """The continuous model of every node."""
        if self.model is not None:
            return self.model
        return dc_motor(self.motor, q=self.process_noise, r=self.current_sigma**2)

    def diagnosis_params(self, outputs: int) -> NDArray[np.float64]:
        """The parameter vector of the per-node diagnosis rules (`monitor.diagnosis.rules`)
        for an estimator of `outputs` outputs."""
        return rules.params(self.thresholds, dwell_s=self.dwell_s, hysteresis=self.hysteresis,
                            outputs=outputs, rate=self.rate, window_s=self.mismatch_window_s,
                            mismatch_dwell_s=self.mismatch_dwell_s,
                            publish_period_s=self.publish_period_s,
                            silence_timeout_s=self.silence_timeout_s,
                            withhold=self.withhold_alarms_on_mismatch,
                            significance=self.significance)


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
    """Estimator, diagnosis and alignment state of one node.

    The diagnosis -- eq (76) debounced, the model-mismatch flag, the reported state, when
    a `Diagnosis` is due -- is the state vector `diag` of `monitor.diagnosis.rules` with
    the parameters `prm` (`MonitorConfig.diagnosis_params`); `rules.on_sample` and
    `rules.on_tick` step it and report into `out`."""

    def __init__(self, node: int, model: DiscreteModel, cfg: MonitorConfig,
                 prm: NDArray[np.float64] | None = None) -> None:
        self.node = node
        self.cfg = cfg
        self.T = 1.0 / cfg.rate
        self.model = model
        self.estimator = FuzzyUKF(model, cfg.estimator)
        self.diag, self.prm, self.out = rules.step_vectors(
            prm if prm is not None else cfg.diagnosis_params(model.p))
        self.held = HeldInputs(model.m)  # `monitor.pipeline.samples`, rule 1
        self.window = cfg.input_window * self.T  # rule 1's, in seconds
        self.u_past = no_past(model.m)  # held inputs of the last input_delay samples
        self.y = np.zeros(model.p)
        self.admission = new_state()  # `monitor.pipeline.admission`: last sample, resumption
        self.truth_gamma: float | None = None
        self.samples = 0

    @property
    def first_input(self) -> float | None:
        """The first input (the voltage command of our bus's motor), None before any."""
        return float(self.held.latest[0]) if self.held.seen[0] else None

    def restart(self) -> None:
        """Forget the estimate (after a gap too long to predict through, or a NaN); the
        step of the sample (`rules.on_sample`, restarted or failed) has the mismatch
        detector forget the innovations of the old estimate with it."""
        self.estimator = FuzzyUKF(self.model, self.cfg.estimator)

    @property
    def state(self) -> HealthState:
        """The reported state: the classifier's, or the one held before it while the
        model-mismatch flag is up (`rules.reported_state`, with withhold_alarms_on_mismatch)."""
        return _STATES[int(self.diag[rules.REPORTED])]

    @property
    def model_mismatch(self) -> bool:
        """The model-mismatch flag: the innovations say the model does not explain the
        plant (`MismatchDetector`); it stands beside the state, never replaces it."""
        return bool(self.diag[rules.FLAGGED] != 0.0)

    @property
    def gamma(self) -> float:
        """The largest gamma^ of the node's actuators (the one the diagnosis reads)."""
        return float(self.estimator.out.gamma.max())

    @property
    def gamma_sd(self) -> float:
        """The standard deviation of that gamma^ (`EstimatorOutput.gamma_sd`)."""
        out = self.estimator.out
        return float(out.gamma_sd[int(np.argmax(out.gamma))])

    @property
    def fault_input(self) -> float:
        """gamma^ times its held input (the latest, `monitor.pipeline.samples`): the input
        the fault takes away, in the input's unit."""
        g = self.estimator.out.gamma
        j = int(np.argmax(g))
        return float(g[j] * self.held.latest[j])


class MonitorPipeline:
    """Frames in, typed events out to `sink`. See the module docstring for every frame's
    outcome."""

    def __init__(self, db: FrameDecoder, cfg: MonitorConfig | None = None, *,
                 sink: Sink | None = None, counters: Counters | None = None) -> None:
        """`counters` may be shared with sinks that count their own outcomes (the bus
        publisher); by default the pipeline starts its own."""
        self.db = db
        self.cfg = cfg or MonitorConfig()
        self.sink: Sink = sink if sink is not None else Sink()
        self.counters = counters if counters is not None else Counters()
        self.nodes: dict[int, NodeMonitor] = {}
        self.warn = _RateLimitedLog()
        """Warnings of kinds of problem: the first of each, then at most one per period."""
        self._last_counters_t = -math.inf
        self.model = self.cfg.plant().discretize(1.0 / self.cfg.rate)
        self.diag_prm = self.cfg.diagnosis_params(self.model.p)
        self.tracker = CounterTracker()
        self.drives = drive_watch(db)  # a CANopen rig's drives: EMCY, heartbeat, statusword
        self.held: set[int] = set()  # nodes whose drive said it was not operational
        # Load the compiled kernels now, not on the first frame of a live bus.
        # (the structure event's onset search and re-processing too: a JIT compile in the
        # middle of a flood would stall the daemon for seconds); once per process and kind
        # of estimator: an archive makes a pipeline per file
        key = (self.model.n, self.model.m, self.model.p, repr(self.cfg.estimator))
        if key not in _WARMED:
            FuzzyUKF(self.model, self.cfg.estimator).warm_up()
            rules.warm_up(self.diag_prm)
            warm_up()
            _WARMED.add(key)
        for n in self.cfg.nodes or ():
            self.node(n)

    # ------------------------------------------------------------------ frames in

    def node(self, n: int) -> NodeMonitor:
        """Node n's state, made on its first frame."""
        nm = self.nodes.get(n)
        if nm is None:
            nm = NodeMonitor(n, self.model, self.cfg, self.diag_prm)
            self.nodes[n] = nm
        return nm

    def feed(self, msg: can.Message) -> None:
        """One frame from the bus or a log; never raises on the frame's content."""
        fd = msg.is_fd
        self.counters.received(1, fd, fd and msg.error_state_indicator)
        if msg.is_error_frame:
            self._on_error_frame(msg)
            return
        res = self.db.decode_can(msg)
        if isinstance(res, Rejected):
            drives = self.drives
            if drives is not None and res.reason == RejectReason.UNKNOWN_ID:
                protocol, reports = drives.unread(msg.arbitration_id, msg.is_extended_id,
                                                  bytes(msg.data), float(msg.timestamp))
                if protocol:
                    self.counters.inc(IGNORED_PROTOCOL)
                else:
                    self._rejected(res)
                self._drive_reports(reports)
            else:
                self._rejected(res)
            return
        self._dispatch(res)

    def _on_error_frame(self, msg: can.Message) -> None:
        """A SocketCAN error frame: counted per condition, logged, shown in the recording."""
        self.sink.on_bus_event(self.error_frame(msg))

    def error_frame(self, msg: can.Message) -> BusEvent:
        """Count and log a SocketCAN error frame, per condition; its bus event (both engines:
        the columnar one puts it in its chunk's order)."""
        self.counters.inc(C.BUS_ERROR_FRAMES)
        names, event = error_frame_event(msg)
        for name in names:
            self.counters.inc(C.bus_error(name))
        self.warn.warn("errframe-" + ",".join(names), event.text)
        return event

    def _rejected(self, res: Rejected) -> None:
        reason = str(res.reason)
        self.counters.inc(C.rejected(reason))
        self.warn.warn(reason, f"frame rejected ({reason}, id 0x{res.arbitration_id:X}): "
                                f"{res.detail}")

    def _dispatch(self, d: Decoded) -> None:
        skip = not_read(d.kind, d.node, self.cfg.nodes, self.db.secoc_enabled)
        if skip is not None:
            self.counters.inc(skip)
            return
        if self.drives is not None:
            if not self.drives.operational(d.node):
                self.counters.inc(IGNORED_NOT_OPERATIONAL)  # the drive says it is not driving
                self.held.add(d.node)
                return
            if d.node in self.held:  # the estimate from before is not the plant's now
                self.held.discard(d.node)
                self.node(d.node).admission[RESUME] = 1.0
        nm = self.node(d.node)
        lost, wrap = NO_COUNTER, False
        if d.counter is not None:
            lost, wrap = alive_verdict(
                self.tracker.lost(d.kind, d.node, d.counter),
                bool(d.outputs) and not d.inputs and d.truth is None)
            if lost == DROP:
                self._repeated(d.kind, d.node, d.counter)
                return
            if lost and not wrap:
                self.counters.inc(C.E2E_COUNTER_JUMPS)
                self.counters.inc(C.E2E_LOST_FRAMES, lost)
        if d.inputs:
            nm.held.take(d.timestamp, d.inputs)
            self.counters.inc(C.SAMPLES_INPUT)
            for i, v in sorted(d.inputs):  # every input the frame carries, by index
                self.sink.on_input(InputSample(d.node, d.timestamp, v, i))
        if d.truth is not None:  # shown beside the estimate, never read by the estimator
            nm.truth_gamma = d.truth
            self.counters.inc(C.SAMPLES_TRUTH)
        if d.outputs:
            self._on_output(nm, d, lost, wrap)

    def _repeated(self, kind: str, node: int, counter: int | None) -> None:
        self.counters.inc(C.E2E_REPEATED)
        self.warn.warn(f"repeat-{kind}-{node}", f"node {node}: repeated {kind} alive "
                                                 f"counter {counter} (replay or duplicate)")

    def _on_output(self, nm: NodeMonitor, d: Decoded, lost: int, wrap: bool) -> None:
        """One output sample, admitted or refused by `admission.admit`; `lost` frames before
        it by the alive counter (`NO_COUNTER`: the time stamps tell), `wrap` a repeated
        counter that may be 16 m periods on (`admission.alive_verdict`)."""
        t = d.timestamp
        cfg = self.cfg
        held, seen = nm.held.at(t, d.inputs, nm.window)
        status, k, restarted, jitter, rate_change = admit(
            nm.admission, t, lost, wrap, seen, False, cfg.rate,
            cfg.max_gap_s, cfg.silence_timeout_s, cfg.jitter_fraction)
        if rate_change:
            self.sink.on_bus_event(self.rate_change(t, nm.node, rate_change))
        if wrap:
            if status == REPEATED:
                self._repeated(d.kind, d.node, d.counter)
                return
            self.counters.inc(C.E2E_COUNTER_JUMPS)
            self.counters.inc(C.E2E_LOST_FRAMES, lost)
        if status != ADMITTED:
            self.counters.inc(REFUSED[status])
            return
        if jitter:
            self.counters.inc(C.TIME_JITTER)
        restart = None
        if restarted:
            self.counters.inc(C.ESTIMATOR_RESTARTS)
            nm.restart()
            restart = _RESTART
        elif k > 1:
            self.counters.inc(C.SAMPLES_PREDICTED_THROUGH, k - 1)
        outputs = d.outputs
        y = nm.y
        for i, v in enumerate(outputs):
            y[i] = v
        applied, nm.u_past = delayed(held[None], self.cfg.input_delay, nm.u_past, restart)
        u = applied[0]
        out = nm.estimator.step(u, y, k * nm.T)
        nm.samples += 1
        self.counters.inc(C.SAMPLES_ESTIMATED)
        g = nm.gamma
        nis = float(out.nis)
        if g != g:  # NaN can only come from a numerical failure: count, restart
            self.counters.inc(C.ESTIMATOR_NAN)
            nm.restart()
            if rules.on_sample(nm.diag, nm.prm, t, g, math.nan, nis, restart is not None, True,
                               nm.out):
                self._report(nm, t)
            return
        if out.structure_event:
            self.counters.inc(C.ESTIMATOR_STRUCTURE_EVENTS)
        g_sd = nm.gamma_sd
        if rules.on_sample(nm.diag, nm.prm, t, g, g_sd, nis, restart is not None, False, nm.out):
            self._report(nm, t)
        diag = nm.diag
        self.sink.on_sample(Sample(nm.node, t, float(outputs[0]), float(out.y_est[0]), g,
                                   out.rules, _STATES[int(diag[rules.REPORTED])], nis,
                                   nm.truth_gamma, bool(diag[rules.FLAGGED] != 0.0),
                                   inputs=tuple(u.tolist()), outputs=tuple(y.tolist()),
                                   predicted=tuple(out.y_est.tolist()),
                                   gammas=tuple(out.gamma.tolist()), gamma_sd=g_sd,
                                   output_noise=tuple(out.output_noise.tolist()),
                                   process_noise=float(out.process_noise[0])))
        if self.counters_due(t):
            self.emit_counters(t)

    # ------------------------------------------------------------------ diagnosis out

    def _report(self, nm: NodeMonitor, t: float) -> None:
        """What a step of a node's diagnosis rules at t reported (`nm.out`, laid out as
        `rules.OUT`): its counts, the events of what changed -- the flag's first, then the
        reported state's -- and the `Diagnosis` due."""
        out = nm.out
        if out[rules.MISMATCH]:
            self.counters.inc(C.NODES_MODEL_MISMATCH)
        if out[rules.SILENT]:
            self.counters.inc(C.NODES_SILENT)
        ev = out[rules.EV]
        flag = out[rules.FLAG]
        before = _STATES[out[rules.PREV]]
        if flag:
            self._event(nm, t, before, before, rules.FLAG_CAUSES[flag - 1], MODEL_MISMATCH)
        new = nm.state
        if ev == 1 and new != before:
            self._event(nm, t, before, new, rules.HEALTH_CAUSES[out[rules.CAUSE]], HEALTH)
        if ev:
            self._diagnosis_due(nm, t)

    def _event(self, nm: NodeMonitor, t: float, prev: HealthState, new: HealthState,
               cause: str, kind: str) -> None:
        ev = DiagnosisEvent(t=t, node=nm.node, state=new.label, previous=prev.label,
                            gamma=nm.gamma, fault_input=nm.fault_input,
                            rules=nm.estimator.out.rules, cause=cause,
                            model_mismatch=nm.model_mismatch, kind=kind)
        if kind == HEALTH:
            self.counters.inc(C.transition(new.label))
        self.sink.on_transition(ev)

    def _diagnosis_due(self, nm: NodeMonitor, t: float) -> None:
        """A node's `Diagnosis` at t (the rules said it is due)."""
        self.sink.on_diagnosis(Diagnosis(nm.node, t, nm.state, nm.gamma, nm.fault_input,
                                         nm.estimator.out.rules, nm.model_mismatch))

    def _drive_reports(self, reports: list[DriveReport]) -> None:
        """What a CANopen drive said about itself: counted, and a bus event each."""
        for r in reports:
            self.sink.on_bus_event(self.drive_report(r))

    def rate_change(self, t: float, node: int, change: int) -> BusEvent:
        """Count and log a node's samples leaving (or coming back to) the nominal rate
        (`admission.rate_event`); its bus event (both engines)."""
        counter, event = rate_event(t, node, change, self.cfg.rate)
        if counter is not None:
            self.counters.inc(counter)
            self.warn.warn(f"rate-{node}", event.text)
        return event

    def drive_report(self, report: DriveReport) -> BusEvent:
        """Count what a CANopen drive said about itself; its bus event (both engines)."""
        self.counters.inc(report_counter(report))
        return drive_event(report)

    def tick(self, now: float) -> None:
        """Timeouts and steady publication, at bus time `now` (no frame needed)."""
        if self.drives is not None:  # a heartbeat lost on a bus gone silent
            self._drive_reports(self.drives.tick(now))
        for nm in self.nodes.values():  # silence, and steady publication while silent
            if rules.on_tick(nm.diag, nm.prm, now, nm.out):
                self._report(nm, now)
        # Counters go with estimated samples (at their time stamps); when none come (a
        # silent bus, error frames, an outage) they still reach the sinks.
        if now - self._last_counters_t >= 2.0 * self.cfg.counters_period_s:
            self.emit_counters(now)

    def counters_due(self, t: float) -> bool:
        """Whether the counters are due at a sample's time t (every `counters_period_s`)."""
        return t - self._last_counters_t >= self.cfg.counters_period_s

    def emit_counters(self, t: float) -> None:
        """Hand every counter to the sink at time `t` (also called on exit)."""
        self._last_counters_t = t
        self.sink.on_counters(t, self.counters)

    # ------------------------------------------------------------------ the interface

    def interface_failed(self, t: float, reason: str) -> None:
        """The CAN interface failed: a new outage (not a failed reopen during one)."""
        self.counters.inc(C.BUS_OUTAGES)
        self.sink.on_bus_event(BusEvent(t, f"CAN interface failed: {reason}", "ERROR"))

    def interface_back(self, t: float, outage_s: float) -> None:
        """The CAN interface delivers frames again after `outage_s` seconds."""
        self.counters.inc(C.BUS_RECONNECTS)
        self.sink.on_bus_event(BusEvent(t, f"CAN interface back after {outage_s:.1f} s", "WARN"))

    def socket_drops(self, total: int) -> None:
        """Frames the kernel dropped before the monitor could read them, since start."""
        self.counters[C.BUS_SOCKET_DROPS] = total

    def summary(self) -> dict[str, Any]:
        return {
            "counters": dict(sorted(self.counters.items())),
            "nodes": {
                n: {"state": nm.state.label, "model_mismatch": nm.model_mismatch,
                    "gamma": nm.gamma,
                    "rules": nm.estimator.out.rules, "samples": nm.samples}
                for n, nm in sorted(self.nodes.items())
            },
        }
