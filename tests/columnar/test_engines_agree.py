"""Both engines, one set of rules: random frame streams -- frames lost, repeated, late,
corrupted, silences, CAN FD and error frames, frames of no node, two nodes of our bus, and
three test rigs (E2E with the command in another frame; no protection at all; SecOC watched
without its key) -- through the
per-frame engine (the live daemon's, `feed_log`) and the columnar engine (replay, in chunks
of a random size), which must give the same events, samples and counters
(`tests.support.engines.compare_engines`). Hypothesis shrinks a disagreement to a short
program."""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Any

import can
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from monitor.app.options import monitor_config
from monitor.bus.codec import load_database
from monitor.bus.rigcodec import RigCodec
from monitor.pipeline import MonitorConfig
from monitor.rig import Rig, build_decoder, load_rig
from sim_ecu.rig_ecu import RigECU
from sim_ecu.scenario import load_scenario
from tests.support.engines import bad_frames, compare_engines, sim_frames
from tests.support.log_readers import write_log
from tests.support.paths import TEST_RIGS
from tests.support.rig_files import written_rig

NO_OVERRIDES = argparse.Namespace(nodes=None, rate=None, thresholds=None)

BASE = sim_frames("fault-outage-recovery", nodes=(0, 1))
"""Two nodes' 30 s of a fault, outage and recovery: the stream every program edits."""


def _rig_stream(rig: str, scenario: str, key: bytes | None = None
                ) -> tuple[Rig, list[can.Message]]:
    """A test rig and its twin's frames of node 1 (as `test_columnar_equals_per_frame_on_rigs`),
    signed with `key` where given (the monitor then watches without it)."""
    r = load_rig(TEST_RIGS / rig)
    codec = build_decoder(r, secoc_key=key)
    assert isinstance(codec, RigCodec)
    ecu = RigECU(None, codec, r, 1, load_scenario(TEST_RIGS / scenario), seed=5)
    return r, list(ecu.frames(start_time=1000.0))


RIGS = {"press": _rig_stream("press.toml", "press_excite.toml"),
        "twin": _rig_stream("twin.toml", "twin_fault.toml"),
        "secure": _rig_stream("secure_drive.toml", "press_excite.toml", bytes(range(16)))}
"""Rigs that are not our bus: `press` (E2E with a fixed data ID, the command in another
frame at another rate), `twin` (no protection: the time stamps alone tell lost and late
samples), `secure` (SecOC frames and sync frames, watched without the key: unverified)."""

_where = st.floats(0.0, 1.0, exclude_max=True)  # a place in the stream, as a fraction
_op = st.one_of(
    st.tuples(st.just("drop"), _where, st.integers(1, 40)),
    st.tuples(st.just("repeat"), _where, st.integers(1, 3)),
    st.tuples(st.just("late"), _where, st.floats(0.001, 0.3)),
    st.tuples(st.just("corrupt"), _where, st.integers(0, 7), st.integers(0, 255)),
    st.tuples(st.just("silence"), _where, st.floats(0.05, 2.0)),
    st.tuples(st.just("fd"), _where, st.integers(9, 64)),
    st.tuples(st.just("error"), _where, st.integers(0, 0x1FFFFFFF)),
    st.tuples(st.just("unknown"), _where, st.integers(0, 0x7FF)),
    st.tuples(st.just("bad"), _where),
)


def _apply(base: list[can.Message], ops: list[tuple[Any, ...]]) -> list[can.Message]:
    """The `base` stream edited by `ops`, in time order."""
    frames = list(base)
    t0, t1 = base[0].timestamp, base[-1].timestamp
    ops = [(kind, (t0 + where * (t1 - t0)) if kind == "silence" else int(where * len(base)),
            *rest) for kind, where, *rest in ops]
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
            extra += bad_frames(t + 0.0004, 0.0009)[:12]
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
        path = write_log(Path(d) / "run.log", _apply(BASE, ops))
        cfg = MonitorConfig(nodes=None if both else (0,))
        res, _, _ = compare_engines(path, load_database(), load_database(), cfg, chunk=chunk)
        assert res.columnar


@settings(max_examples=12, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(rig=st.sampled_from(sorted(RIGS)), ops=st.lists(_op, min_size=1, max_size=10),
       chunk=st.integers(64, 5000))
def test_the_engines_agree_on_random_streams_of_other_rigs(rig: str, ops: list[tuple[Any, ...]],
                                                           chunk: int) -> None:
    r, base = RIGS[rig]
    with tempfile.TemporaryDirectory() as d:
        path = write_log(Path(d) / "run.log", _apply(base, ops))
        res, _, _ = compare_engines(path, build_decoder(r), build_decoder(r),
                                    monitor_config(NO_OVERRIDES, r), chunk=chunk)
        assert res.columnar


def test_a_secoc_rig_watched_without_its_key_replays_in_columns() -> None:
    """Without the key nothing depends on a stream's freshness: the columns decode the
    secured frames unverified and count the sync frames as the per-frame path does."""
    r, base = RIGS["secure"]
    with tempfile.TemporaryDirectory() as d:
        path = write_log(Path(d) / "run.log", base)
        res, _, seen = compare_engines(path, build_decoder(r), build_decoder(r),
                                       monitor_config(NO_OVERRIDES, r))
    assert res.columnar and not res.fallback
    assert len(seen.samples) >= 5990  # the first outputs come before any input
    assert not any(k.startswith("rejected/") and v for k, v in res.counters.items())


def test_the_engines_agree_on_a_model_with_friction(tmp_path: Path) -> None:
    """Coulomb friction (`[model.friction]`, here on the second output's rate of change) is
    applied in the step kernel both engines run: the twin's stream, made without friction,
    so that the friction term moves the estimate (and the structure test fires), gives the
    same events, samples and counters in either."""
    text = (TEST_RIGS / "twin.toml").read_text() + (
        '\n[model.friction]\nB = [0.3, -0.2]\nspeed = "rate"\noutput = 1\nwidth = 0.05\n')
    r = load_rig(written_rig(tmp_path, text, TEST_RIGS / "twin.dbc"))
    assert r.model is not None and r.model.friction is not None
    path = write_log(tmp_path / "run.log", RIGS["twin"][1])
    res, _, got = compare_engines(path, build_decoder(r), build_decoder(r),
                                  monitor_config(NO_OVERRIDES, r), chunk=701)
    assert res.columnar
    plain = load_rig(TEST_RIGS / "twin.toml")
    _, _, without = compare_engines(path, build_decoder(plain), build_decoder(plain),
                                    monitor_config(NO_OVERRIDES, plain), chunk=701)
    # the friction is no dead letter: the estimates differ from the model's without it
    assert any(abs(a.estimated - b.estimated) > 1e-6
               for a, b in zip(got.samples, without.samples, strict=True))
