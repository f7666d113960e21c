"""matplotlib for the figures (identify's report, the experiments'), imported only when a figure
is drawn: the daemon never imports it."""

from __future__ import annotations

from types import ModuleType

from monitor.errors import UsageError

__all__ = ["pyplot"]


def pyplot() -> ModuleType:
    """matplotlib.pyplot on the file-only Agg backend; a clear error if it is missing."""
    try:
        import matplotlib
    except ImportError:
        raise UsageError("this command draws figures and needs matplotlib: "
                         "pip install 'motor-monitor[experiments]'") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
