"""The live daemon's two ways in (`monitor.columnar.live.BacklogFeed`): frames one by one
through `MonitorPipeline.feed`, a backlog in one call through the `ColumnarEngine`, on one
pipeline's state. The same frames in the same batches, ticked between batches as the live
loop ticks, give the same events, samples, diagnoses and counters whether every batch goes
one way, the other, or each by its size: so the state each path leaves (estimator, held
inputs, alive counters, admission, diagnosis rules, drives) is the one the other reads."""

from __future__ import annotations

import math
from typing import Any

import can
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from monitor.bus.codec import load_database
from monitor.columnar.live import BacklogFeed
from monitor.pipeline import MonitorConfig, MonitorPipeline
from monitor.pipeline.feed import TICK_S
from tests.support.engines import sim_frames
from tests.support.pipeline import Recorder

ALL_PER_FRAME = 10**9


def _live(frames: list[can.Message], sizes: list[int], min_frames: int,
          cfg: MonitorConfig) -> tuple[Recorder, MonitorPipeline, BacklogFeed]:
    """`frames` in batches of `sizes` (cycled), each fed as `BacklogFeed` takes it, the
    timeouts checked after a batch as the live loop does (every `TICK_S` of the newest
    frame's time)."""
    rec = Recorder()
    pipe = MonitorPipeline(load_database(), cfg, sink=rec)
    feed = BacklogFeed(pipe, min_frames)
    last_tick = -math.inf
    i = k = 0
    while i < len(frames):
        batch = frames[i:i + sizes[k % len(sizes)]]
        i += len(batch)
        k += 1
        feed.feed(batch)
        newest = batch[-1].timestamp
        if newest - last_tick >= TICK_S:
            last_tick = newest
            pipe.tick(newest)
    return rec, pipe, feed


def _same(a: tuple[Recorder, MonitorPipeline, Any], b: tuple[Recorder, MonitorPipeline, Any]
          ) -> None:
    ra, pa, _ = a
    rb, pb, _ = b
    assert dict(pb.counters) == dict(pa.counters)
    assert rb.transitions == ra.transitions
    assert rb.diagnoses == ra.diagnoses
    assert rb.bus == ra.bus
    assert sorted(rb.inputs, key=lambda v: v.node) == sorted(ra.inputs, key=lambda v: v.node)
    assert sorted(rb.samples, key=lambda v: v.node) == sorted(ra.samples, key=lambda v: v.node)
    assert pb.summary()["nodes"] == pa.summary()["nodes"]


FRAMES = sim_frames("fault-outage-recovery", bad=True, drop=23, repeat=31, late=True,
                    nodes=(0, 1))[:5000]
"""Faults, bad, lost, repeated and late frames, two nodes."""


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.integers(1, 400), min_size=1, max_size=12), st.integers(1, 120))
def test_backlogs_and_single_frames_leave_the_same_state(sizes: list[int],
                                                         min_frames: int) -> None:
    frames = FRAMES
    cfg = MonitorConfig(nodes=None)
    per_frame = _live(frames, sizes, ALL_PER_FRAME, cfg)
    assert per_frame[2].chunks == 0
    mixed = _live(frames, sizes, min_frames, cfg)
    if max(sizes) >= min_frames:
        assert mixed[2].chunks > 0
    _same(per_frame, mixed)


def test_every_backlog_in_columns_gives_the_per_frame_result() -> None:
    """All in columns (batches of 1 to 97 frames, every one a chunk) against all one by
    one: chunk boundaries fall at every kind of frame."""
    frames = FRAMES
    sizes = [1, 97, 2, 13, 64, 5, 40]
    cfg = MonitorConfig(nodes=None)
    per_frame = _live(frames, sizes, ALL_PER_FRAME, cfg)
    columns = _live(frames, sizes, 1, cfg)
    assert columns[2].chunks > len(frames) / max(sizes)
    assert sum(1 for t in per_frame[0].transitions if t.kind == "health") >= 3
    _same(per_frame, columns)


def test_a_secoc_codec_feeds_frame_by_frame() -> None:
    """A codec whose frames need per-frame freshness state: never a chunk, and said why."""
    db = load_database(secoc_key=bytes(range(16)))
    pipe = MonitorPipeline(db, MonitorConfig(), sink=Recorder())
    feed = BacklogFeed(pipe, 1)
    assert feed.engine is None and feed.obstacle
    frames = sim_frames("healthy")[:200]
    feed.feed(frames)
    assert feed.chunks == 0
    assert pipe.counters["frames/received"] == 200
