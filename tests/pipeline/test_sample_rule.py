"""The one rule that pairs inputs with output samples (`monitor.pipeline.samples`): the
input delay, carried between chunks and forgotten at a restart, the same numbers from
both engines, and the rig's `[model] input_delay`."""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

import can
import numpy as np
import pytest

from monitor.app.identify import NodeCapture, _row, fit_series
from monitor.bus.codec import Decoded, load_database
from monitor.bus.logfile import read_log
from monitor.pipeline import MonitorConfig
from monitor.pipeline.samples import (
    MAX_INPUT_DELAY,
    delayed,
    fit_rows,
    input_window_of,
    input_window_problem,
    no_past,
)
from monitor.rig import RigError, load_rig
from sim_ecu.ecu import VirtualECU
from sim_ecu.scenario import scenario_from_dict
from tests.support.engines import compare_engines, sim_frames
from tests.support.log_readers import write_log
from tests.support.paths import ROOT, TEST_RIGS


def test_no_delay_is_the_held_input() -> None:
    held = np.arange(10.0).reshape(5, 2)
    got, past = delayed(held, 0, no_past(2))
    assert np.array_equal(got, held) and past.shape == (0, 2)


def test_delay_carried_between_chunks_equals_the_whole() -> None:
    held = np.arange(40.0).reshape(20, 2)
    restart = np.zeros(20, np.bool_)
    restart[11] = True
    whole, _ = delayed(held, 3, no_past(2), restart)
    # before three held inputs exist (the start, the restart) the first of the run
    assert np.array_equal(whole[:, 0], [0, 0, 0, 0, 2, 4, 6, 8, 10, 12, 14,
                                        22, 22, 22, 22, 24, 26, 28, 30, 32, 34, 36][:20])
    parts, past = [], no_past(2)
    for a, b in ((0, 1), (1, 2), (2, 9), (9, 12), (12, 20)):
        got, past = delayed(held[a:b], 3, past, restart[a:b])
        parts.append(got)
        assert past.shape[0] <= 3
    assert np.array_equal(np.concatenate(parts), whole)


def test_a_view_of_the_held_inputs_is_not_carried() -> None:
    u = np.array([1.0])
    _, past = delayed(u[None], 1, no_past(1))
    u[0] = 5.0
    got, _ = delayed(u[None], 1, past)
    assert got[0, 0] == 1.0


@pytest.mark.parametrize("d", [0, 1, 2, 3])
def test_fit_rows_pair_the_state_input_with_the_filters_step(d: int) -> None:
    """v(j) drives x(j+1): the filter's step k + 1 applies it, which the rule gives the
    held input of sample k + 1 - d."""
    held = np.arange(10.0)[:, None]
    y = 100.0 + np.arange(10.0)[:, None]
    v, yy, rows = fit_rows(held, y, d)
    assert len(v) == len(yy) == rows.stop - rows.start
    for j in range(len(v)):
        assert v[j, 0] == held[rows.start + j + 1 - d, 0]
        assert yy[j, 0] == y[rows.start + j, 0]


@pytest.mark.parametrize("d", [1, 3])
def test_both_engines_give_the_same_numbers_with_a_delay(tmp_path: Path, d: int) -> None:
    """Lost frames, repeats and a gap that restarts the estimator, with a delay."""
    frames = sim_frames("fault-outage-recovery", bad=True, drop=97, repeat=211)
    path = write_log(tmp_path / "run.log", frames)
    res, _, a = compare_engines(path, load_database(), load_database(),
                                MonitorConfig(nodes=(0,), input_delay=d))
    assert res.columnar and a.samples
    assert res.counters.get("estimator/restarts", 0) > 0


