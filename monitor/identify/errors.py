"""The one error of the identification, and the refusals a model with friction or a load
may answer."""

from __future__ import annotations

from typing import Any

from monitor.errors import MonitorError

__all__ = ["GrowingModeError", "IdentifyError", "PlantChangeError", "SlowModeError"]


class IdentifyError(MonitorError, ValueError):
    """A capture (or a fitted model) that cannot give a trustworthy model. The message is
    one line that says what is wrong and what to record instead."""


class GrowingModeError(IdentifyError):
    """A fit refused for a growing mode the input drives (`monitor.identify.core`): the
    linear model's stand-in for a nonlinearity, which may be a friction that keeps one sign
    (`identify`'s friction refit answers it where the output is a speed or a position)."""


class PlantChangeError(IdentifyError):
    """A fit refused because the capture's halves, or its hold-out part, fit differently
    (`monitor.identify.core`): a fault or an outage, or a load that steps while the capture
    runs (`identify`'s load refit answers that one)."""


class SlowModeError(IdentifyError):
    """A fit refused because its slowest mode is too slow for the capture to span
    (`monitor.identify.core`): a plant that needs a longer capture, or a load that steps
    while the capture runs, which a linear fit explains with a slow mode (`identify`'s load
    refit answers that one). `friction` is the report's "friction" entry of a fit with
    Coulomb friction refused so: what the refit measured of the friction stands, the model
    does not (`identify`'s friction probe weighs it)."""

    def __init__(self, message: str, friction: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.friction = friction
