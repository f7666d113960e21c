"""What a process that reads no MF4 file leaves out of its start-up.

python-can imports its MF4 reader and writer with every ``import can`` (cantools imports
python-can too), and that module imports asammdf and, through it, pandas when they are
installed: 0.7 s of a 3 s start on a desktop machine, 12 s of a 35 s start in the User-Mode
Linux guest of the vcan tests, where every imported file is read through hostfs. The live
daemon (`motor-monitor run`) and the virtual ECU read no log and write only .blf and .log
(`monitor.bus.rawlog.RAW_FORMATS`), so they start without it, as on an install without the
``mf4`` extra: python-can then treats asammdf as absent (its documented behaviour, the MF4
classes raise when used), and `monitor.bus.logfile` names the missing extra should an MF4
file be asked for anyway.
"""

from __future__ import annotations

import sys

__all__ = ["MF4_MODULE", "without_mf4"]

#: The package python-can's MF4 support imports (and which imports pandas).
MF4_MODULE = "asammdf"


def without_mf4() -> bool:
    """Make this process's imports of asammdf fail, as if it were not installed, so that
    python-can does not load it; True if done.

    Only a program's own process may call this, before anything imported python-can (after
    that it is too late, and it leaves things as they are: False). A None entry in
    `sys.modules` is the import system's own way to refuse a module (``import asammdf``
    raises ModuleNotFoundError, `importlib.util.find_spec` returns None).
    """
    if "can" in sys.modules or MF4_MODULE in sys.modules:
        return False
    sys.modules[MF4_MODULE] = None  # type: ignore[assignment]
    return True
