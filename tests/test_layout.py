"""The layout holds: every module imports on its own (no import cycle between stages), the
monitor never imports the simulation, the experiments or a plotting library, and data flows
one way (the pipeline knows no Rerun and builds no CAN frame)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

PROBE = r"""
import importlib, json, pkgutil, sys
roots = ("monitor", "sim_ecu", "experiments")
names = []
for root in roots:
    pkg = importlib.import_module(root)
    names.append(root)
    names += [m.name for m in pkgutil.walk_packages(pkg.__path__, root + ".")
              if not m.name.endswith("__main__") and "_aot" not in m.name]
def fresh():
    for k in list(sys.modules):
        if k.split(".")[0] in roots:
            del sys.modules[k]
failed = {}
for name in names:
    fresh()
    try:
        importlib.import_module(name)
    except Exception as exc:
        failed[name] = f"{type(exc).__name__}: {exc}"
print(json.dumps({"modules": len(names), "failed": failed}))
"""


def _run(code: str) -> object:
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout.strip().splitlines()[-1])


def _modules_after(imports: str) -> list[str]:
    found = _run(f"import json, sys\nimport {imports}\nprint(json.dumps(sorted(sys.modules)))")
    assert isinstance(found, list)
    return found


def test_every_module_imports_alone() -> None:
    found = _run(PROBE)
    assert isinstance(found, dict)
    assert found["failed"] == {}, found["failed"]
    assert found["modules"] > 40


def test_the_daemon_imports_no_simulation_experiments_or_plotting() -> None:
    loaded = _modules_after("monitor.app.cli, monitor.app.run, monitor.app.replay, "
                            "monitor.app.identify, monitor.app.calibrate")
    for forbidden in ("sim_ecu", "experiments", "matplotlib"):
        assert not [m for m in loaded if m.split(".")[0] == forbidden], forbidden


def test_the_pipeline_knows_no_rerun_and_no_outlet() -> None:
    loaded = _modules_after("monitor.pipeline")
    assert not [m for m in loaded if m.split(".")[0] in ("rerun", "rerun_bindings")]
    assert not [m for m in loaded if m.startswith("monitor.sinks.") and m != "monitor.sinks.base"]
