"""RerunSink: write real .rrd files / a real gRPC stream and read back what the sink wrote."""

from __future__ import annotations

import argparse
import contextlib
import gc
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import tracemalloc
import uuid
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
import rerun.blueprint as rrb
from numpy.typing import NDArray
from rerun.chunk import RrdReader

from monitor.diagnosis import HealthState
from monitor.pipeline.events import (
    BusEvent,
    Diagnosis,
    DiagnosisEvent,
    InputSample,
    PlantSignals,
    Sample,
    SampleColumns,
)
from monitor.sinks.base import Sink
from monitor.sinks.blueprint import STYLES, default_blueprint, node_path, signal_parts
from monitor.sinks.rerun import (
    DEFAULT_FLUSH_INTERVAL_S,
    RUNS,
    RerunSink,
    recording_parts,
    run_ends,
)
from monitor.sinks.rotation import RotatingRerunSink
from monitor.sinks.runs import SLOW_ROW_S, bin_starts
from tests.conftest import _ci_enabled
from tests.support.rrd import blueprint_names, chunk_series, entity_chunks, recording_rows

T0 = 1_700_000_000.0  # epoch seconds, like CAN kernel time stamps
DT = 1e-3
N = 2000
RERUN_EXE = Path(sys.executable).with_name("rerun")