def test_both_engines_on_a_rig_whose_input_varies(tmp_path: Path) -> None:
    from dataclasses import replace

    from monitor.app.options import monitor_config
    from monitor.bus.rigcodec import RigCodec
    from monitor.rig import build_decoder
    from sim_ecu.rig_ecu import RigECU
    from sim_ecu.scenario import load_scenario

    r = load_rig(TEST_RIGS / "press.toml")
    codec = build_decoder(r)
    assert isinstance(codec, RigCodec)
    ecu = RigECU(None, codec, r, 1,
                 load_scenario(TEST_RIGS / "press_excite.toml"), seed=5)
    frames = [m for i, m in enumerate(ecu.frames(start_time=1000.0)) if i % 50 != 7]
    path = write_log(tmp_path / "rig.log", frames)
    cfg = monitor_config(argparse.Namespace(nodes=None, rate=None, thresholds=None), r)
    _, _, a = compare_engines(path, build_decoder(r), build_decoder(r),
                              replace(cfg, input_delay=2), chunk=1500)
    _, _, b = compare_engines(path, build_decoder(r), build_decoder(r), cfg, chunk=1500)
    assert [s.inputs for s in a.samples] != [s.inputs for s in b.samples]


def _rig_with(tmp_path: Path, line: str) -> Path:
    text = (ROOT / "rigs" / "motor.toml").read_text(encoding="utf-8")
    text = text.replace('dbc = "', 'dbc = "' + str(ROOT / "rigs") + "/", 1) \
        if 'dbc = "../' in text else text
    out = tmp_path / "rig.toml"
    out.write_text(text.replace("[model]\n", f"[model]\n{line}\n", 1), encoding="utf-8")
    return out


def test_rig_input_delay_loads(tmp_path: Path) -> None:
    from monitor.app import options

    rig = load_rig(_rig_with(tmp_path, "input_delay = 2"))
    assert rig.model is not None and rig.model.input_delay == 2
    ns = argparse.Namespace(nodes=None, rate=None, thresholds=None)
    assert options.monitor_config(ns, rig).input_delay == 2
    windowed = load_rig(_rig_with(tmp_path, "input_window = 0.5"))
    assert windowed.model is not None and windowed.model.input_window == 0.5
    assert options.monitor_config(ns, windowed).input_window == 0.5


@pytest.mark.parametrize("value", ["-1", "1.5", "true", str(MAX_INPUT_DELAY + 1), '"2"'])
def test_a_wrong_input_delay_is_one_line(tmp_path: Path, value: str) -> None:
    with pytest.raises(RigError) as info:
        load_rig(_rig_with(tmp_path, f"input_delay = {value}"))
    msg = str(info.value)
    assert "\n" not in msg and "model.input_delay" in msg, msg


def _reordered(frames: list[can.Message], how: str, seed: int = 4) -> list[can.Message]:
    """Our bus's frames with each voltage command (0x120, sent at the instant of a current
    sample 0x110, after it) moved to before that sample's frame: at the same time stamp
    ("same"), 2 % of a period earlier ("early"), or either of those or left after it, at
    random ("mixed")."""
    rng = np.random.default_rng(seed)
    out = []
    for m in frames:
        if m.arbitration_id != 0x120:
            out.append(m)
            continue
        choice = how if how != "mixed" else str(rng.choice(["same", "early", "after"]))
        if choice == "after":
            out.append(m)
            continue
        t = m.timestamp - (0.0002 if choice == "early" else 0.0)
        moved = can.Message(timestamp=t, arbitration_id=m.arbitration_id, data=m.data,
                            is_extended_id=m.is_extended_id)
        k = max(i for i, f in enumerate(out) if f.arbitration_id == 0x110)  # its sample's
        out.insert(k, moved)
    return out


def _prbs_frames() -> list[can.Message]:
    """Our bus's frames of a node whose command changes every 0.1 s, a 0.4 loss at 10 s."""
    sc = scenario_from_dict({"name": "prbs-loss", "duration": 20.0,
                             "fault": [{"kind": "step", "start": 10.0, "gamma": 0.4}],
                             "voltage": {"prbs": {"level": 200.0, "amplitude": 20.0,
                                                  "clock": 0.1, "seed": 1}}})
    base = list(VirtualECU(None, load_database(), 0, sc, seed=3).frames(start_time=1000.0))
    assert len({bytes(m.data[2:4]) for m in base if m.arbitration_id == 0x120}) > 1  # it varies
    return base


