"""Samples handed to the pipeline's sinks as columns.

A sink may take a node's samples as columns (`on_sample_columns(node, SampleColumns)`,
`on_voltage_columns(node, t, volts)`). `SinkRouter` walks a `FanOut` and gives each sink
what it takes: columns where it has those methods; a `monitor.sinks.rerun.RerunSink` its
column buffers filled by slices (it sends them with ``rr.send_columns``, the same chunks and
the same rows as sample by sample); one `Sample` at a time to any other sink that overrides
`on_sample` / `on_voltage`; nothing to a sink that ignores samples (the JSON events, the
log).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from monitor.diagnosis import HealthState
from monitor.pipeline.events import Sample, VoltageSample
from monitor.sinks.base import FanOut, Sink

__all__ = ["SampleColumns", "SinkRouter"]

log = logging.getLogger("motor_monitor")
_STATES = tuple(HealthState)


@dataclass
class SampleColumns:
    """A node's estimator samples, one row each (`Sample`'s fields as columns; true_gamma
    NaN where none)."""

    t: NDArray[np.float64]
    measured: NDArray[np.float64]
    estimated: NDArray[np.float64]
    gamma: NDArray[np.float64]
    rules: NDArray[np.int64]
    state: NDArray[np.int64]
    nis: NDArray[np.float64]
    true_gamma: NDArray[np.float64]

    def rows(self, node: int) -> list[Sample]:
        tg = self.true_gamma
        return [Sample(node, float(self.t[i]), float(self.measured[i]),
                       float(self.estimated[i]), float(self.gamma[i]), int(self.rules[i]),
                       _STATES[int(self.state[i])], float(self.nis[i]),
                       None if tg[i] != tg[i] else float(tg[i]))
                for i in range(len(self.t))]


def _leaves(sink: Sink) -> list[Sink]:
    if isinstance(sink, FanOut):
        return [x for s in sink.sinks for x in _leaves(s)]
    return [sink]


def _rerun_buffers(sink: Sink) -> bool:
    """A RerunSink whose column buffers this module knows how to fill."""
    from monitor.sinks.rerun import RerunSink

    return isinstance(sink, RerunSink) and all(
        hasattr(sink, a) for a in ("_nodes", "_new_node", "_batch_size", "_flush_samples",
                                   "_flush_voltage", "_closed"))


class SinkRouter:
    """Hands columns of samples to every sink of a (fan-out) sink, each as it takes them."""

    def __init__(self, sink: Sink) -> None:
        self.columns: list[Any] = []
        self.rerun: list[Any] = []
        self.rows: list[Sink] = []
        self.volt_rows: list[Sink] = []
        leaves = _leaves(sink)
        self.wants_diagnosis = any(type(s).on_diagnosis is not Sink.on_diagnosis for s in leaves)
        """Whether any sink takes the due `Diagnosis` (else they are not even built)."""
        for s in leaves:
            if hasattr(s, "on_sample_columns"):
                self.columns.append(s)
            elif _rerun_buffers(s):
                self.rerun.append(s)
            else:
                if type(s).on_sample is not Sink.on_sample:
                    self.rows.append(s)
                if type(s).on_voltage is not Sink.on_voltage:
                    self.volt_rows.append(s)

    def samples(self, node: int, cols: SampleColumns) -> None:
        for s in self.columns:
            s.on_sample_columns(node, cols)
        for s in self.rerun:
            _rerun_samples(s, node, cols)
        if self.rows:
            rows = cols.rows(node)
            for s in self.rows:
                for r in rows:
                    s.on_sample(r)

    def voltages(self, node: int, t: NDArray[np.float64], volts: NDArray[np.float64]) -> None:
        for s in self.columns:
            s.on_voltage_columns(node, t, volts)
        for s in self.rerun:
            _rerun_voltages(s, node, t, volts)
        for s in self.volt_rows:
            for i in range(len(t)):
                s.on_voltage(VoltageSample(node, float(t[i]), float(volts[i])))


def _rerun_samples(sink: Any, node: int, c: SampleColumns) -> None:
    """What `RerunSink.add_sample` does row by row, a slice at a time: fill the node's
    buffers up to the batch size, send them (`send_columns`), go on."""
    if sink._closed:
        return
    st = sink._nodes.get(node)
    if st is None:
        st = sink._new_node(node)
    size = sink._batch_size
    n = len(c.t)
    i = 0
    while i < n:
        at = st.n
        k = min(size - at, n - i)
        sl = slice(at, at + k)
        src = slice(i, i + k)
        st.t[sl] = c.t[src]
        st.measured[sl] = c.measured[src]
        st.estimated[sl] = c.estimated[src]
        st.gamma[sl] = c.gamma[src]
        st.true_gamma[sl] = c.true_gamma[src]
        st.rules[sl] = c.rules[src]
        st.health[sl] = c.state[src]
        st.nis[sl] = c.nis[src]
        st.n = at + k
        i += k
        if st.n == size:
            sink._flush_samples(st)


def _rerun_voltages(sink: Any, node: int, t: NDArray[np.float64],
                    volts: NDArray[np.float64]) -> None:
    if sink._closed:
        return
    st = sink._nodes.get(node)
    if st is None:
        st = sink._new_node(node)
    size = sink._batch_size
    n = len(t)
    i = 0
    while i < n:
        at = st.nv
        k = min(size - at, n - i)
        st.tv[at:at + k] = t[i:i + k]
        st.volts[at:at + k] = volts[i:i + k]
        st.nv = at + k
        i += k
        if st.nv == size:
            sink._flush_voltage(st)
