"""Both engines, one set of rules: random frame streams -- frames lost, repeated, late,
corrupted, silences, CAN FD and error frames, frames of no node, two nodes -- through the
per-frame engine (the live daemon's, `feed_log`) and the columnar engine (replay, in chunks
of a random size), which must give the same events, samples and counters
(`tests.columnar.test_columnar._compare`). Hypothesis shrinks a disagreement to a short program."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import can
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from monitor.bus.codec import load_database
from monitor.pipeline import MonitorConfig
from tests.columnar.test_columnar import _bad_frames, _compare, _sim_frames, _write

BASE = _sim_frames("fault-outage-recovery", nodes=(0, 1))
"""Two nodes' 30 s of a fault, outage and recovery: the stream every program edits."""
T0, T1 = BASE[0].timestamp, BASE[-1].timestamp

_index = st.integers(0, len(BASE) - 1)
_op = st.one_of(
    st.tuples(st.just("drop"), _index, st.integers(1, 40)),
    st.tuples(st.just("repeat"), _index, st.integers(1, 3)),
    st.tuples(st.just("late"), _index, st.floats(0.001, 0.3)),
    st.tuples(st.just("corrupt"), _index, st.integers(0, 7), st.integers(0, 255)),
    st.tuples(st.just("silence"), st.floats(T0, T1), st.floats(0.05, 2.0)),
    st.tuples(st.just("fd"), _index, st.integers(9, 64)),
    st.tuples(st.just("error"), _index, st.integers(0, 0x1FFFFFFF)),
    st.tuples(st.just("unknown"), _index, st.integers(0, 0x7FF)),
    st.tuples(st.just("bad"), _index),
)


def _apply(ops: list[tuple[Any, ...]]) -> list[can.Message]:
    """The base stream edited by `ops`, in time order."""
    frames = list(BASE)
    drop: set[int] = set()
    extra: list[can.Message] = []
    moved: dict[int, float] = {}
    for op in ops:
        kind, *a = op
        if kind == "drop":
            i, n = int(a[0]), int(a[1])
            drop.update(range(i, min(i + n, len(frames))))
        elif kind == "repeat":
            m = frames[int(a[0])]
            extra += [m] * int(a[1])
        elif kind == "late":
            moved[int(a[0])] = float(a[1])
        elif kind == "corrupt":
            i = int(a[0])
            m = frames[i]
            data = bytearray(m.data)
            data[int(a[1]) % max(len(data), 1)] = int(a[2])
            frames[i] = can.Message(timestamp=m.timestamp, arbitration_id=m.arbitration_id,
                                    is_extended_id=m.is_extended_id, data=bytes(data))
        elif kind == "silence":
            t, d = float(a[0]), float(a[1])
            drop.update(k for k, m in enumerate(frames) if t <= m.timestamp < t + d)
        elif kind == "fd":
            m = frames[int(a[0])]
            extra.append(can.Message(timestamp=m.timestamp + 0.0001, is_fd=True,
                                     arbitration_id=m.arbitration_id, is_extended_id=False,
                                     data=bytes(int(a[1]))))
        elif kind == "error":
            m = frames[int(a[0])]
            extra.append(can.Message(timestamp=m.timestamp + 0.0002, is_error_frame=True,
                                     arbitration_id=int(a[1]) & 0x1FFFFFFF,
                                     is_extended_id=True, data=bytes(8)))
        elif kind == "unknown":
            m = frames[int(a[0])]
            extra.append(can.Message(timestamp=m.timestamp + 0.0003, is_extended_id=False,
                                     arbitration_id=int(a[1]), data=bytes(8)))
        elif kind == "bad":
            t = frames[int(a[0])].timestamp
            extra += _bad_frames(t + 0.0004, 0.0009)[:12]
    out = []
    for k, m in enumerate(frames):
        if k in drop:
            continue
        if k in moved:
            m = can.Message(timestamp=m.timestamp + moved[k], arbitration_id=m.arbitration_id,
                            is_extended_id=m.is_extended_id, data=bytes(m.data))
        out.append(m)
    out += extra
    out.sort(key=lambda m: m.timestamp)  # a log holds its frames in time order
    return out


@settings(max_examples=12, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(ops=st.lists(_op, min_size=1, max_size=12), chunk=st.integers(64, 5000),
       both=st.booleans())
def test_the_engines_agree_on_random_streams(ops: list[tuple[Any, ...]], chunk: int,
                                              both: bool) -> None:
    with tempfile.TemporaryDirectory() as d:
        path = _write(_apply(ops), Path(d) / "run.log")
        cfg = MonitorConfig(nodes=None if both else (0,))
        res, _, _ = _compare(path, load_database(), load_database(), cfg, chunk=chunk)
        assert res.columnar
