"""The pipeline's events onto a recording's column API: the adapter between the pipeline's
`Sink` protocol and the Rerun sinks (`monitor.sinks.rerun`), and the recording's settings."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Final

from monitor.pipeline.events import BusEvent, DiagnosisEvent, DriveEvent, InputSample, Sample
from monitor.sinks.base import Sink

__all__ = ["DEFAULT_FLUSH_INTERVAL_S", "REPLAY_BATCH_SIZE", "REPLAY_PART_BYTES", "RecordingOutlet"]

# The recording's settings live here, apart from the modules that import rerun-sdk: a daemon
# that records nothing does not import it (`monitor.setup.recording_sink` does, when asked).

DEFAULT_FLUSH_INTERVAL_S: Final = 0.1
"""Buffered samples reach the file at most this long after they were added (plus the period of
the `maybe_flush` calls and ~1 ms of writing)."""

REPLAY_BATCH_SIZE: Final = 1 << 15
"""Rows per chunk when a replay is recorded (`RerunSink` ``batch_size``): nothing waits for a
replay's samples, so each chunk is as large as a compacted file's (256 KiB a float64 column;
``rerun rrd optimize`` aims at 2 MiB chunks). Against the live default of 2,048 rows, a replay
of 10^7 frames writes 16x fewer chunks (the footer manifest the SDK holds in memory until the
file closes shrinks with them), a ~30 % smaller file, ~25 % faster (`python -m
tests.bench.pipeline`)."""

REPLAY_PART_BYTES: Final = 1 << 30
"""A replay's recording goes on into a new part once its file has reached this size
(`RerunSink` ``part_bytes``): about 4*10^7 frames of a 100 Hz node, an hour of a saturated
1 Mbit/s bus. A part is what the viewer loads whole into memory, and the SDK keeps each open
file's footer manifest (a few kB a chunk) in memory until it closes: parts keep both bounded
however long the log."""


class RecordingOutlet(Sink):
    """The pipeline's events onto a recording's column API (`add_sample`, `add_input`,
    `log_event`, `log_counters`). An outlet that records implements the API; one that
    spreads its rows over others (`RotatingRerunSink`: the files and a live viewer) gives
    them by `outlets`, and each call goes to every one of them."""

    _closed: bool = False
    _flush_interval_s: float
    """`maybe_flush` flushes once this long has passed since the last flush."""
    _last_flush: float
    """`time.monotonic` at the last flush."""

    def maybe_flush(self, now_monotonic: float) -> None:
        """Flush (`flush`: the buffers, and what else is due) if ``flush_interval_s`` has
        passed since the last flush."""
        if now_monotonic - self._last_flush >= self._flush_interval_s:
            self.flush()
            self._last_flush = now_monotonic

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def flush_interval_s(self) -> float:
        """`maybe_flush` flushes once this long has passed since the last flush."""
        return self._flush_interval_s

    def outlets(self) -> Sequence[RecordingOutlet]:
        """The outlets the column API forwards to (an outlet that records overrides it)."""
        raise NotImplementedError

    def add_sample(self, node: int, t: float, measured: float, estimated: float,
                   gamma_hat: float, rule_count: int, health: int, nis: float,
                   true_gamma: float | None = None, model_mismatch: bool = False, *,
                   outputs: Sequence[float] = (), predicted: Sequence[float] = (),
                   gamma_sd: float = math.nan, output_noise: Sequence[float] = (),
                   process_noise: float = math.nan) -> None:
        """Buffer one estimator sample (see `RerunSink.add_sample`)."""
        for o in self.outlets():
            o.add_sample(node, t, measured, estimated, gamma_hat, rule_count, health, nis,
                         true_gamma, model_mismatch, outputs=outputs, predicted=predicted,
                         gamma_sd=gamma_sd, output_noise=output_noise,
                         process_noise=process_noise)

    def add_input(self, node: int, t: float, value: float, index: int = 0) -> None:
        for o in self.outlets():
            o.add_input(node, t, value, index)

    def log_event(self, node: int, t: float, text: str, level: str = "INFO") -> None:
        for o in self.outlets():
            o.log_event(node, t, text, level)

    def log_counters(self, t: float, counters: Mapping[str, int]) -> None:
        for o in self.outlets():
            o.log_counters(t, counters)

    def on_sample(self, sample: Sample) -> None:
        self.add_sample(sample.node, sample.t, sample.measured, sample.estimated, sample.gamma,
                        sample.rules, int(sample.state), sample.nis, sample.true_gamma,
                        sample.model_mismatch, outputs=sample.outputs,
                        predicted=sample.predicted, gamma_sd=sample.gamma_sd,
                        output_noise=sample.output_noise, process_noise=sample.process_noise)

    def on_input(self, sample: InputSample) -> None:
        self.add_input(sample.node, sample.t, sample.value, sample.index)

    def on_transition(self, event: DiagnosisEvent) -> None:
        self.log_event(event.node, event.t, event.text, event.level)

    def on_bus_event(self, event: BusEvent) -> None:
        # what a drive says of itself goes beside its node's diagnosis
        node = event.node if isinstance(event, DriveEvent) else -1
        self.log_event(node, event.t, event.text, event.level)

    def on_counters(self, t: float, counters: Mapping[str, int]) -> None:
        self.log_counters(t, counters)
