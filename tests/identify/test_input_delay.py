"""The input delay identify learns (issue 16): the rows formed by the monitor's rule
(`monitor.pipeline.samples`), the delay estimated as MATLAB's ``delayest`` does
(`monitor.identify.delay`), and the model fitted for the monitor's pairing."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import scipy.signal

from monitor.app.identify import NodeCapture, _row, collect, rig_document
from monitor.bus.codec import Decoded, load_database
from monitor.identify import identify, prbs
from monitor.identify.delay import estimate_input_delay
from monitor.rig import builtin_rig, load_rig
from sim_ecu.ecu import VirtualECU
from sim_ecu.scenario import Scenario

T = 0.01


def _plant(order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A first-order lag (time constant 3 samples) or a second-order resonance (40 rad/s,
    damping 0.5), zero-order hold at T."""
    if order == 1:
        A, B, C = np.array([[-30.0]]), np.array([[30.0]]), np.array([[1.0]])
    else:
        A, B = np.array([[0.0, 1.0], [-1600.0, -40.0]]), np.array([[0.0], [1600.0]])
        C = np.array([[1.0, 0.0]])
    Ad, Bd, Cd, _, _ = scipy.signal.cont2discrete((A, B, C, np.zeros((1, 1))), T, "zoh")
    return Ad, Bd, Cd


def _rows(order: int, dead: int, input_first: bool, *, n: int = 3000, seed: int = 0,
          sigma: float = 0.02) -> NodeCapture:
    """The rows `identify` collects from a bus where an ECU, every period, measures y(k),
    applies its command u(k) from t(k) to a plant with `dead` samples of dead time, and
    sends the output frame and the input frame in the order asked."""
    rng = np.random.default_rng(seed)
    Ad, Bd, Cd = _plant(order)
    u = np.repeat(rng.uniform(-1.0, 1.0, n), rng.integers(3, 40, n))[:n]
    x = np.zeros(Ad.shape[0])
    nc = NodeCapture()
    counts: dict[str, int] = defaultdict(int)
    for k in range(n):
        y = float((Cd @ x)[0]) + sigma * float(rng.standard_normal())
        x = Ad @ x + Bd[:, 0] * u[max(k - dead, 0)]
        out = Decoded("out", 1, k * T, y, None, {}, outputs=(y,))
        cmd = Decoded("in", 1, k * T + 1e-4, float(u[k]), None, {}, inputs=((0, float(u[k])),))
        for d in ((cmd, out) if input_first else (out, cmd)):
            _row(nc, d, 1, counts)
    return nc


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("input_first", [False, True])
@pytest.mark.parametrize("dead", [0, 1, 2, 3])
def test_the_delay_of_a_dead_time_and_of_the_frame_order(order: int, dead: int,
                                                         input_first: bool) -> None:
    nc = _rows(order, dead, input_first, seed=dead + 4 * order)
    u, y = nc.inputs(T, 0.0)[0], np.asarray(nc.y)
    # a command sent before the output it cannot yet affect is held one sample early
    want = dead + int(input_first)
    est = estimate_input_delay(u[:2100], y[:2100])
    assert est.delay == want, est
    assert set(est.loss) == set(range(11))


def _slow(seed: int, dead: int, *, n: int = 12000, T: float = 0.004, tau: float = 0.4,
          sigma: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """A slow plant sampled fast (poles at 1/tau and 4/tau, tau = 100 samples: the
    response starts as t^2, its first samples far below the noise sigma) behind `dead`
    samples of dead time, driven by steps switching every 100-300 samples."""
    rng = np.random.default_rng(seed)
    den = np.polymul([tau, 1.0], [tau / 4, 1.0])
    b, a, _ = scipy.signal.cont2discrete(([1.0], den), T, "zoh")
    u = np.repeat(rng.choice([-1.0, 1.0], n), rng.integers(100, 300, n))[:n]
    y = scipy.signal.lfilter(np.ravel(b), a, np.concatenate([np.zeros(dead), u[:n - dead]]))
    return u[:, None], (y + sigma * rng.standard_normal(n))[:, None]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_start_the_data_do_not_show_is_not_placed(seed: int) -> None:
    """No candidate's dropped taps matter (the first samples of a slow response are
    buried): the delay is 0, which the model's dynamics absorb, not the largest candidate,
    which would leave the model blind to the response's start."""
    u, y = _slow(seed, 2)
    est = estimate_input_delay(u, y)
    assert min(est.p_value.values()) > 1e-3, est  # the taps do not show the start
    assert not est.placed and est.delay == 0, est


def test_identify_fits_for_the_monitors_pairing() -> None:
    """A dead time of two samples: identify reports it, the model written for it gives
    the monitor's own filter unit NIS on the capture, and the rig file carries it."""
    nc = _rows(2, 2, False, n=6000, seed=11, sigma=0.01)
    ident = identify(nc.inputs(T, 0.0)[0], np.asarray(nc.y), T, kind="state_space")
    rep = ident.report
    assert ident.input_delay == 2 and rep["input_delay"]["samples"] == 2
    assert not rep["input_delay"]["given"] and len(rep["input_delay"]["arx_loss"]) == 11
    assert 0.7 < rep["fuzzy_ukf"]["mean_nis_holdout"] < 1.5, rep["fuzzy_ukf"]
    given = identify(nc.inputs(T, 0.0)[0], np.asarray(nc.y), T, kind="state_space",
                     input_delay=2, run_filter=False)
    assert given.report["input_delay"] == {"samples": 2, "given": True}
    assert given.report["fit"] == rep["fit"]


def test_our_own_bus_has_no_input_delay(tmp_path: Path) -> None:
    """The built-in rig: the ECU sends the current measured at t(k) before the command it
    applies from t(k), so the held command is the one the current answers: d = 0, and the
    learned rig says so."""
    import argparse

    import can

    u = prbs(40.0, T, level=220.0, amplitude=40.0, clock=0.3, seed=5)[:, 0]
    change = np.flatnonzero(np.diff(u, prepend=np.nan) != 0)
    sc = Scenario(name="excite", duration=40.0,
                  voltage_steps=tuple((float(k * T), float(u[k])) for k in change))
    rig = builtin_rig()
    path = tmp_path / "ours.log"
    ecu = VirtualECU(None, load_database(), 1, sc, seed=6)
    with can.Logger(str(path)) as log:
        for msg in ecu.frames(start_time=1.7e9):
            log(msg)
    args = argparse.Namespace(rig=None, dbc=None, key=None)
    nodes, _ = collect(args, rig, [path])
    nc = nodes[1]
    ident = identify(nc.inputs(T, 0.0)[0], np.asarray(nc.y), T, kind="dc_motor",
                     run_filter=True)
    assert ident.input_delay == 0, ident.report["input_delay"]
    assert 0.7 < ident.report["fuzzy_ukf"]["mean_nis_holdout"] < 1.4
    out = tmp_path / "learned.toml"
    doc = rig_document(rig, ident, out)
    assert doc["model"]["input_delay"] == 0
    import tomli_w

    out.write_text(tomli_w.dumps(doc), encoding="utf-8")
    learned = load_rig(out).model
    assert learned is not None and learned.input_delay == 0
