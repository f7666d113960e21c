"""Samples handed to the pipeline's sinks as columns.

A sink may take a node's samples as columns (`on_sample_columns(node, SampleColumns)`,
`on_input_columns(node, t, values, index)`; `monitor.sinks.rerun.RerunSink` does, and sends
them with ``rr.send_columns``). `SinkRouter` walks a `FanOut` and gives each sink what it
takes: columns where it has those methods; one `Sample` / `InputSample` at a time to any
other sink that overrides `on_sample` / `on_input`; nothing to a sink that ignores samples
(the JSON events, the log).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from numpy.typing import NDArray

from monitor.pipeline.events import InputSample, SampleColumns
from monitor.sinks.base import FanOut, Sink

__all__ = ["SampleColumns", "SinkRouter"]

log = logging.getLogger("motor_monitor")


def _leaves(sink: Sink) -> list[Sink]:
    if isinstance(sink, FanOut):
        return [x for s in sink.sinks for x in _leaves(s)]
    return [sink]


class SinkRouter:
    """Hands columns of samples to every sink of a (fan-out) sink, each as it takes them."""

    def __init__(self, sink: Sink) -> None:
        self.columns: list[Any] = []
        self.rows: list[Sink] = []
        self.input_rows: list[Sink] = []
        leaves = _leaves(sink)
        self.wants_diagnosis = any(type(s).on_diagnosis is not Sink.on_diagnosis for s in leaves)
        """Whether any sink takes the due `Diagnosis` (else they are not even built)."""
        for s in leaves:
            if hasattr(s, "on_sample_columns"):
                self.columns.append(s)
            else:
                if type(s).on_sample is not Sink.on_sample:
                    self.rows.append(s)
                if type(s).on_input is not Sink.on_input:
                    self.input_rows.append(s)

    def samples(self, node: int, cols: SampleColumns) -> None:
        for s in self.columns:
            s.on_sample_columns(node, cols)
        if self.rows:
            rows = cols.rows(node)
            for s in self.rows:
                for r in rows:
                    s.on_sample(r)

    def inputs(self, node: int, t: NDArray[np.float64], values: NDArray[np.float64],
               index: NDArray[np.int64]) -> None:
        """A node's inputs as its frames carried them: row i is input `index[i]` at `t[i]`,
        every input of every frame in bus order (as `InputSample`)."""
        for s in self.columns:
            s.on_input_columns(node, t, values, index)
        for s in self.input_rows:
            for i in range(len(t)):
                s.on_input(InputSample(node, float(t[i]), float(values[i]), int(index[i])))
