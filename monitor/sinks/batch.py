"""The column buffers of the Rerun sink: per node and per input, preallocated float64 rows
(``batch_size`` long, reused for the whole run) that a full batch, a flush or a timer sends
as one ``send_columns`` per entity; `fill` is the one way rows go into them."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from monitor.sinks.blueprint import STYLES, node_path
from monitor.sinks.runs import RunThinner

Array = NDArray[np.float64]

__all__ = ["InputColumns", "NodeColumns", "fill", "put_output_columns", "put_outputs"]


class InputColumns:
    """The column buffer of one input of a node: its own rate, its own rows."""

    __slots__ = ("n", "path", "t", "v")

    def __init__(self, path: str, batch_size: int) -> None:
        self.path = path
        self.n = 0
        self.t: Array = np.zeros(batch_size)
        self.v: Array = np.zeros(batch_size)


class NodeColumns:
    """Preallocated column buffers and entity paths of one node."""

    __slots__ = (
        "estimated",
        "gamma",
        "gamma_sd",
        "health",
        "inputs",
        "measured",
        "mismatch",
        "n",
        "nis",
        "node",
        "noise_paths",
        "out_paths",
        "output_noise",
        "path",
        "process_noise",
        "rules",
        "runs",
        "slow",
        "slow_last_t",
        "slow_sent_t",
        "t",
        "true_gamma",
        "true_styled",
    )

    def __init__(self, node: int, batch_size: int, outputs: Sequence[str]) -> None:
        self.node = node
        self.path: dict[str, str] = {s[0]: node_path(node, s[0]) for s in STYLES}
        self.path["events"] = node_path(node, "events")
        self.out_paths: list[tuple[str, str]] = [
            (node_path(node, f"{o}/measured"), node_path(node, f"{o}/estimated"))
            for o in outputs]
        """(measured, estimated) entity of each output."""
        self.noise_paths: list[str] = [node_path(node, f"{o}/noise") for o in outputs]
        """The entity of each output's noise factor."""
        self.n = 0
        self.t: Array = np.zeros(batch_size)
        # one row per output; NaN where a producer gives only the first output
        self.measured: Array = np.zeros((len(outputs), batch_size))
        self.estimated: Array = np.zeros((len(outputs), batch_size))
        self.gamma: Array = np.zeros(batch_size)
        self.gamma_sd: Array = np.zeros(batch_size)
        """gamma^'s standard deviation; NaN where a producer gives none."""
        self.true_gamma: Array = np.zeros(batch_size)
        self.rules: Array = np.zeros(batch_size)
        self.health: Array = np.zeros(batch_size)
        self.mismatch: Array = np.zeros(batch_size)
        self.nis: Array = np.zeros(batch_size)
        # the noise factors the estimator adapted (one row per output); NaN where a
        # producer gives none
        self.output_noise: Array = np.zeros((len(outputs), batch_size))
        self.process_noise: Array = np.zeros(batch_size)
        self.runs = RunThinner()
        """The run thinning of the node's piecewise-constant series (`RUNS`)."""
        self.slow_last_t = -math.inf
        """The time of the last sample sent to the file (-inf: none yet), where the slowly
        varying series' next bin starts from (`monitor.sinks.runs.bin_starts`)."""
        self.slow: list[tuple[Array, Array, Array]] = []
        """The slowly varying series' rows not yet sent, batch by batch: (times, output
        noise factors (one row per output), process noise factors). Held back so that they
        go at most once a second (`monitor.sinks.runs.RUN_TAIL_S`), one chunk per series,
        not one per flush: a chunk's framing costs far more than its few rows."""
        self.slow_sent_t = -math.inf
        """The time of the last slow row sent."""
        self.true_styled = False
        self.inputs: dict[int, InputColumns] = {}
        """Each input's buffer, by its index (one beyond the names given from its first
        row)."""


def fill(buf: NodeColumns | InputColumns, count: int, size: int,
         write: Callable[[slice, slice], None], full: Callable[[], None]) -> None:
    """Rows 0 .. count - 1 of a source into `buf` (``size`` rows), as many at a time as it
    has room for: write(dst, src) copies the source's rows src into the buffer's rows dst,
    full() sends a full buffer (which empties it)."""
    i = 0
    while i < count:
        at = buf.n
        k = min(size - at, count - i)
        write(slice(at, at + k), slice(i, i + k))
        buf.n = at + k
        i += k
        if buf.n == size:
            full()


def put_outputs(dst: Array, first: float, values: Sequence[float]) -> None:
    """One sample's outputs into a column of the output rows: `values` where given (as many
    as there are rows), else `first` into the first row and NaN into the others."""
    if len(values):
        k = min(len(values), len(dst))
        dst[:k] = values[:k]
        dst[k:] = math.nan
    else:
        dst[0] = first
        dst[1:] = math.nan


def put_output_columns(dst: Array, first: Array | float, values: Array | None,
                       rows: slice) -> None:
    """`put_outputs` for a slice of samples: `values` (one column per output) where given,
    else `first`."""
    if values is not None and values.shape[1]:
        k = min(values.shape[1], len(dst))
        dst[:k] = values[rows, :k].T
        dst[k:] = math.nan
    else:
        dst[0] = first
        dst[1:] = math.nan
