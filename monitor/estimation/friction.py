"""Coulomb friction in the plant model: a term the estimator applies with the input, one rule
for the step kernel and for `identify` (our extension, not Liu, Bao, Xue, Du, Int. J. Fuzzy
Systems 22(1), 2020).

A drive's shaft meets a torque of constant size against its motion, -T_c sign(speed). A
linear model has nothing like it: where the speed keeps one sign it is a constant the fit
takes for an offset, where the speed reverses (a spring-held valve, a positioning axis)
its switching reads as a change of the input's effect, which the fuzzy UKF's gamma^ takes
for a loss of effectiveness (the rig zoo: gamma^ 0.25 to 0.64 on healthy captures). With
`Friction` the plant is

    E x' = A x + B u_F + b_f phi + w,     phi = -tanh(v / width)                  (1)

where v is the speed the model itself predicts over the step: the output `output`'s
mean over the step where that output is a speed ("output"), its mean rate of change
where it is a position ("rate"), from the filter's estimate at the step's start and the
input applied in it (the prior's mean without the friction). tanh smooths the sign where
v is within a few `width` of zero: there the estimate does not know the sign, and a hard
sign would flip the term with the noise. phi is a known input of the step, like a known
actuator of the model (gamma = 0 on it), held over the step as the inputs are (the
zero-order hold of b_f: `DiscreteModel.friction_at`); the covariance is propagated as for
a known input (phi's dependence on x is left out of the Jacobian: it acts only within a
few widths of zero speed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from monitor.jit import njit

Array = NDArray[np.float64]

__all__ = ["FRICTION_SPEEDS", "Friction", "coulomb", "friction_code", "friction_speed",
           "speed_row"]

FRICTION_SPEEDS = ("output", "rate")
"""What the friction's speed v is: the output itself (a speed), or its rate of change (a
position)."""


@dataclass(frozen=True)
class Friction:
    """Coulomb friction (1) of a model with n states: `B` the state equation's column b_f
    (n,), in the descriptor's own coordinates, `speed` one of FRICTION_SPEEDS, `output` the
    index of the output it is read from, `width` the speed (in that output's unit, per
    second for "rate") within which the friction fades to zero."""

    B: Array
    speed: str
    output: int
    width: float


def friction_code(speed: str) -> float:
    """The kernel's code of a friction speed (0: no friction)."""
    return float(FRICTION_SPEEDS.index(speed) + 1)


@njit
def friction_speed(A: Array, b: Array, x: Array, S: Array, code: float, dt: float) -> float:
    """v of (1) for the step of dt from the estimate x (the filter's state), with A the
    step's transition and b its input term B u_F: S (x + x-) / 2 (code 1, "output") or
    S (x- - x) / dt (code 2, "rate"), x- = A x + b the prior's mean without the friction."""
    n = x.shape[0]
    v = 0.0
    for r in range(n):
        if S[r] == 0.0:
            continue
        xm = b[r]
        for c in range(n):
            xm += A[r, c] * x[c]
        v += S[r] * (0.5 * (x[r] + xm) if code < 1.5 else (xm - x[r]) / dt)
    return v


@njit
def coulomb(A: Array, b: Array, x: Array, S: Array, code: float, width: float,
            dt: float) -> float:
    """phi of (1), -tanh(v / width) with v = `friction_speed`; 0 without friction
    (code 0)."""
    if code <= 0.0:
        return 0.0
    return -math.tanh(friction_speed(A, b, x, S, code, dt) / width)


def speed_row(C: Array, output: int, n: int) -> Array:
    """S of `coulomb`: the output's row of C over the filter's n states (zeros beyond C's
    own: bias states carry no speed)."""
    S = np.zeros(n)
    S[:C.shape[1]] = C[output]
    return S
