"""A node whose samples come at another rate than the rig's (or --rate) is said so, by both
engines alike (`monitor.pipeline.admission.rate_event`): a counter, a warning and a bus event
when it starts, an event when the samples come at the nominal rate again."""

from __future__ import annotations

from pathlib import Path

import can
import pytest

from monitor.bus.codec import load_database
from monitor.pipeline import MonitorConfig
from monitor.pipeline.admission import RATE_WINDOW
from tests.support.engines import compare_engines, sim_frames
from tests.support.log_readers import write_log

OFF_RATE = "time/off_rate"


def _restamped(frames: list[can.Message], start: float, end: float, stretch: float
               ) -> list[can.Message]:
    """The frames with the stretch of bus time [start, end) (from the first frame) slowed
    down `stretch` times, the frames after it shifted along."""
    t0 = frames[0].timestamp
    out = []
    for m in frames:
        t = m.timestamp - t0
        if t >= start:
            t = start + (min(t, end) - start) * stretch + max(0.0, t - end)
        out.append(can.Message(timestamp=t0 + t, arbitration_id=m.arbitration_id,
                               is_extended_id=m.is_extended_id, data=m.data))
    return out


@pytest.mark.parametrize("rate", [5.0, 1000.0])
def test_a_wrong_nominal_rate_is_said_once(tmp_path: Path, rate: float) -> None:
    # the ECU sends at 100 Hz; the rig says 5 Hz (or 1 kHz)
    path = write_log(tmp_path / "run.log", sim_frames("healthy"))
    db = load_database()
    res, _, seen = compare_engines(path, db, load_database(), MonitorConfig(rate=rate))
    assert res.counters[OFF_RATE] == 1
    [event] = [b for b in seen.bus if "nominal" in b.text]
    assert event.level == "WARN" and f"nominal {rate:g} Hz" in event.text
    assert "[bus] rate or --rate" in event.text
    # found at the end of the first window of intervals
    first = min(s.t for s in seen.samples)
    assert event.t == pytest.approx(first + RATE_WINDOW / 100.0, abs=0.02)


def test_the_nominal_rate_says_nothing(tmp_path: Path) -> None:
    path = write_log(tmp_path / "run.log", sim_frames("healthy"))
    res, _, seen = compare_engines(path, load_database(), load_database(), MonitorConfig())
    assert OFF_RATE not in res.counters
    assert not [b for b in seen.bus if "nominal" in b.text]


def test_an_ecu_that_slows_down_and_recovers_is_said_both_times(tmp_path: Path) -> None:
    # 3 s at 100 Hz, then 1.5 s of samples sent 20x slower (30 s at 5 Hz), then 100 Hz again
    frames = _restamped(sim_frames("healthy"), 3.0, 4.5, 20.0)
    path = write_log(tmp_path / "slow.log", frames)
    res, _, seen = compare_engines(path, load_database(), load_database(), MonitorConfig(),
                                   chunk=613)
    assert res.counters[OFF_RATE] == 1
    said = [(b.level, b.t - frames[0].timestamp) for b in seen.bus if "nominal" in b.text]
    assert [level for level, _ in said] == ["WARN", "INFO"]
    warn_t, info_t = said[0][1], said[1][1]
    assert 3.0 < warn_t <= 3.0 + 30.0 and info_t > 33.0
