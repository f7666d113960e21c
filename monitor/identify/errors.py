"""The one error of the identification, and the refusal a model with friction may answer."""

from __future__ import annotations

from monitor.errors import MonitorError

__all__ = ["GrowingModeError", "IdentifyError"]


class IdentifyError(MonitorError, ValueError):
    """A capture (or a fitted model) that cannot give a trustworthy model. The message is
    one line that says what is wrong and what to record instead."""


class GrowingModeError(IdentifyError):
    """A fit refused for a growing mode the input drives (`monitor.identify.core`): the
    linear model's stand-in for a nonlinearity, which may be a friction that keeps one sign
    (`identify`'s friction refit answers it where the output is a speed or a position)."""
