"""The bus outlet: each due `Diagnosis` becomes a MonitorDiagnosis frame on the bus."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import can

from monitor.bus.codec import MotorDatabase
from monitor.pipeline import counters as C
from monitor.pipeline.counters import Counters
from monitor.pipeline.events import Diagnosis
from monitor.sinks.base import Sink

__all__ = ["BusPublisher"]

log = logging.getLogger("motor_monitor")

_WARN_PERIOD_S = 10.0
_FAULT_LIMIT_V = 999.0  # what FaultEstimate (V: our bus's input) can carry


class BusPublisher(Sink):
    """Encodes diagnoses with the DBC (alive counter and E2E CRC per node) and hands the
    frames to `send` (e.g. a bus's `send`; it may raise `can.CanError`, e.g. while the
    interface is down). Every outcome is counted in `counters` (the pipeline's):
    `publish/sent`, `publish/errors`, `publish/encode_errors`."""

    def __init__(self, db: MotorDatabase, send: Callable[[can.Message], None],
                 counters: Counters) -> None:
        self.db = db
        self.send = send
        self.counters = counters
        self._alive: dict[int, int] = {}
        self._last_warning: dict[str, float] = {}

    def on_diagnosis(self, diagnosis: Diagnosis) -> None:
        node = diagnosis.node
        fault = max(-_FAULT_LIMIT_V, min(_FAULT_LIMIT_V, diagnosis.fault_input))
        counter = self._alive.get(node, 0)
        try:
            data = self.db.encode_diagnosis(node, int(diagnosis.state), diagnosis.gamma, fault,
                                            min(diagnosis.rules, 255), counter,
                                            diagnosis.model_mismatch)
        except ValueError as exc:  # a value the DBC cannot carry: count, never crash
            self.counters.inc(C.PUBLISH_ENCODE_ERRORS)
            self._warn("encode", f"node {node}: cannot encode diagnosis: {exc}")
            return
        self._alive[node] = (counter + 1) % 16
        msg = can.Message(arbitration_id=self.db.frame_id("diagnosis", node), data=data,
                          is_extended_id=False, timestamp=diagnosis.t)
        try:
            self.send(msg)
            self.counters.inc(C.PUBLISH_SENT)
        except can.CanError as exc:
            self.counters.inc(C.PUBLISH_ERRORS)
            self._warn("publish", f"cannot send diagnosis: {exc}")

    def _warn(self, key: str, message: str) -> None:
        now = time.monotonic()
        if now - self._last_warning.get(key, -_WARN_PERIOD_S) >= _WARN_PERIOD_S:
            self._last_warning[key] = now
            log.warning("%s", message)
