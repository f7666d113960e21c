"""The one error of the identification, and the refusals a model with friction or a load
may answer."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from monitor.errors import MonitorError

__all__ = ["GrowingModeError", "IdentifyError", "PlantChangeError", "SlowModeError",
           "carrying_fit"]


class IdentifyError(MonitorError, ValueError):
    """A capture (or a fitted model) that cannot give a trustworthy model. The message is
    one line that says what is wrong and what to record instead. `friction` is the
    report's "friction" entry where a fit with Coulomb friction was refused after it was
    measured: what the refit measured of the friction stands, its model does not
    (`identify`'s friction probe weighs it). `order` is the order the data chose where a
    black box of an automatic order was refused after its fit (None otherwise): one order
    lower may fit without what refused it (`identify` tries it)."""

    def __init__(self, message: str, friction: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.friction = friction
        self.order: int | None = None


@contextmanager
def carrying_fit(friction: dict[str, Any] | None, order: int | None) -> Iterator[None]:
    """Gives every IdentifyError raised inside it the friction measured before and the
    order the data chose (None: none was)."""
    try:
        yield
    except IdentifyError as exc:
        if exc.friction is None:
            exc.friction = friction
        if exc.order is None:
            exc.order = order
        raise


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
    refit answers that one)."""
