"""The input delay of a capture: how many samples pass before an output answers its input.

`estimate_input_delay` follows MATLAB's ``delayest``: for every candidate delay d it fits
an ARX model by least squares on the rows of held inputs h and outputs y
(`monitor.pipeline.samples`: h(k) is the input held at output sample k),

    y(k) = - a1 y(k-1) - ... - a_na y(k-na) + b_d h(k-d) + ... + b_L h(k-L) + c + e(k),

and compares the losses. d is the delay of the monitor's rule: the estimator's step for
sample k applies h(k - d). Unlike ``delayest``'s equal-length input taps, the taps of every
candidate run to the same last lag L = max_delay + nb - 1, so the candidates are nested
(delay d drops the first d taps of delay 0) and the delay is the largest one whose dropped
taps an F-test does not find (level `ALPHA`). Equal-length taps, two poles and the least
loss misplace the delay of a second-order plant sampled fast, where the equation error of
the noisy output lags outweighs the input's first small effect (the taps a few samples
later fit that error better); nested models with `NA` output lags do not.

A delay is placed only where the data bracket it: some candidate's dropped taps must
matter (the response is seen to start). When no candidate's do -- a slow or smooth plant
sampled fast, whose first samples of response are far below the noise, or a plant the
output lags alone predict -- the taps give no start, and the delay is 0: a delay too short
is absorbed by the model's dynamics (a lag, more order), whereas one too long leaves the
model blind to the response's start, which no order repairs (the sequential rule alone
would then run to `max_delay`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import stats

Array = NDArray[np.float64]

__all__ = ["MAX_ESTIMATED_DELAY", "DelayEstimate", "estimate_input_delay"]

MAX_ESTIMATED_DELAY = 10
"""The largest delay `estimate_input_delay` tries by default (samples): dead times of
several samples, far past the one a held command sent before its output adds."""

NA = 4  # output lags: enough for the plants the estimator's rule base holds to whiten e
NB = 3  # input taps past the largest candidate delay
ALPHA = 1e-3  # F-test level: a delay is refused only when its dropped taps clearly matter


@dataclass(frozen=True)
class DelayEstimate:
    """The delay chosen and, per candidate delay, the ARX loss: the residual sum of squares
    over the output's own (mean-removed) sum of squares, averaged over the outputs; and the
    F-test's p-value of the taps that delay drops (1 for delay 0). `placed`: some
    candidate's dropped taps matter, so the taps show where the response starts (False:
    delay 0 by default, see the module docstring)."""

    delay: int
    loss: dict[int, float]
    p_value: dict[int, float]
    placed: bool = True


def estimate_input_delay(held: Array, y: Array, max_delay: int = MAX_ESTIMATED_DELAY
                         ) -> DelayEstimate:
    """The input delay (0..max_delay samples) of held inputs `held` (N, m) and outputs `y`
    (N, p): the largest delay whose ARX model fits as well as delay 0's by an F-test, and 0
    when no candidate's dropped taps matter (the start of the response is not seen). One
    delay for every input and output, as the monitor applies one. ValueError for a record
    too short to fit the candidates."""
    h = np.asarray(held, dtype=float)
    yy = np.asarray(y, dtype=float)
    N, p = yy.shape
    m = h.shape[1]
    last = max_delay + NB - 1
    rows = np.arange(max(NA, last), N)
    n_full = NA * p + (last + 1) * m + 1
    dof = rows.size - n_full
    if dof <= 10 * n_full:
        raise ValueError(f"{N} samples are too few to estimate a delay of up to {max_delay}")
    target = yy[rows]
    ss = np.sum((target - target.mean(axis=0)) ** 2, axis=0)
    ss = np.where(ss > 0, ss, 1.0)  # a constant output: its residual is 0 for every delay
    # Columns ordered so that delay d keeps the first n_full - d m: one QR of the whole
    # regressor gives every candidate's residual (the projections on the columns it drops).
    phi = np.hstack([*(yy[rows - i] for i in range(1, NA + 1)), np.ones((rows.size, 1)),
                     *(h[rows - j] for j in range(last, -1, -1))])
    q, r = np.linalg.qr(phi)
    proj = q.T @ target
    # a column dependent on the others (an input constant over the rows) projects nothing
    proj[np.abs(np.diag(r)) <= 1e-10 * np.max(np.abs(np.diag(r))), :] = 0.0
    full = np.sum(target ** 2, axis=0) - np.sum(proj ** 2, axis=0)
    rss = {d: full + np.sum(proj[n_full - d * m:] ** 2, axis=0) for d in range(max_delay + 1)}
    noise = np.maximum(full, np.finfo(float).tiny) / dof
    p_value: dict[int, float] = {0: 1.0}
    delay = 0
    for d in range(1, max_delay + 1):
        # the outputs' F statistics pooled: each output's extra residual in units of its
        # own noise variance under the full model
        f = float(np.sum((rss[d] - rss[0]) / noise)) / (d * m * p)
        p_value[d] = float(stats.f.sf(f, d * m * p, dof * p))
        if p_value[d] > ALPHA and delay == d - 1:
            delay = d
    loss = {d: float(np.mean(r / ss)) for d, r in rss.items()}
    placed = min(p_value.values()) <= ALPHA
    return DelayEstimate(delay if placed else 0, loss, p_value, placed)
