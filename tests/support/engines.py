"""Both engines on the same log: frames of the virtual ECU (good, lost, repeated, late and
bad), written by python-can, through the per-frame pipeline and the columnar replay, which
must agree (`compare_engines`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import can

from monitor.bus.codec import load_database
from monitor.bus.logfile import read_log
from monitor.columnar.replay import ReplayResult, replay_file
from monitor.pipeline import MonitorConfig, MonitorPipeline
from monitor.pipeline.feed import feed_log
from sim_ecu.ecu import VirtualECU
from sim_ecu.scenario import load_scenario
from tests.support.bad_frames import frame_kinds
from tests.support.pipeline import Recorder, stalled, without_currents

__all__ = ["bad_frames", "compare_engines", "sim_frames"]


def bad_frames(start: float, period: float) -> list[can.Message]:
    """Every kind of bad frame of the robustness tests, one after another."""
    db = load_database()
    out: list[can.Message] = []
    t = start
    for kind in frame_kinds(db, n=6):
        for f in kind.frames:
            out.append(f.message(t))
            t += period
    return out


def sim_frames(scenario: str, *, bad: bool = False, drop: int = 0, repeat: int = 0,
               late: bool = False, nodes: tuple[int, ...] = (0,)) -> list[can.Message]:
    """A virtual ECU's frames of `scenario` on our bus (node n seeded 3 + n, from t = 1000 s),
    with every `drop`-th frame lost, every `repeat`-th sent twice, a held-up sender's
    backlogs and counter wraps (`late`), and bad frames and a silence (`bad`)."""
    db = load_database()
    frames: list[can.Message] = []
    for node in nodes:
        ecu = VirtualECU(None, db, node, load_scenario(scenario), seed=3 + node)
        frames += list(ecu.frames(start_time=1000.0 + 0.0013 * node))
    frames.sort(key=lambda m: m.timestamp)
    if drop:
        frames = [m for i, m in enumerate(frames) if i % drop != 5]
    if repeat:
        frames = [x for i, m in enumerate(frames) for x in ((m, m) if i % repeat == 3 else (m,))]
    if late:
        # a held-up sender's backlogs (late, not lost), counter wraps of lost frames (not
        # repeats), and a frame replayed after a silence (a repeat)
        for t0, periods in ((1003.0005, 14), (1004.5005, 9), (1021.0005, 40)):
            frames = stalled(frames, t0, t0 + periods / 100.0)
        frames = without_currents(without_currents(frames, 600, 15), 900, 31)
        last = max((m for m in frames if m.arbitration_id == 0x110), key=lambda m: m.timestamp)
        frames.append(can.Message(arbitration_id=0x110, data=last.data, is_extended_id=False,
                                  timestamp=last.timestamp + 0.7))
        frames.sort(key=lambda m: m.timestamp)
    if bad:
        # a gap that restarts the estimator, with frames of other kinds in it: a silence
        frames = [m for m in frames if not 1010.0 <= m.timestamp < 1015.6]
        frames += bad_frames(1002.0005, 0.0031)
        frames += bad_frames(1010.2007, 0.0109)  # in the gap below: ticks see a silence
        frames.sort(key=lambda m: m.timestamp)
    return frames


def compare_engines(path: Path, db: Any, db2: Any, cfg: MonitorConfig, chunk: int = 997
                    ) -> tuple[ReplayResult, MonitorPipeline, Recorder]:
    """The log at `path` through the per-frame engine (`feed_log`, with decoder `db`) and the
    columnar one (`replay_file` in chunks of `chunk` frames, with `db2`): asserts the same
    frames, counters, transitions, diagnoses, bus events, inputs, samples and node summaries;
    returns the replay's result, the pipeline and what it gave."""
    a = Recorder()
    pipe = MonitorPipeline(db, cfg, sink=a)
    n = feed_log(pipe, read_log(path))
    b = Recorder()
    res = replay_file(path, db2, cfg, b, chunk_frames=chunk)
    assert res.frames == n
    assert res.counters == dict(pipe.counters)
    assert b.transitions == a.transitions
    assert res.events == a.transitions
    assert b.diagnoses == a.diagnoses
    assert b.bus == a.bus
    # samples and voltages go to the sinks as columns, node by node: each node's in order
    assert sorted(b.inputs, key=lambda v: v.node) == sorted(a.inputs, key=lambda v: v.node)
    assert len(b.samples) == len(a.samples)
    assert sorted(b.samples, key=lambda v: v.node) == sorted(a.samples, key=lambda v: v.node)
    assert res.nodes == pipe.summary()["nodes"]
    return res, pipe, a
