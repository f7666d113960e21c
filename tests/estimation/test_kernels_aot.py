"""The kernels made at install: the ahead-of-time kernel (for W^X services) computes exactly
what the JIT kernel does, and the warmed JIT cache leaves the daemon nothing to compile."""

from __future__ import annotations

import importlib.util
import os
import signal
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from monitor.estimation.fuzzy_ukf import KERNEL_LAYOUT, FuzzyUKF, select_kernel
from monitor.estimation.kernels_aot import MODULE, build
from monitor.estimation.model import ContinuousDescriptor, dc_motor
from monitor.jit import JIT_DISABLED
from sim_ecu.plant import SimulatedRun, simulate
from sim_ecu.scenario import load_scenario, scenario_from_dict
from tests.support.daemon import notified_daemon


@pytest.fixture(scope="module")
def aot_module(tmp_path_factory: pytest.TempPathFactory) -> ModuleType:
    so = build(tmp_path_factory.mktemp("aot"))
    spec = importlib.util.spec_from_file_location(MODULE, so)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _run_both(run: SimulatedRun, jit: FuzzyUKF, aot: FuzzyUKF) -> None:
    """Step both estimators through the run; they must agree at every sample."""
    for k in range(len(run.t)):
        a = jit.step(run.u[k], run.y[k], 0.01)
        b = aot.step(run.u[k], run.y[k], 0.01)
        assert np.allclose(a.gamma, b.gamma, rtol=0, atol=1e-12)
        assert np.allclose(a.x_hat, b.x_hat, rtol=1e-12, atol=1e-12)
        assert a.rules == b.rules and a.structure_event == b.structure_event
        for a_known in set(range(len(a.gamma))) - set(jit.model.fault_inputs):
            assert a.gamma[a_known] == b.gamma[a_known] == 0.0


def test_aot_kernel_matches_jit_kernel(aot_module: ModuleType) -> None:
    model = dc_motor()
    run = simulate(model, load_scenario("fault-outage-recovery"), 0.01, seed=7)
    jit = FuzzyUKF(model.discretize(0.01))
    aot = FuzzyUKF(model.discretize(0.01))
    aot._kernel = aot_module.fuzzy_ukf_step
    _run_both(run, jit, aot)
    assert jit.structure_events == aot.structure_events >= 3


def test_aot_kernel_matches_jit_kernel_with_a_known_actuator(aot_module: ModuleType) -> None:
    # Three actuators, two outputs; actuator 1 is a known input (per-actuator bounds [0, 0]).
    model = ContinuousDescriptor(
        E=np.eye(2), A=np.array([[-2.0, 0.5], [0.3, -3.0]]),
        B=np.array([[1.0, 0.4, 0.2], [0.1, 0.3, 1.0]]), C=np.eye(2),
        D=np.array([[0.05, 0.0, 0.0], [0.0, 0.0, 0.02]]), Qc=np.eye(2) * 0.01,
        R=np.eye(2) * 0.01, state_names=("a", "b"), fault_inputs=(0, 2),
    )
    sc = scenario_from_dict({
        "name": "three", "duration": 5.0, "actuators": 3, "noise": {"current_sigma": 0.1},
        "voltage": {"steps": [[0.0, 10.0]]},
        "fault": [{"start": 2.0, "gamma": 0.5, "actuator": 2}],
    })
    run = simulate(model, sc, 0.01, seed=2)
    jit = FuzzyUKF(model.discretize(0.01))
    aot = FuzzyUKF(model.discretize(0.01))
    aot._kernel = aot_module.fuzzy_ukf_step
    _run_both(run, jit, aot)
    assert jit.out.gamma[2] == pytest.approx(0.5, abs=0.1)
    assert jit.structure_events == aot.structure_events >= 1


def test_aot_module_reports_the_kernel_layout(aot_module: ModuleType) -> None:
    # A stale build of an older buffer layout has the same signature; select_kernel tells
    # it apart by this export and refuses it.
    assert aot_module.kernel_layout() == KERNEL_LAYOUT


def test_stale_aot_kernel_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    stale = ModuleType("monitor.estimation._fuzzy_ukf_aot")
    stale.fuzzy_ukf_step = lambda *args: None  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "monitor.estimation._fuzzy_ukf_aot", stale)
    with pytest.raises(ImportError, match="rebuild"):
        select_kernel("aot")
    monkeypatch.setenv("NUMBA_DISABLE_JIT", "1")
    assert select_kernel("auto")[0] == "python"


@pytest.mark.skipif(JIT_DISABLED, reason="the JIT is off: it compiles and caches nothing")
def test_the_warmed_cache_leaves_the_daemon_nothing_to_compile(tmp_path: Path) -> None:
    # What scripts/setup-venv.sh does, into a cache of this test's own; then the daemon's
    # start up to READY=1 (its kernels loaded, the bus open) must only load from it: numba
    # says "data saved" for every kernel it compiles and caches.
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"), NUMBA_DISABLE_JIT="0")
    env.pop("MOTOR_MONITOR_KERNEL", None)
    warm = subprocess.run([sys.executable, "-m", "monitor.runtime.warm", "--quiet"], env=env,
                          capture_output=True, text=True, timeout=900, check=False)
    assert warm.returncode == 0 and not warm.stdout and not warm.stderr, warm
    saved = list((tmp_path / "cache").rglob("*.nbi"))
    assert saved, "the warm-up cached nothing"

    out = tmp_path / "daemon.out"
    with out.open("w") as stdout, notified_daemon(
            ["run", "--interface", "virtual", "--channel", "warm-cache-test"],
            tmp_path / "notify.sock", dict(env, NUMBA_DEBUG_CACHE="1"),
            stdout=stdout) as (proc, sock):
        sock.settimeout(600)
        while b"READY=1" not in sock.recv(4096):
            pass
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    debug = out.read_text()
    assert "data loaded" in debug, debug[-2000:]
    compiled = [line for line in debug.splitlines() if "data saved" in line]
    assert not compiled, "the daemon compiled at start:\n" + "\n".join(compiled)
