"""The one error of the identification."""

from __future__ import annotations

from monitor.errors import MonitorError

__all__ = ["IdentifyError"]


class IdentifyError(MonitorError, ValueError):
    """A capture (or a fitted model) that cannot give a trustworthy model. The message is
    one line that says what is wrong and what to record instead."""
