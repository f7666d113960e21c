"""The one rule that pairs inputs with output samples (`monitor.pipeline.samples`): the
input delay, carried between chunks and forgotten at a restart, the same numbers from
both engines, and the rig's `[model] input_delay`."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest

from monitor.bus.codec import load_database
from monitor.pipeline import MonitorConfig
from monitor.pipeline.samples import MAX_INPUT_DELAY, delayed, fit_rows, no_past
from monitor.rig import RigError, load_rig
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


@pytest.mark.parametrize("value", ["-1", "1.5", "true", str(MAX_INPUT_DELAY + 1), '"2"'])
def test_a_wrong_input_delay_is_one_line(tmp_path: Path, value: str) -> None:
    with pytest.raises(RigError) as info:
        load_rig(_rig_with(tmp_path, f"input_delay = {value}"))
    msg = str(info.value)
    assert "\n" not in msg and "model.input_delay" in msg, msg
