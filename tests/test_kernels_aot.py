"""The ahead-of-time kernel (for W^X services) computes exactly what the JIT kernel does."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

from monitor.estimation.fuzzy_ukf import FuzzyUKF
from monitor.estimation.kernels_aot import MODULE, build
from monitor.estimation.model import dc_motor
from sim_ecu.plant import simulate
from sim_ecu.scenario import load_scenario


def test_aot_kernel_matches_jit_kernel(tmp_path: Path) -> None:
    so = build(tmp_path)
    spec = importlib.util.spec_from_file_location(MODULE, so)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    model = dc_motor()
    run = simulate(model, load_scenario("fault-outage-recovery"), 0.01, seed=7)
    jit = FuzzyUKF(model.discretize(0.01))
    aot = FuzzyUKF(model.discretize(0.01))
    aot._kernel = mod.fuzzy_ukf_step
    for k in range(len(run.t)):
        a = jit.step(run.u[k], run.y[k], 0.01)
        b = aot.step(run.u[k], run.y[k], 0.01)
        assert np.allclose(a.gamma, b.gamma, rtol=0, atol=1e-12)
        assert np.allclose(a.x_hat, b.x_hat, rtol=1e-12, atol=1e-12)
        assert a.rules == b.rules and a.structure_event == b.structure_event
    assert jit.structure_events == aot.structure_events >= 3
