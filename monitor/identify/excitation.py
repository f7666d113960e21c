"""What to record: an input that identification can use.

A healthy capture for `identify` moves the input (a motor's voltage command, say) around its
operating point, so the output shows the plant's dynamics above the noise: steps between
several levels, or a pseudo-random sequence of them, of a few per cent of the operating
point, switching on a clock of about the plant's main time constant, for about a minute.
Two levels alone (a binary PRBS) check the model between them only: an actuator that
clips the larger one looks like a smaller gain with an offset (`identify` refuses such a
capture where it cannot tell them apart).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

__all__ = ["ONE_CONDITION_ADVICE", "RECORDING_ADVICE", "prbs"]

RECORDING_ADVICE = (
    "record with the input varying: steps between several levels (random steps or a "
    "multi-level PRBS) within +-5 to 10 % of the operating point, switching every 1 to 3 "
    "time constants of the plant, for 60 s"
)

ONE_CONDITION_ADVICE = "record the healthy node only, at one load"
"""What to record where the capture holds more than one plant: a fault, an outage or load
steps within it."""


def prbs(
    duration: float,
    T: float,
    *,
    level: float | NDArray[np.float64],
    amplitude: float | NDArray[np.float64],
    clock: float,
    seed: int = 0,
    levels: int = 2,
) -> Array:
    """(N, m) samples of level + amplitude s, s drawn anew every `clock` seconds from
    `levels` values evenly spaced over [-1, 1] (kept with probability 1 / levels: a random
    signal with a flat spectrum up to about 0.4 / clock Hz). `levels` 2 is the binary
    sequence (+-amplitude); more levels show a gain that changes with the level (an
    actuator's limit). Channels are independent; m follows `level`/`amplitude`."""
    if levels < 2:
        raise ValueError(f"levels must be 2 or more, got {levels}")
    lv = np.atleast_1d(np.asarray(level, dtype=float))
    am = np.atleast_1d(np.asarray(amplitude, dtype=float))
    m = max(lv.size, am.size)
    N = round(duration / T)
    per = max(1, round(clock / T))
    rng = np.random.default_rng(seed)
    signs = rng.choice(np.linspace(-1.0, 1.0, levels), size=(N // per + 1, m))
    return np.asarray(lv + am * np.repeat(signs, per, axis=0)[:N])
