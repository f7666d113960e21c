"""Files written again every period (`monitor.files.PeriodicWrite`): the SecOC freshness
saver and the metrics' textfile, each read back, with a failing disk logged once a burst."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import pytest
from prometheus_client.parser import text_string_to_metric_families

from monitor.bus.secoc import SecOC
from monitor.runtime.freshness import FreshnessSaver
from monitor.sinks.metrics import MetricsSink

KEY = bytes.fromhex("000102030405060708090a0b0c0d0e0f")


def test_freshness_is_saved_each_period_and_a_failing_burst_is_logged_once(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "state" / "secoc.state"
    path.parent.mkdir()
    secoc = SecOC(KEY)
    saver = FreshnessSaver(secoc, str(path), period_s=10.0)
    start = 1e9  # a monotonic time far ahead of the saver's start
    saver.maybe_write(start)
    assert SecOC(KEY).load_state(path) is not None  # the period had passed: saved
    path.unlink()
    saver.maybe_write(start + 5.0)
    assert not path.exists()  # within the period: nothing written
    shutil.rmtree(path.parent)
    with caplog.at_level(logging.WARNING):
        for k in range(1, 4):  # three failing periods: one line
            saver.maybe_write(start + 10.0 * k)
    failures = [r.getMessage() for r in caplog.records if "cannot write" in r.getMessage()]
    assert len(failures) == 1 and str(path) in failures[0] and "retrying every 10 s" in failures[0]
    assert "\n" not in failures[0]
    path.parent.mkdir()
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        saver.maybe_write(start + 40.0)
    assert SecOC(KEY).load_state(path) is not None
    assert [r.getMessage() for r in caplog.records] == [
        f"the SecOC state to {path}: written again"]
    assert saver.final() is None


def test_metrics_textfile_is_written_at_first_and_again_after_a_failure(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    directory = tmp_path / "textfile"
    directory.mkdir()
    path = directory / "monitor.prom"
    sink = MetricsSink(path, period_s=5.0, live=False)
    sink.maybe_flush(0.0)  # the first call writes: the file exists from the start
    names = {f.name for f in text_string_to_metric_families(path.read_text())}
    assert "motor_monitor_up" in names  # read back by Prometheus' own parser
    shutil.rmtree(directory)
    with caplog.at_level(logging.WARNING):
        sink.maybe_flush(5.0)
        sink.maybe_flush(10.0)
        sink.flush()
    assert sum("cannot write metrics" in r.getMessage() for r in caplog.records) == 1
    directory.mkdir()
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        sink.maybe_flush(15.0)
    assert path.exists()
    assert [r.getMessage() for r in caplog.records] == [f"metrics to {path}: written again"]
    sink.close()
