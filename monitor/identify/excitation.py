"""What to record: an input that identification can use.

A healthy capture for `identify` moves the input (a motor's voltage command, say) around its
operating point, so the output shows the plant's dynamics above the noise: steps or a
pseudo-random binary sequence (PRBS) of a few per cent of the operating point, switching
on a clock of about the plant's main time constant, for about a minute.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

__all__ = ["RECORDING_ADVICE", "prbs"]

RECORDING_ADVICE = (
    "record with the input varying: steps or a PRBS of +-5 to 10 % around the "
    "operating point, switching every 1 to 3 time constants of the plant, for 60 s"
)


def prbs(
    duration: float,
    T: float,
    *,
    level: float | NDArray[np.float64],
    amplitude: float | NDArray[np.float64],
    clock: float,
    seed: int = 0,
) -> Array:
    """(N, m) samples of level +- amplitude, each channel's sign drawn anew every `clock`
    seconds (kept with probability 1/2: a random binary signal with a flat spectrum up to
    about 0.4 / clock Hz). Channels are independent; m follows `level`/`amplitude`."""
    lv = np.atleast_1d(np.asarray(level, dtype=float))
    am = np.atleast_1d(np.asarray(amplitude, dtype=float))
    m = max(lv.size, am.size)
    N = round(duration / T)
    per = max(1, round(clock / T))
    rng = np.random.default_rng(seed)
    signs = rng.choice([-1.0, 1.0], size=(N // per + 1, m))
    return np.asarray(lv + am * np.repeat(signs, per, axis=0)[:N])
