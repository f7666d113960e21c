"""monitor.pipeline.feed: a recorded bus fed frame by frame, its timeouts checked in bus time."""

from __future__ import annotations

import can

from monitor.bus.codec import load_database
from monitor.pipeline import MonitorConfig, MonitorPipeline
from monitor.pipeline.feed import TICK_S, feed_log

T0 = 1_700_000_000.0


def test_on_tick_sees_every_check_at_its_bus_time() -> None:
    # frames every 1/64 s (exact in binary): a check at the first frame, then at the first
    # frame at least TICK_S after the last check, i.e. every 4th one
    assert 3 / 64 < TICK_S <= 4 / 64
    frames = [can.Message(arbitration_id=0x7FF, is_extended_id=False, data=b"",
                          timestamp=T0 + k / 64) for k in range(17)]
    pipe = MonitorPipeline(load_database(), MonitorConfig(nodes=(0,)))
    ticks: list[float] = []
    assert feed_log(pipe, frames, ticks.append) == 17
    assert ticks == [T0 + k / 64 for k in (0, 4, 8, 12, 16)]
