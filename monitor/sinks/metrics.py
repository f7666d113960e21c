"""Bus and monitor health for operators: Prometheus / OpenMetrics text through
node_exporter's textfile collector.

`MetricsSink` keeps the latest figures it is handed (per node: health state, model-mismatch
flag, gamma^ and its standard deviation, the windowed NIS, the estimator's noise factors,
estimation latency; the pipeline's counters; the bus statistics of
`monitor.bus.stats.BusStats`) and every `period_s` writes them to a ``.prom`` file with
`prometheus_client.write_to_textfile` (a temporary file renamed over the old one, so
node_exporter never reads half a file and the hardened unit needs no IP socket). The
exposition is prometheus_client's; the names:

    motor_monitor_node_health_state{node}          0 fault_free, 1 fault, 2 outage, 3 no_data
    motor_monitor_node_model_mismatch{node}        1 while the node's model-mismatch flag is
                                                   up (beside the state, which it keeps)
    motor_monitor_node_gamma{node}                 latest gamma^
    motor_monitor_node_gamma_sd{node}              its standard deviation (what the
                                                   diagnosis may weigh it by)
    motor_monitor_node_nis{node}                   windowed NIS (p when the model fits)
    motor_monitor_node_output_noise_factor{node,output}
                                                   the output's noise variance as the
                                                   estimator has adapted it, a factor on the
                                                   model's (1: the model's noise fits; above:
                                                   the sensor is noisier than it says);
                                                   output: the rig's signal name
    motor_monitor_node_process_noise_factor{node}  the factor the estimator puts on the
                                                   model's process noise (1 to 100; far
                                                   above 1: the model misses dynamics, and
                                                   a loss shows less in gamma^)
    motor_monitor_node_samples_total{node}         from 0, for every node asked for (--nodes)
    motor_monitor_nothing_decoded                  1 while no sample was decoded (of a node
                                                   asked for, or of any node) since the
                                                   silence timeout after start; else 0
    motor_monitor_estimation_latency_seconds       histogram: frame timestamp to estimate
    motor_monitor_events_total{name}               every pipeline counter (frames/received,
                                                   rejected/<reason>, bus/errors/<condition>,
                                                   e2e/lost_frames, bus/socket_drops, ...)
    motor_monitor_bus_load_ratio                   share of the bit rate, last second
    motor_monitor_bus_frames_total / _error_frames_total
    motor_monitor_id_frames_total{id}, motor_monitor_id_period_seconds{id},
    motor_monitor_id_jitter_seconds{id}            per arbitration ID
    motor_monitor_up, motor_monitor_last_write_timestamp_seconds

Alerting on a monitor that runs but diagnoses nothing (a wrong rig, node layout, DBC or
key; a bus that carries no frame of the rig): ``motor_monitor_nothing_decoded == 1`` (the
daemon's own judgement, `monitor.pipeline.counters.DecodeWatch`, whose one journal line
gives the counts by outcome and the likely cause), or from the counters alone
``increase(motor_monitor_node_samples_total[10m]) == 0``. Both series are there from the
first write (``frames/received`` and ``samples/estimated`` of `motor_monitor_events_total`
too, at 0), so a rule never has to tell a missing series from a stopped one.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator, Mapping
from pathlib import Path

from prometheus_client import CollectorRegistry, Histogram, write_to_textfile
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from monitor.bus.stats import BusStats
from monitor.files import PeriodicWrite
from monitor.pipeline import counters as C
from monitor.pipeline.counters import DecodeWatch
from monitor.pipeline.events import PlantSignals, Sample
from monitor.sinks.base import Sink

__all__ = ["MetricsSink"]


PREFIX = "motor_monitor"
_LATENCY_BUCKETS = (1e-4, 2.5e-4, 5e-4, 1e-3, 2.5e-3, 5e-3, 1e-2, 2.5e-2, 5e-2, 0.1, 0.25, 1.0)


class _Figures(Collector):
    """The latest figures, as metric families at collect time (counters mirrored, not
    re-counted: the pipeline's counters are the one source)."""

    def __init__(self, bus: BusStats | None, watch: DecodeWatch | None,
                 signals: PlantSignals) -> None:
        self.bus = bus
        self.watch = watch
        self.signals = signals
        self.counters: Mapping[str, int] = {}
        self.nodes: dict[int, Sample] = {}
        self.samples: dict[int, int] = {}
        self.nis: dict[int, float] = {}

    def collect(self) -> Iterator[Metric]:
        up = GaugeMetricFamily(f"{PREFIX}_up", "1 while the monitor runs")
        up.add_metric([], 1.0)
        yield up
        written = GaugeMetricFamily(f"{PREFIX}_last_write_timestamp_seconds",
                                    "when this file was written (Unix time)")
        written.add_metric([], time.time())
        yield written
        ev = CounterMetricFamily(f"{PREFIX}_events", "the pipeline's counters: every frame's "
                                 "outcome, bus errors, publication", labels=["name"])
        counts = {C.FRAMES_RECEIVED: 0, C.SAMPLES_ESTIMATED: 0, **self.counters}
        for name, value in sorted(counts.items()):
            ev.add_metric([name], float(value))
        yield ev
        if self.watch is not None:
            silent = GaugeMetricFamily(f"{PREFIX}_nothing_decoded", "1 while no sample was "
                                       "decoded since the silence timeout after start (of a "
                                       "node asked for, or of any node)")
            silent.add_metric([], 1.0 if self.watch.active else 0.0)
            yield silent
        state = GaugeMetricFamily(f"{PREFIX}_node_health_state", "0 fault_free, 1 fault, "
                                  "2 outage, 3 no_data", labels=["node"])
        mismatch = GaugeMetricFamily(f"{PREFIX}_node_model_mismatch", "1 while the model "
                                     "does not explain the plant (windowed NIS outside its "
                                     "band), beside the health state", labels=["node"])
        gamma = GaugeMetricFamily(f"{PREFIX}_node_gamma", "estimated loss of effectiveness",
                                  labels=["node"])
        gamma_sd = GaugeMetricFamily(f"{PREFIX}_node_gamma_sd", "standard deviation of the "
                                     "estimated loss of effectiveness", labels=["node"])
        nis = GaugeMetricFamily(f"{PREFIX}_node_nis", "normalised innovation squared, "
                                "windowed", labels=["node"])
        output_noise = GaugeMetricFamily(
            f"{PREFIX}_node_output_noise_factor", "the output's noise variance as the "
            "estimator has adapted it, a factor on the model's (1: the model's noise fits)",
            labels=["node", "output"])
        process_noise = GaugeMetricFamily(
            f"{PREFIX}_node_process_noise_factor", "the factor the estimator puts on the "
            "model's process noise (1 to 100; far above 1: the model misses dynamics and a "
            "loss shows less)", labels=["node"])
        samples = CounterMetricFamily(f"{PREFIX}_node_samples", "estimated samples",
                                      labels=["node"])
        for n, s in sorted(self.nodes.items()):
            state.add_metric([str(n)], float(int(s.state)))
            mismatch.add_metric([str(n)], 1.0 if s.model_mismatch else 0.0)
            gamma.add_metric([str(n)], s.gamma)
            gamma_sd.add_metric([str(n)], s.gamma_sd)
            nis.add_metric([str(n)], self.nis.get(n, math.nan))
            for j, factor in enumerate(s.output_noise):
                output_noise.add_metric([str(n), self.signals.output(j)[0]], factor)
            process_noise.add_metric([str(n)], s.process_noise)
        asked = self.watch.nodes if self.watch is not None and self.watch.nodes else ()
        for n in sorted({*self.nodes, *asked}):
            samples.add_metric([str(n)], float(self.samples.get(n, 0)))
        yield from (state, mismatch, gamma, gamma_sd, nis, output_noise, process_noise, samples)
        bus = self.bus
        if bus is None:
            return
        load = GaugeMetricFamily(f"{PREFIX}_bus_load_ratio", "share of the bit rate the "
                                 "frames took over the last second (worst-case stuffing)")
        load.add_metric([], bus.load)
        frames = CounterMetricFamily(f"{PREFIX}_bus_frames", "frames received")
        frames.add_metric([], float(bus.frames))
        errors = CounterMetricFamily(f"{PREFIX}_bus_error_frames", "error frames received")
        errors.add_metric([], float(bus.error_frames))
        per = CounterMetricFamily(f"{PREFIX}_id_frames", "frames per arbitration ID",
                                  labels=["id"])
        period = GaugeMetricFamily(f"{PREFIX}_id_period_seconds", "mean spacing of an ID's "
                                   "frames", labels=["id"])
        jitter = GaugeMetricFamily(f"{PREFIX}_id_jitter_seconds", "standard deviation of an "
                                   "ID's frame spacing", labels=["id"])
        for (fid, ext), st in sorted(bus.ids.items()):
            label = f"0x{fid:08X}" if ext else f"0x{fid:03X}"
            per.add_metric([label], float(st.frames))
            period.add_metric([label], st.period_s)
            jitter.add_metric([label], st.jitter_s)
        yield from (load, frames, errors, per, period, jitter)


class MetricsSink(Sink):
    """Writes the monitor's figures to `path` (a ``.prom`` file in node_exporter's textfile
    directory) every `period_s`, and at close. `live` measures estimation latency (frame
    timestamp to estimate, wall clock): off for replays. `watch`, the daemon's
    `DecodeWatch`, gives `motor_monitor_nothing_decoded` and the nodes asked for.
    `signals` names the outputs in the ``output`` label (the rig's,
    `monitor.setup.plant_signals`; default: our bus's)."""

    def __init__(self, path: str | Path, *, bus: BusStats | None = None,
                 period_s: float = 5.0, live: bool = True, nis_window_s: float = 2.0,
                 watch: DecodeWatch | None = None, signals: PlantSignals | None = None) -> None:
        self.path = Path(path)
        if self.path.suffix != ".prom":
            raise ValueError(f"{self.path}: node_exporter's textfile collector reads *.prom")
        if not self.path.parent.is_dir():
            raise ValueError(f"{self.path.parent}: no such directory")
        self.live = live
        self.registry = CollectorRegistry(auto_describe=False)
        self.figures = _Figures(bus, watch,
                                signals if signals is not None else PlantSignals())
        self.registry.register(self.figures)
        self.latency = Histogram(f"{PREFIX}_estimation_latency_seconds", "from a frame's "
                                 "timestamp to its estimate (wall clock)",
                                 buckets=_LATENCY_BUCKETS, registry=self.registry)
        self._nis_window_s = nis_window_s
        self._nis_t: dict[int, float] = {}
        self._writes = PeriodicWrite(self._write, f"metrics to {self.path}", period_s)

    def on_sample(self, sample: Sample) -> None:
        f = self.figures
        n = sample.node
        f.nodes[n] = sample
        f.samples[n] = f.samples.get(n, 0) + 1
        prev, last_t = f.nis.get(n), self._nis_t.get(n)
        self._nis_t[n] = sample.t
        if prev is None or prev != prev or last_t is None:
            f.nis[n] = sample.nis
        else:  # exponential average with a time constant of nis_window_s
            a = 1.0 - math.exp(-max(sample.t - last_t, 0.0) / self._nis_window_s)
            f.nis[n] = prev + a * (sample.nis - prev)
        if self.live:
            self.latency.observe(max(0.0, time.time() - sample.t))

    def on_counters(self, t: float, counters: Mapping[str, int]) -> None:
        self.figures.counters = dict(counters)

    def maybe_flush(self, now_monotonic: float) -> None:
        self._writes.maybe_write(now_monotonic)

    def flush(self) -> None:
        self._writes.write()

    def _write(self) -> None:
        write_to_textfile(str(self.path), self.registry)

    def close(self) -> None:
        self.flush()
