"""The layout holds: every module imports on its own, no import cycle among the modules
(counting the imports inside functions: `import_cycle`, itself tested on small packages
written here), the monitor never imports the simulation, the experiments or a plotting
library, and data flows one way (the pipeline knows no Rerun and no outlet). The direction
between the packages is import-linter's contracts in pyproject.toml (`lint-imports`)."""

from __future__ import annotations

import graphlib
import json
import subprocess
import sys
import uuid
from pathlib import Path

import grimp
import pytest

from tests.support.paths import ROOT

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
    loaded = _modules_after("monitor.app.cli, monitor.app.run, monitor.app.daemon, "
                            "monitor.app.replay, monitor.app.identify, monitor.app.calibrate")
    for forbidden in ("sim_ecu", "experiments", "matplotlib"):
        assert not [m for m in loaded if m.split(".")[0] == forbidden], forbidden


def test_the_pipeline_knows_no_rerun_and_no_outlet() -> None:
    loaded = _modules_after("monitor.pipeline")
    assert not [m for m in loaded if m.split(".")[0] in ("rerun", "rerun_bindings")]
    assert not [m for m in loaded if m == "monitor.sinks" or m.startswith("monitor.sinks.")]


# ------------------------------------------------------------------ import cycles


def import_cycle(*packages: str) -> list[str] | None:
    """A cycle of imports among the modules of `packages` (the first module again at its
    end), None if there is none. Every import statement counts, those inside functions
    too (grimp reads them all), except those under ``if TYPE_CHECKING:``, which never run.
    Importing ``a.b.c`` runs ``a/b/__init__.py`` first: an import also leads to each
    package above the imported module that does not hold the importer."""
    graph = grimp.build_graph(*packages, exclude_type_checking_imports=True, cache_dir=None)
    edges: dict[str, set[str]] = {m: set() for m in graph.modules}
    for importer in graph.modules:
        for imported in graph.find_modules_directly_imported_by(importer):
            edges[importer].add(imported)
            parts = imported.split(".")
            for i in range(1, len(parts)):
                parent = ".".join(parts[:i])
                if not (importer == parent or importer.startswith(parent + ".")):
                    edges[importer].add(parent)
    try:
        graphlib.TopologicalSorter(edges).prepare()
    except graphlib.CycleError as exc:
        return [str(m) for m in exc.args[1]]
    return None


def test_no_import_cycle() -> None:
    assert import_cycle("monitor", "sim_ecu", "experiments") is None


def _package(root: Path, files: dict[str, str]) -> str:
    """A package of `files` (path below the package -> source) under `root`, its name new
    to this process; returns the name."""
    name = f"cycle_probe_{uuid.uuid4().hex}"
    for rel, text in {"__init__.py": "", **files}.items():
        path = root / name / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text.replace("PKG", name), encoding="utf-8")
    return name


@pytest.fixture
def probe_root(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.syspath_prepend(str(tmp_path))
    return tmp_path


def test_the_cycle_check_sees_an_import_inside_a_function(probe_root: Path) -> None:
    late = "def f() -> None:\n    from PKG import a\n"
    name = _package(probe_root, {"a.py": "from PKG import b\n", "b.py": late})
    assert import_cycle(name) in ([f"{name}.a", f"{name}.b", f"{name}.a"],
                                  [f"{name}.b", f"{name}.a", f"{name}.b"])
    acyclic = _package(probe_root, {"a.py": "from PKG import b\n", "b.py": "X = 1\n"})
    assert import_cycle(acyclic) is None


def test_the_cycle_check_sees_a_cycle_through_a_package(probe_root: Path) -> None:
    """The pipeline and its outlets as they were: the engine's package imports the engine,
    the engine the outlets' interface, and that the events beside the engine, which runs
    the engine's package first."""
    name = _package(probe_root, {
        "pipe/__init__.py": "from PKG.pipe.core import run\n",
        "pipe/core.py": "from PKG.out.base import Out\n\ndef run() -> None: ...\n",
        "pipe/events.py": "class Event: ...\n",
        "out/__init__.py": "",
        "out/base.py": "from PKG.pipe.events import Event\n\nclass Out: ...\n",
    })
    cycle = import_cycle(name)
    assert cycle is not None and f"{name}.pipe" in cycle and f"{name}.out.base" in cycle


def test_the_cycle_check_leaves_out_what_only_type_checkers_read(probe_root: Path) -> None:
    typing_only = ("from typing import TYPE_CHECKING\n\nif TYPE_CHECKING:\n"
                   "    from PKG import a\n")
    name = _package(probe_root, {"a.py": "from PKG import b\n", "b.py": typing_only})
    assert import_cycle(name) is None
