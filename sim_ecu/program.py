"""The `sim-ecu` executable: `sim_ecu.cli.main` in a process of its own, started without
python-can's MF4 support (`monitor.runtime.imports.without_mf4`): the virtual ECU reads no
bus log. The command line module is imported only after that, since it imports python-can."""

from __future__ import annotations

import importlib

from monitor.runtime.imports import without_mf4

__all__ = ["main"]


def main() -> int:
    without_mf4()
    cli = importlib.import_module("sim_ecu.cli")
    return int(cli.main())
