"""The one error of the identification, and the refusals a model with friction or a load
may answer."""

from __future__ import annotations

from monitor.errors import MonitorError

__all__ = ["GrowingModeError", "IdentifyError", "LevelAmbiguityError", "PlantChangeError",
           "SlowModeError"]


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
    refit answers that one)."""


class LevelAmbiguityError(IdentifyError):
    """A fit refused because the capture's input took two levels alone and the outputs show
    what two levels cannot tell apart (`monitor.identify.core`, `_limit_ambiguity`): an
    actuator limit at the larger level, friction or a sensor offset. A fact of the data,
    not of one fit: where a refit that can carry an offset (the friction's) shows it, a
    linear fit that took it into its gain is as ambiguous. `error_noise_units`: how far
    wrong at other levels the model may be, in innovation standard deviations (infinite
    where the capture is blind to a limit)."""

    def __init__(self, message: str, error_noise_units: float) -> None:
        super().__init__(message)
        self.error_noise_units = error_noise_units