def _identify_rows(path: Path) -> tuple[np.ndarray, float]:
    """identify's rows of node 0 and the input window it chose."""
    nc: dict[int, NodeCapture] = {}
    counts: dict[str, int] = defaultdict(int)
    db = load_database()
    for m in read_log(path):
        d = db.decode_can(m)
        if isinstance(d, Decoded) and d.node == 0:
            _row(nc.setdefault(0, NodeCapture()), d, 1, counts)
    series = fit_series(nc[0], 0, [path], counts)
    return series.u, series.input_window


@pytest.mark.parametrize("how", ["same", "early", "mixed"])
def test_an_input_window_pairs_a_command_sent_with_the_output_alike(tmp_path: Path,
                                                                    how: str) -> None:
    """With an input window of half a period, a command frame sent with an output frame is
    held from the next sample on whichever the bus put first: every sample holds the same
    inputs in both engines as when the command came after the output (without the window,
    a command moved before its sample is held one sample early)."""
    base = _prbs_frames()
    cfg = MonitorConfig(nodes=(0,), input_window=0.5)
    _, _, ref = compare_engines(write_log(tmp_path / "ref.log", base), load_database(),
                                load_database(), cfg)
    log = write_log(tmp_path / f"{how}.log", _reordered(base, how))
    _, _, got = compare_engines(log, load_database(), load_database(), cfg)
    assert len(got.samples) == len(ref.samples) > 1900
    assert [s.inputs for s in got.samples] == [s.inputs for s in ref.samples]
    assert [s.gamma for s in got.samples] == [s.gamma for s in ref.samples]
    _, _, plain = compare_engines(log, load_database(), load_database(),
                                  MonitorConfig(nodes=(0,)))
    assert [s.inputs for s in plain.samples] != [s.inputs for s in ref.samples]


def test_identify_finds_the_window_where_the_frames_straddle_the_output(tmp_path: Path) -> None:
    """Commands sent with their sample in either order, at random: identify places the
    window's edge mid-period and forms the rows the monitor forms; sent after it, or
    consistently before it, there is nothing to straddle and no window."""
    base = _prbs_frames()
    ref_rows, ref_window = _identify_rows(write_log(tmp_path / "ref.log", base))
    assert ref_window == 0.0
    rows, window = _identify_rows(write_log(tmp_path / "mixed.log", _reordered(base, "mixed")))
    assert 0.4 < window < 0.6
    assert np.array_equal(rows, ref_rows)
    _, early = _identify_rows(write_log(tmp_path / "early.log", _reordered(base, "early")))
    assert early == 0.0


@pytest.mark.parametrize(("phases", "want"), [
    ((0.01, 0.03, 0.97, 0.99), (0.45, 0.55)),  # around the output frame, either side
    ((0.02, 0.04, 0.06), (0.0, 0.0)),  # just after it: today's rule pairs them alike
    ((0.91, 0.93, 0.95), (0.0, 0.0)),  # just before it (rig zoo seed 205): the same
    ((0.3, 0.5, 0.98, 0.99, 0.02), (0.25, 0.45)),  # the widest empty stretch: 0.02-0.3
])
def test_input_window_of(phases: tuple[float, ...], want: tuple[float, float]) -> None:
    T = 0.01
    t_out = 100.0 + T * np.arange(400, dtype=np.float64)
    rng = np.random.default_rng(0)
    k = np.arange(1, 399)
    t_in = t_out[k] + T * np.asarray(phases)[k % len(phases)] \
        + rng.uniform(-1e-5, 1e-5, k.size)
    w = input_window_of(t_out, np.sort(t_in), T)
    assert want[0] <= w <= want[1], w
    assert input_window_problem(w) is None