def _values(k: int, node: int
            ) -> tuple[float, float, float, int, int, float, float, float, float]:
    measured = math.sin(0.01 * k) + 0.1 * node
    estimated = measured + 1e-3 * math.cos(0.1 * k)
    gamma = k / N + 0.25 * node
    rules = 1 + k // 400
    health = min(3, k // 600)
    nis = 0.5 + (k % 7) / 7
    gamma_sd = 0.2 / (1 + k) + 0.01 * node
    output_noise = 1.0 + k / N + 0.5 * node
    process_noise = 1.0 + 0.3 * math.sin(0.02 * k) ** 2 + node
    return (measured, estimated, gamma, rules, health, nis, gamma_sd, output_noise,
            process_noise)


def _static_entities(path: Path) -> set[str]:
    return {c.entity_path for c in RrdReader(path).stream() if c.is_static}


def _write_run(sink: RerunSink) -> None:
    """2 nodes x N samples, inputs, events, counters and a threshold change."""
    for k in range(N):
        t = T0 + k * DT
        for node in (0, 1):
            m, e, g, r, h, nis, sd, on, pn = _values(k, node)
            sink.add_sample(node, t, m, e, g, r, h, nis, true_gamma=0.5 if node == 0 else None,
                            gamma_sd=sd, output_noise=(on,), process_noise=pn)
        if k % 20 == 0:
            sink.add_input(0, t, 24.0 + k / N)
        if k == 1200:
            sink.log_event(1, t, "node 1: health 1 -> 2 (degraded)", level="warning")
        if k == 1000:
            sink.set_thresholds(0.2, 0.9)
        if k % 500 == 499:
            sink.log_counters(t, {"frames_ok": k + 1, "rejected/crc": k // 500})


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rrd") / "run.rrd"
    sink = RerunSink(
        rrd_path=path, nodes=(0, 1), batch_size=128, recording_id="test-run", f1=0.15, f2=0.85
    )
    _write_run(sink)
    sink.close()
    sink.close()  # idempotent
    return path


def test_rrd_verify(recorded: Path) -> None:
    proc = subprocess.run(
        [str(RERUN_EXE), "rrd", "verify", str(recorded)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr


def test_recording_and_blueprint_stores(recorded: Path) -> None:
    reader = RrdReader(recorded)
    (rec,) = reader.recordings()
    assert rec.application_id == "motor-monitor"
    assert rec.recording_id == "test-run"
    assert len(list(reader.blueprints())) == 1
    names = blueprint_names(recorded)
    assert {
        "node 0",
        "node 1",
        "ArmatureCurrent: measured vs estimated",
        "VoltageCommand (V)",
        "gamma^ vs thresholds",
        "rule count",
        "health state",
        "noise factors (1: the model's)",
        "events",
        "daemon counters",
    } <= names


def _views(c: rrb.Container) -> Iterator[rrb.View]:
    for x in c.contents:
        if isinstance(x, rrb.Container):
            yield from _views(x)
        else:
            yield x


def test_gamma_view_shows_every_gamma_series() -> None:
    """A node's "gamma^ vs thresholds" view takes its origin's whole subtree, so gamma^'s
    standard deviation is drawn beside gamma^, the true gamma and the thresholds."""
    root = default_blueprint([4]).root_container
    assert root is not None
    (view,) = [v for v in _views(root) if v.name == "gamma^ vs thresholds"]
    assert view.origin == "/node/4/gamma" and view.contents == "$origin/**"
    assert [s[0] for s in STYLES if s[0].startswith("gamma/")] == [
        "gamma/estimate", "gamma/sd", "gamma/true", "gamma/F1", "gamma/F2"]
    assert node_path(4, "gamma/sd").startswith(f"{view.origin}/")


def test_noise_factors_have_a_view_of_their_own() -> None:
    """The estimator's noise factors (ratios near 1) are drawn together in one view, not in
    their outputs' measured-vs-estimated views (amperes, volts...), which show those two
    series only."""
    sig = PlantSignals(outputs=(("Speed", "rad/s"), ("Position", "rad")))
    root = default_blueprint([4], sig).root_container
    assert root is not None
    views = {v.name: v for v in _views(root)}
    for output in ("Speed", "Position"):
        view = views[f"{output}: measured vs estimated"]
        assert view.origin == f"/node/4/{output}"
        assert view.contents == ["$origin/measured", "$origin/estimated"]
    noise = views["noise factors (1: the model's)"]
    assert noise.origin == "/node/4"
    assert noise.contents == ["$origin/Speed/noise", "$origin/Position/noise",
                              "$origin/process_noise"]
    assert "process_noise" in [s[0] for s in STYLES]
    assert signal_parts(PlantSignals(outputs=(("process_noise", None),)))[1] == (
        "process_noise_signal",)  # a signal cannot take the factor's entity


def _latest_at(t: NDArray[np.float64], v: NDArray[np.float64],
               at: NDArray[np.float64]) -> NDArray[np.float64]:
    """The value a latest-at query (the viewer's at a time cursor) gives at each time `at`."""
    i = np.searchsorted(t, at, side="right") - 1
    assert np.all(i >= 0), "a time before the first row"
    return v[i]


def test_samples_read_back_exactly(recorded: Path) -> None:
    ents = entity_chunks(recorded)
    k = np.arange(N)
    expected_t = T0 + k * DT
    for node in (0, 1):
        vals = np.array([_values(i, node) for i in range(N)], dtype=np.float64)
        t_samples, _ = chunk_series(ents[f"/node/{node}/gamma/estimate"])
        for col, suffix in enumerate(
            ["ArmatureCurrent/measured", "ArmatureCurrent/estimated", "gamma/estimate", "rules",
             "health", "nis", "gamma/sd", "ArmatureCurrent/noise", "process_noise"]
        ):
            t, v = chunk_series(ents[f"/node/{node}/{suffix}"])
            if suffix in RUNS:
                # piecewise constant: recorded as its runs; the same latest value at every
                # sample, the same line (straight or stepped), first and last sample included
                assert len(v) < N // 10, suffix
                np.testing.assert_array_equal(_latest_at(t, v, t_samples), vals[:, col])
                np.testing.assert_array_equal(np.interp(t_samples, t, v), vals[:, col])
                np.testing.assert_array_equal(t[[0, -1]], t_samples[[0, -1]])
                continue
            if suffix.endswith("noise"):
                # slowly varying: the samples that open each SLOW_ROW_S of the time axis
                kept = bin_starts(expected_t, -math.inf, SLOW_ROW_S)
                assert 0 < kept.sum() < N // 5, suffix
                np.testing.assert_array_equal(v, vals[kept, col], err_msg=suffix)
                np.testing.assert_allclose(t, expected_t[kept], rtol=0, atol=1e-6)
                continue
            assert len(v) == N, suffix
            np.testing.assert_array_equal(v, vals[:, col], err_msg=suffix)
            np.testing.assert_allclose(t, expected_t, rtol=0, atol=1e-6)
    t, v = chunk_series(ents["/node/0/gamma/estimate"])
    assert v[-1] == _values(N - 1, 0)[2] == (N - 1) / N
    # the true gamma exists only where it was given; constant, so a few rows span it
    t, v = chunk_series(ents["/node/0/gamma/true"])
    assert np.all(v == 0.5) and len(v) < N // 10
    np.testing.assert_allclose(t[[0, -1]], expected_t[[0, -1]], rtol=0, atol=1e-6)
    assert "/node/1/gamma/true" not in ents
    assert "/node/1/gamma/true" not in _static_entities(recorded)


def test_run_ends_keep_the_line() -> None:
    nan = math.nan
    assert list(run_ends(np.array([1.0]))) == [True]
    assert list(run_ends(np.array([1.0]), previous=1.0)) == [True]  # the last row: always
    assert list(run_ends(np.array([1.0, 1.0, 1.0, 2.0, 2.0]), previous=1.0)) == [
        False, False, True, True, True]
    assert list(run_ends(np.array([1.0, 1.0, 1.0]), previous=nan)) == [True, False, True]
    assert len(run_ends(np.zeros(0))) == 0
    # in batches, with the last value of each carried over, like the sink
    rng = np.random.default_rng(7)
    for _ in range(200):
        n = int(rng.integers(1, 300))
        v = rng.integers(0, 3, size=n).cumsum() * (rng.random(n) < 0.05)
        v = np.repeat(v, rng.integers(1, 9, size=n))[:n].astype(np.float64)
        t = np.arange(n, dtype=np.float64)
        cuts = np.sort(rng.choice(np.arange(1, n), size=min(n - 1, 4), replace=False)) if n > 1 \
            else np.zeros(0, dtype=np.int64)
        kept_t: list[NDArray[np.float64]] = []
        kept_v: list[NDArray[np.float64]] = []
        previous = math.nan
        for tb, vb in zip(np.split(t, cuts), np.split(v, cuts), strict=True):
            keep = run_ends(vb, previous)
            previous = float(vb[-1])
            kept_t.append(tb[keep])
            kept_v.append(vb[keep])
        tk, vk = np.concatenate(kept_t), np.concatenate(kept_v)
        assert tk[0] == 0 and tk[-1] == n - 1
        np.testing.assert_array_equal(np.interp(t, tk, vk), v)  # the straight line
        np.testing.assert_array_equal(_latest_at(tk, vk, t), v)  # the stepped one
        assert len(tk) <= 2 * (np.count_nonzero(np.diff(v)) + 1) + len(cuts)


def test_bin_starts_keep_one_row_per_bin_across_batches() -> None:
    """One row per bin of the time axis, the first of it, however the rows are batched."""
    assert list(bin_starts(np.array([0.0, 0.05, 0.1, 0.15, 0.31]), -math.inf, 0.1)) == [
        True, False, True, False, True]
    assert list(bin_starts(np.array([0.12, 0.25]), 0.11, 0.1)) == [False, True]
    assert len(bin_starts(np.zeros(0), -math.inf, 0.1)) == 0
    rng = np.random.default_rng(3)
    for _ in range(100):
        t = np.cumsum(rng.uniform(0.001, 0.05, int(rng.integers(2, 400)))) + 1.7e9
        cuts = np.sort(rng.choice(np.arange(1, t.size), size=min(t.size - 1, 5),
                                  replace=False))
        previous, kept = -math.inf, []
        for tb in np.split(t, cuts):
            kept.append(tb[bin_starts(tb, previous, 0.1)])
            previous = float(tb[-1])
        tk = np.concatenate(kept)
        bins = np.floor(t / 0.1)
        assert len(tk) == len(np.unique(bins))  # one row per bin the rows fall in
        np.testing.assert_array_equal(np.floor(tk / 0.1), np.unique(bins))


def test_thresholds_span_the_data_and_step(recorded: Path) -> None:
    ents = entity_chunks(recorded)
    t_est, _ = chunk_series(ents["/node/0/gamma/estimate"])
    t_change = T0 + 1000 * DT
    for suffix, old, new in (("F1", 0.15, 0.2), ("F2", 0.85, 0.9)):
        t, v = chunk_series(ents[f"/node/0/gamma/{suffix}"])
        assert t[0] == t_est[0] and t[-1] == t_est[-1]
        np.testing.assert_array_equal(v[t < t_change - 1e-7], old)
        np.testing.assert_array_equal(v[t > t_change - 1e-7], new)
    assert "/node/0/gamma/F1" in _static_entities(recorded)  # styled


def test_inputs_counters_and_event(recorded: Path) -> None:
    ents = entity_chunks(recorded)
    _, v = chunk_series(ents["/node/0/VoltageCommand"])
    assert len(v) == N // 20 and v[-1] == 24.0 + (N - 20) / N
    assert "/node/1/VoltageCommand" not in ents

    _, v = chunk_series(ents["/monitor/counters/frames_ok"])
    np.testing.assert_array_equal(v, [500, 1000, 1500, 2000])
    _, v = chunk_series(ents["/monitor/counters/rejected/crc"])
    np.testing.assert_array_equal(v, [0, 1, 2, 3])

    (event,) = ents["/node/1/events"]
    rb = event.to_record_batch()
    assert rb.column("TextLog:text").flatten().to_pylist() == ["node 1: health 1 -> 2 (degraded)"]
    assert rb.column("TextLog:level").flatten().to_pylist() == ["WARN"]
    t_event = rb.column("time").cast(pa.int64()).to_numpy()[0] / 1e9
    assert t_event == pytest.approx(T0 + 1200 * DT, abs=1e-6)


def test_event_comes_after_the_samples_before_it(recorded: Path) -> None:
    """An event is buffered and sent at the next flush, after the samples buffered with it:
    in file order, every sample of node 1 up to the event time is written before the event
    (and the event is not a chunk of its own per call: see the batching test below)."""
    chunks = [c for c in RrdReader(recorded).stream() if not c.is_static]
    i_event = next(i for i, c in enumerate(chunks) if c.entity_path == "/node/1/events")
    t_event = T0 + 1200 * DT
    before, _ = chunk_series([c for c in chunks[:i_event]
                              if c.entity_path == "/node/1/gamma/estimate"])
    assert len(before) >= 1201
    np.testing.assert_allclose(before[:1201], T0 + DT * np.arange(1201), atol=1e-6)
    assert (before <= t_event + 1e-6).sum() == 1201


def test_events_between_flushes_are_one_chunk(tmp_path: Path) -> None:
    """A replay's transitions go out as columns: many events between two flushes are one
    chunk per entity, in time order, every one of them."""
    path = tmp_path / "ev.rrd"
    sink = RerunSink(rrd_path=path, nodes=(0,), flush_interval_s=1e9)
    for k in range(300):
        sink.add_sample(0, T0 + k * DT, 1.0, 1.0, 0.0, 1, 1, 1.0)
        if k % 3 == 0:
            sink.log_event(0, T0 + k * DT, f"event {k}", "WARN" if k % 2 else "INFO")
    sink.log_event(-1, T0, "bus: error frame", "ERROR")
    sink.close()
    chunks = [c for c in RrdReader(path).stream() if not c.is_static]
    (events,) = [c for c in chunks if c.entity_path == "/node/0/events"]
    rb = events.to_record_batch()
    assert rb.column("TextLog:text").flatten().to_pylist() == [
        f"event {k}" for k in range(0, 300, 3)]
    assert rb.column("TextLog:level").flatten().to_pylist()[:2] == ["INFO", "WARN"]
    (bus,) = [c for c in chunks if c.entity_path == "/monitor/events"]
    assert bus.to_record_batch().column("TextLog:text").flatten().to_pylist() == [
        "bus: error frame"]


def test_maybe_flush_makes_data_visible_while_open(tmp_path: Path) -> None:
    path = tmp_path / "open.rrd"
    sink = RerunSink(rrd_path=path, batch_size=10_000, flush_interval_s=0.2)
    for k in range(10):
        sink.add_sample(0, T0 + k * DT, 1.0, 1.0, 0.1 * k, 1, 0, 1.0)
    now = time.monotonic()
    sink.maybe_flush(now)  # < flush_interval since construction: keeps buffering
    sink.recording.flush(timeout_sec=10)
    assert "/node/0/gamma/estimate" not in entity_chunks(path)
    sink.maybe_flush(now + 0.25)
    sink.recording.flush(timeout_sec=10)
    _, v = chunk_series(entity_chunks(path)["/node/0/gamma/estimate"])
    np.testing.assert_array_equal(v, 0.1 * np.arange(10))
    sink.close()


def test_close_twice_and_use_after_close(tmp_path: Path) -> None:
    path = tmp_path / "c.rrd"
    with RerunSink(rrd_path=path, nodes=(3,)) as sink:
        sink.add_sample(3, T0, 1.0, 1.0, 0.5, 1, 0, 1.0)
    assert sink.closed
    sink.close()
    sink.add_sample(3, T0 + 1, 1.0, 1.0, 0.5, 1, 0, 1.0)  # ignored, no error
    sink.log_event(3, T0 + 1, "late")
    sink.flush()
    _, v = chunk_series(entity_chunks(path)["/node/3/gamma/estimate"])
    assert list(v) == [0.5]


def test_unannounced_node_is_added(tmp_path: Path) -> None:
    path = tmp_path / "n.rrd"
    with RerunSink(rrd_path=path, nodes=(0,)) as sink:
        sink.add_sample(7, T0, 1.0, 1.0, 0.25, 1, 0, 1.0)
    _, v = chunk_series(entity_chunks(path)["/node/7/gamma/estimate"])
    assert list(v) == [0.25]
    _, sd = chunk_series(entity_chunks(path)["/node/7/gamma/sd"])  # none given: NaN
    assert len(sd) == 1 and math.isnan(sd[0])
    for noise in ("ArmatureCurrent/noise", "process_noise"):  # none given: NaN
        _, v = chunk_series(entity_chunks(path)[f"/node/7/{noise}"])
        assert len(v) == 1 and math.isnan(v[0]), noise


def test_needs_a_destination() -> None:
    with pytest.raises(ValueError):
        RerunSink()


def test_null_sink_and_protocol(tmp_path: Path) -> None:
    null = Sink()
    with null as s:
        s.on_sample(Sample(0, T0, 1.0, 1.0, 0.5, 1, HealthState.FAULT_FREE, 1.0, 0.5))
        s.on_input(InputSample(0, T0, 24.0))
        s.on_transition(DiagnosisEvent(T0, 0, "fault", "fault_free", 0.5, 12.0, 2, "estimate"))
        s.on_diagnosis(Diagnosis(0, T0, HealthState.FAULT, 0.5, 12.0, 2))
        s.on_bus_event(BusEvent(T0, "x", "ERROR"))
        s.on_counters(T0, {"a": 1})
        s.maybe_flush(time.monotonic())
        s.flush()
    null.close()
    with RerunSink(rrd_path=tmp_path / "p.rrd") as sink:
        assert isinstance(sink, Sink)


def test_memory_bounded_and_buffers_reused(tmp_path: Path) -> None:
    n = 100_000
    sink = RerunSink(rrd_path=tmp_path / "m.rrd", nodes=(0,), batch_size=64, write_footer=False)
    node = sink._nodes[0]
    buffers = [node.t, node.gamma, node.gamma_sd, node.measured, node.health]
    ids = [id(b) for b in buffers]

    def feed(start: int, count: int) -> None:
        for k in range(start, start + count):
            sink.add_sample(0, T0 + k * 1e-4, 1.0, 1.0, 0.3, 2, 1, 1.0, 0.3)

    feed(0, 5_000)  # warm up caches (descriptors, arrow types, ...)
    gc.collect()
    tracemalloc.start()
    try:
        before, _ = tracemalloc.get_traced_memory()
        feed(5_000, n)
        sink.flush()
        # Rerun keeps the Arrow copies of the batches alive until its writer thread has
        # encoded them: wait for that, then nothing of the 10^5 samples may remain.
        sink.recording.flush(timeout_sec=30)
        gc.collect()
        after, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    sink.close()
    assert [id(b) for b in (node.t, node.gamma, node.gamma_sd, node.measured,
                            node.health)] == ids
    assert all(b.shape[-1] == 64 for b in buffers)  # the outputs' one row per output
    # 10^5 samples of 9 float64 would be 7.2 MB if they were kept
    assert after - before < 256 * 1024, (before, after)


def test_runs_in_small_batches_cost_about_a_row_a_second(tmp_path: Path) -> None:
    """At the default 0.1 s flush a run that goes on sends a row a second, not one a batch;
    what was held back goes at `switch_file` and `close`, so every line reaches the end of
    its file's data, and each line is still the line through every sample."""
    first, second = tmp_path / "a.rrd", tmp_path / "b.rrd"
    sink = RerunSink(rrd_path=first, nodes=(0,))
    start = time.monotonic() + 10.0
    sink.maybe_flush(start)
    n = 1000  # 10 s at 100 Hz
    changes = (300, 505, 700, 701, 702, 950)
    health = np.cumsum(np.isin(np.arange(2 * n), changes)) % 3
    truth = np.where(health == 1, 0.4, 0.0)
    for k in range(2 * n):
        if k == n:
            sink.switch_file(second)
        sink.add_sample(0, T0 + k * 0.01, 1.0, 1.0, 0.5, 2, int(health[k]), 1.0,
                        true_gamma=float(truth[k]))
        sink.maybe_flush(start + (k + 1) * 0.01)
    sink.close()
    for path, part in ((first, slice(0, n)), (second, slice(n, 2 * n))):
        ents = entity_chunks(path)
        t_samples, _ = chunk_series(ents["/node/0/gamma/estimate"])
        assert len(t_samples) == n
        for suffix, full in (("health", health[part]), ("gamma/true", truth[part]),
                             ("rules", np.full(n, 2.0)), ("gamma/F1", np.full(n, 0.15))):
            t, v = chunk_series(ents[f"/node/0/{suffix}"])
            assert len(v) <= 10 + 2 + 2 * len(changes), (suffix, len(v))
            np.testing.assert_array_equal(t[[0, -1]], t_samples[[0, -1]])
            np.testing.assert_array_equal(_latest_at(t, v, t_samples), full, err_msg=suffix)
            np.testing.assert_array_equal(np.interp(t_samples, t, v), full, err_msg=suffix)


# -- live streaming to a headless gRPC receiver -------------------------------------------


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def _headless_receiver(save_to: Path) -> Iterator[str]:
    """`rerun --port P --save FILE` hosts a gRPC proxy without a viewer and writes whatever
    SDKs stream to it into FILE. One that does not start is a skip, and a failure with CI
    set (tests/conftest.py)."""
    port = _free_port()
    proc = subprocess.Popen(
        [str(RERUN_EXE), "--bind", "127.0.0.1", "--port", str(port), "--save", str(save_to)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        start_new_session=True,  # the `rerun` script runs the real binary as a child
    )
    try:
        deadline = time.monotonic() + 30
        while True:
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", port)) == 0:
                    break
            if proc.poll() is not None or time.monotonic() > deadline:
                err = proc.stderr.read().decode() if proc.stderr else ""
                why = f"headless rerun receiver did not start: {err[-500:]}"
                if _ci_enabled():  # in CI the receiver must run, as vcan must
                    pytest.fail(f"CI is set, so this may not be skipped: {why}", pytrace=False)
                pytest.skip(why)
            time.sleep(0.05)
        yield f"rerun+http://127.0.0.1:{port}/proxy"
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
        if proc.stderr:
            proc.stderr.close()


def test_live_stream_to_headless_server_and_file_at_once(tmp_path: Path) -> None:
    received = tmp_path / "received.rrd"
    local = tmp_path / "local.rrd"
    rec_id = f"live-{uuid.uuid4().hex[:8]}"
    n = 500
    with _headless_receiver(received) as url:
        sink = RerunSink(
            rrd_path=local, connect_url=url, nodes=(0,), batch_size=64, recording_id=rec_id
        )
        for k in range(n):
            sink.add_sample(0, T0 + k * DT, 1.0, 2.0, k / n, 1, 0, 1.0)
        sink.log_event(0, T0 + n * DT, "live hello")
        sink.close()
        deadline = time.monotonic() + 30
        got: NDArray[np.float64] = np.zeros(0)
        while time.monotonic() < deadline:
            with contextlib.suppress(Exception):  # the file may end in a partial message
                if received.exists():
                    ents = entity_chunks(received)
                    _, got = chunk_series(ents.get("/node/0/gamma/estimate", []))
                    if len(got) == n and "/node/0/events" in ents:
                        break
            time.sleep(0.1)
    assert len(got) == n
    np.testing.assert_array_equal(got, np.arange(n) / n)
    _, v_local = chunk_series(entity_chunks(local)["/node/0/gamma/estimate"])
    np.testing.assert_array_equal(v_local, got)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert {r.recording_id for r in RrdReader(received).recordings()} == {rec_id}


# -- durability: the flush interval, switching files, rotation with a live stream ---------------


def test_maybe_flush_reaches_the_disk_without_waiting(tmp_path: Path) -> None:
    """No `recording.flush` here: `send_columns` bypasses the SDK's batcher and its file writer
    does not buffer, so what `maybe_flush` sends is in the file within milliseconds."""
    assert DEFAULT_FLUSH_INTERVAL_S <= 0.2
    path = tmp_path / "fast.rrd"
    sink = RerunSink(rrd_path=path, nodes=(0,))  # the default flush interval
    start = time.monotonic()
    for k in range(5):
        sink.add_sample(0, T0 + k * DT, 1.0, 1.0, 0.1 * k, 1, 0, 1.0)
    sink.maybe_flush(start + DEFAULT_FLUSH_INTERVAL_S)
    sent = time.monotonic()
    got: NDArray[np.float64] = np.zeros(0)
    while time.monotonic() - sent < 0.1 and len(got) < 5:
        with contextlib.suppress(Exception):  # maybe in the middle of a write
            _, got = chunk_series(entity_chunks(path).get("/node/0/gamma/estimate", []))
        time.sleep(0.002)
    latency = time.monotonic() - sent
    sink.close()
    np.testing.assert_array_equal(got, 0.1 * np.arange(5))
    assert latency < 0.1, latency


def test_a_recording_split_into_parts_holds_every_row_once(tmp_path: Path) -> None:
    """`part_bytes`: the recording goes on into ``<stem>-part0002.rrd``... once a file has
    reached the size; every part passes ``rerun rrd verify``, all are one recording, and
    their rows together are every sample once, in order. Stale parts of an earlier run to
    the same path are deleted at start."""
    path = tmp_path / "log.rrd"
    stale = tmp_path / "log-part0009.rrd"
    stale.write_bytes(b"an earlier run's part")
    other = tmp_path / "log2-part0002.rrd"  # another recording's part: kept
    other.write_bytes(b"x")
    sink = RerunSink(rrd_path=path, nodes=(0,), recording_id="parts", batch_size=1000,
                     part_bytes=100_000)
    assert not stale.exists() and other.exists()
    n = 40_000
    k = np.arange(n, dtype=np.float64)
    cols = SampleColumns(t=T0 + k * DT, measured=np.sin(k), estimated=np.cos(k), gamma=k,
                         rules=np.ones(n, np.int64), state=np.zeros(n, np.int64),
                         nis=np.ones(n), true_gamma=np.full(n, np.nan),
                         model_mismatch=np.zeros(n, np.bool_))
    for a in range(0, n, 3000):  # uneven slices across the batch boundaries
        at = slice(a, a + 3000)
        sink.on_sample_columns(0, SampleColumns(
            cols.t[at], cols.measured[at], cols.estimated[at], cols.gamma[at], cols.rules[at],
            cols.state[at], cols.nis[at], cols.true_gamma[at], cols.model_mismatch[at]))
    sink.close()
    parts = list(sink.parts)
    assert parts == recording_parts(path)
    assert len(parts) >= 3, parts
    assert parts[1].name == "log-part0002.rrd"
    proc = subprocess.run([str(RERUN_EXE), "rrd", "verify", *map(str, parts)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    gammas = []
    for p in parts:
        (rec,) = RrdReader(p).recordings()
        assert rec.recording_id == "parts"
        assert "/node/0/gamma/estimate" in entity_chunks(p)
        gammas.append(chunk_series(entity_chunks(p)["/node/0/gamma/estimate"])[1])
    np.testing.assert_array_equal(np.concatenate(gammas), k)
    sds = np.concatenate([chunk_series(entity_chunks(p)["/node/0/gamma/sd"])[1] for p in parts])
    assert len(sds) == n and np.isnan(sds).all()  # columns without gamma_sd: NaN
    with pytest.raises(ValueError, match="part_bytes"):
        RerunSink(connect_url="rerun+http://127.0.0.1:1/proxy", part_bytes=1)


def test_switch_file_finishes_the_old_file_and_starts_a_complete_one(tmp_path: Path) -> None:
    first, second = tmp_path / "a.rrd", tmp_path / "b.rrd"
    sink = RerunSink(rrd_path=first, nodes=(0,), recording_id="sw", f1=0.1, f2=0.9)
    for k in range(300):
        sink.add_sample(0, T0 + k * DT, 1.0, 1.0, float(k), 1, 0, 1.0, true_gamma=0.5)
    sink.log_counters(T0, {"frames_ok": 1})
    sink.set_thresholds(0.2, 0.8)
    sink.add_sample(5, T0 + 300 * DT, 1.0, 1.0, 300.0, 1, 0, 1.0)  # a new node
    sink.switch_file(second)
    assert sink.rrd_path == second
    # the old file is finished when switch_file returns
    proc = subprocess.run([str(RERUN_EXE), "rrd", "verify", str(first)], capture_output=True)
    assert proc.returncode == 0, proc.stderr
    for k in range(301, 400):
        sink.add_sample(0, T0 + k * DT, 1.0, 1.0, float(k), 1, 0, 1.0, true_gamma=0.5)
    sink.log_counters(T0 + 1, {"frames_ok": 2})
    sink.close()
    _, a = chunk_series(entity_chunks(first)["/node/0/gamma/estimate"])
    _, b = chunk_series(entity_chunks(second)["/node/0/gamma/estimate"])
    np.testing.assert_array_equal(a, np.arange(300))  # everything before the switch
    np.testing.assert_array_equal(b, np.arange(301, 400))  # everything after
    # self-contained: recording, start time, styles, blueprint with every node, thresholds
    reader = RrdReader(second)
    (rec,) = reader.recordings()
    assert rec.recording_id == "sw"
    assert {
        "/__properties",
        "/node/0/gamma/F1",
        "/node/0/gamma/sd",
        "/node/0/gamma/true",
        "/node/5/nis",
        "/monitor/counters/frames_ok",
    } <= _static_entities(second)
    (bp,) = reader.blueprints()
    names = {
        x
        for chunk in reader.stream(store=bp)
        for col in chunk.to_record_batch().schema.names
        if col.endswith("Blueprint:display_name")
        for row in chunk.to_record_batch().column(col).to_pylist()
        if row
        for x in row
    }
    assert {"node 0", "node 5"} <= names
    _, f1 = chunk_series(entity_chunks(second)["/node/0/gamma/F1"])
    assert np.all(f1 == 0.2)


def test_switch_file_does_not_leak_threads(tmp_path: Path) -> None:
    """`RecordingStream.send_blueprint` would leave a blueprint stream (two threads, ~1 MB)
    behind per call; the sink reuses one."""
    sink = RerunSink(rrd_path=tmp_path / "0.rrd", nodes=(0, 1))
    sink.switch_file(tmp_path / "1.rrd")
    threads = len(os.listdir("/proc/self/task"))
    for i in range(2, 22):
        sink.add_sample(0, T0 + i, 1.0, 1.0, 0.5, 1, 0, 1.0)
        sink.switch_file(tmp_path / f"{i}.rrd")
    assert len(os.listdir("/proc/self/task")) <= threads
    sink.close()
    proc = subprocess.run(
        [str(RERUN_EXE), "rrd", "verify", *(str(tmp_path / f"{i}.rrd") for i in range(22))],
        capture_output=True,
    )
    assert proc.returncode == 0, proc.stderr


def test_switch_file_refuses_live_and_closed_sinks(tmp_path: Path) -> None:
    with _headless_receiver(tmp_path / "received.rrd") as url:
        sink = RerunSink(rrd_path=tmp_path / "a.rrd", connect_url=url)
        with pytest.raises(ValueError):
            sink.switch_file(tmp_path / "b.rrd")
        sink.close()
    sink = RerunSink(rrd_path=tmp_path / "c.rrd")
    sink.close()
    with pytest.raises(RuntimeError):
        sink.switch_file(tmp_path / "d.rrd")


def test_rotating_sink_streams_live_across_rotations(tmp_path: Path) -> None:
    received = tmp_path / "received.rrd"
    out = tmp_path / "files"
    n = 3000
    with _headless_receiver(received) as url:
        sink = RotatingRerunSink(
            out, max_bytes=50_000, max_age_s=None, keep=None, connect_url=url, nodes=(0,),
            batch_size=128,
        )  # fmt: skip
        assert isinstance(sink, Sink)
        for k in range(n):
            sink.add_sample(0, T0 + k * DT, 1.0, 2.0, float(k), 1, 0, 1.0)
            if k % 100 == 99:
                sink.recording.flush(timeout_sec=10)
                sink.flush()
        sink.close()
        assert sink.rotations >= 3
        deadline = time.monotonic() + 30
        got: NDArray[np.float64] = np.zeros(0)
        while time.monotonic() < deadline and len(got) < n:
            with contextlib.suppress(Exception):  # the file may end in a partial message
                if received.exists():
                    _, got = chunk_series(entity_chunks(received).get("/node/0/gamma/estimate", []))
            time.sleep(0.1)
    np.testing.assert_array_equal(got, np.arange(n))  # one connection, nothing lost
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert {r.recording_id for r in RrdReader(received).recordings()} == {sink.recording_id}
    files = sink.files()
    parts = [chunk_series(entity_chunks(p)["/node/0/gamma/estimate"])[1] for p in files]
    np.testing.assert_array_equal(np.concatenate(parts), np.arange(n))
    assert {RrdReader(p).recordings()[0].recording_id for p in files} == {sink.recording_id}


# -- the flush interval and compaction ------------------------------------------------------


def _gamma_rows(path: Path) -> int:
    with contextlib.suppress(Exception):  # maybe in the middle of a write
        return len(chunk_series(entity_chunks(path).get("/node/0/gamma/estimate", []))[1])
    return -1


@pytest.mark.parametrize("kind", ["one file", "rotating"])
def test_a_larger_flush_interval_is_honoured(tmp_path: Path, kind: str) -> None:
    """--record-flush-s 2: the buffers wait 2 s of the caller's clock, then all go at once."""
    sink: RerunSink | RotatingRerunSink
    if kind == "one file":
        sink = RerunSink(rrd_path=tmp_path / "slow.rrd", nodes=(0,), flush_interval_s=2.0)
        path = tmp_path / "slow.rrd"
    else:
        sink = RotatingRerunSink(tmp_path, max_bytes=None, max_age_s=None, keep=None,
                                 nodes=(0,), flush_interval_s=2.0)
        path = sink.path
    assert sink.flush_interval_s == 2.0
    start = time.monotonic() + 10.0
    sink.maybe_flush(start)  # the clock starts here (nothing to send yet)
    for batch in range(2):
        for k in range(150):  # 1.5 s of 100 Hz
            i = 150 * batch + k
            sink.add_sample(0, T0 + i * 0.01, 1.0, 1.0, float(i), 1, 0, 1.0)
            sink.maybe_flush(start + 2.0 * batch + k * 0.01)
        sink.maybe_flush(start + 2.0 * batch + 1.99)
        sink.recording.flush(timeout_sec=10)
        assert _gamma_rows(path) == 150 * batch  # nothing of this batch yet
        sink.maybe_flush(start + 2.0 * (batch + 1))
        sink.recording.flush(timeout_sec=10)
        assert _gamma_rows(path) == 150 * (batch + 1)
    sink.close()
    _, v = chunk_series(entity_chunks(path)["/node/0/gamma/estimate"])
    np.testing.assert_array_equal(v, np.arange(300))


def _parse(*extra: str) -> argparse.Namespace:
    from monitor.app.cli import build_parser

    return build_parser().parse_args(["run", "--interface", "virtual", *extra])


def test_run_wires_the_flush_interval_and_compaction(tmp_path: Path) -> None:
    from monitor.app import outputs
    from monitor.pipeline import MonitorConfig

    rrd = ("--rrd", str(tmp_path / "one.rrd"))
    raw = ("--raw-dir", str(tmp_path))
    # the default stays 0.1 s, with or without the raw bus log
    assert outputs.record_flush_s(_parse(*rrd)) == DEFAULT_FLUSH_INTERVAL_S == 0.1
    assert outputs.record_flush_s(_parse(*rrd, *raw)) == DEFAULT_FLUSH_INTERVAL_S
    assert outputs.record_flush_s(_parse(*rrd, "--record-flush-s", "0.25")) == 0.25
    assert outputs.record_flush_s(_parse(*rrd, *raw, "--record-flush-s", "5")) == 5.0
    cfg = MonitorConfig(nodes=(0,))
    one = outputs.rerun_sink(_parse(*rrd, *raw, "--record-flush-s", "2"), cfg)
    assert isinstance(one, RerunSink) and one.flush_interval_s == 2.0
    one.close()
    files = tmp_path / "files"
    files.mkdir()
    rotating = outputs.rerun_sink(_parse("--record-dir", str(files)), cfg)
    assert isinstance(rotating, RotatingRerunSink)
    assert rotating.flush_interval_s == DEFAULT_FLUSH_INTERVAL_S
    assert rotating.compactor is not None  # rotated files are compacted
    for k in range(100):
        rotating.add_sample(0, T0 + k * 0.01, 1.0, 1.0, 0.0, 1, 0, 1.0)
    rotating.rotate()
    assert rotating.compactor.wait(60)
    counters: dict[str, int] = {}
    outputs.count_compactions(rotating, counters)
    assert counters == {"recording/compacted": 1}
    rotating.close()
    outputs.count_compactions(one, counters)  # no compactor: nothing to count
    assert counters == {"recording/compacted": 1}


@pytest.mark.parametrize(("extra", "message"), [
    (("--rrd", "{tmp}/x.rrd", "--record-flush-s", "2"),
     "--record-flush-s: 2 s needs --raw-dir (without the raw bus log a kill may lose at most "
     "0.25 s of the recording)"),
    (("--raw-dir", "{tmp}", "--record-flush-s", "2"),
     "--record-flush-s: there is no recording file to flush (give --rrd or --record-dir)"),
    (("--rrd", "{tmp}/x.rrd", "--record-flush-s", "0"),
     "argument --record-flush-s: must be positive: '0'"),
    (("--rrd", "{tmp}/x.rrd", "--record-flush-s", "nan"),
     "argument --record-flush-s: must be positive: 'nan'"),
    (("--rrd", "{tmp}/x.rrd", "--record-flush-s", "soon"),
     "argument --record-flush-s: not a number: 'soon'"),
])
def test_flush_interval_mistakes_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                              extra: tuple[str, ...], message: str) -> None:
    from monitor.app.cli import main

    argv = ["run", "--interface", "virtual", "--channel", f"flush-{uuid.uuid4().hex}",
            *(a.format(tmp=tmp_path) for a in extra)]
    try:
        rc = main(argv)
    except SystemExit as exc:  # argparse's own errors
        rc = int(exc.code or 0)
    err = capsys.readouterr().err
    assert rc == 2
    assert [ln for ln in err.splitlines() if ln.strip()] == [
        ln for ln in err.splitlines() if "error:" in ln], err
    assert len(err.strip().splitlines()) == 1 and err.rstrip().endswith(
        message if "argument" not in message else message + " (see motor-monitor run --help)"
    ), err
    assert not list(tmp_path.iterdir())  # nothing written


def test_compact_rrd_keeps_every_row(tmp_path: Path) -> None:
    """`compact_rrd` rewrites a whole recording (samples, voltages, events, counters, a
    threshold change, the blueprint store) with the real ``rerun rrd optimize``: it verifies,
    has a few times fewer chunks, is smaller, and holds every row of the file as written."""
    from monitor.sinks.compact import compact_rrd

    path, before = tmp_path / "run.rrd", tmp_path / "before.rrd"
    sink = RerunSink(rrd_path=path, nodes=(0, 1), batch_size=128)
    _write_run(sink)
    sink.close()
    shutil.copyfile(path, before)
    saved = compact_rrd(path)
    assert saved == before.stat().st_size - path.stat().st_size > 0
    proc = subprocess.run([str(RERUN_EXE), "rrd", "verify", str(path)], capture_output=True)
    assert proc.returncode == 0, proc.stderr
    n_before = sum(1 for _ in RrdReader(before).stream())
    n_after = sum(1 for _ in RrdReader(path).stream())
    assert n_after < n_before / 3, (n_before, n_after)
    assert recording_rows(path) == recording_rows(before)
    assert {k[0] for k in recording_rows(path)} >= {"/node/0/gamma/estimate", "/node/1/events",
                                          "/monitor/counters/frames_ok"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["before.rrd", "run.rrd"]
