"""Where `identify` raises an output's R to its quantisation floor, it refits the process
noise with that R (`monitor.identify.noise`): the model written is the innovation
likelihood's best for the R it holds, not the Q learned beside a lower R (issue 16)."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from monitor.identify import identify
from monitor.identify.noise import process_noise_scale
from monitor.pipeline.samples import fit_rows

Array = NDArray[np.float64]

T = 1e-3
STEP = 0.1  # the output's step: its rounding is what the fit leaves below step^2 / 12


def _quantised_capture() -> tuple[Array, Array]:
    """A first-order plant (tau 20 ms, gain 2) under a +-5 PRBS around 10, its process noise
    small against the output's step, read in whole steps of STEP."""
    rng = np.random.default_rng(1)
    N, clock = 30000, 40
    a = np.exp(-T / 0.02)
    u = 10.0 + 5.0 * np.repeat(rng.choice([-1.0, 1.0], N // clock + 1), clock)[:N]
    y = np.empty(N)
    x = 0.0
    for k in range(N):
        y[k] = x
        x = a * x + (1.0 - a) * 2.0 * u[k] + rng.normal(0.0, 0.002)
    return u[:, None], (np.round((y + rng.normal(0.0, 1e-4, N)) / STEP) * STEP)[:, None]


def test_the_process_noise_is_refitted_where_r_is_raised_to_its_floor() -> None:
    u, y = _quantised_capture()
    ident = identify(u, y, T, kind="state_space", order=1,
                     output_steps=[(STEP, "test: integer-coded")])
    noise = ident.report["noise"]
    (row,) = noise["quantisation_floor"]
    assert row["applied"]  # the fit alone went below the floor: the case at hand
    # the model written: the likelihood's best Q for the floored R on the training rows the
    # fit used (refitting it again moves nothing)
    uf, yf, _ = fit_rows(u, y, ident.input_delay)
    ntr = uf.shape[0] - round(0.3 * uf.shape[0])
    assert process_noise_scale(ident.model, uf[:ntr], yf[:ntr], T) == pytest.approx(1.0, abs=0.02)
    # the rounding the fit gave the process noise left it with the raised R
    assert noise["q"] < 0.99 * noise["q_learned"]
    assert ident.q == pytest.approx(noise["q"])
    assert np.asarray(noise["Qc"]) == pytest.approx(
        np.asarray(ident.model.Qc), rel=1e-12)


def test_without_a_floor_the_learned_noise_is_kept() -> None:
    u, y = _quantised_capture()
    floored = identify(u, y, T, kind="state_space", order=1, input_delay=0, run_filter=False)
    assert {"q_learned", "quantisation_floor"}.isdisjoint(floored.report["noise"])
    # a step far below the noise: the floor does not apply, the fit's noise is written as is
    fine = identify(u, y, T, kind="state_space", order=1, input_delay=0, run_filter=False,
                    output_steps=[(1e-6, "test: fine")])
    (row,) = fine.report["noise"]["quantisation_floor"]
    assert not row["applied"]
    assert fine.report["noise"]["q_learned"] == fine.q
    assert fine.q == floored.q
    assert np.array_equal(fine.model.Qc, floored.model.Qc)
