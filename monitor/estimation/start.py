"""Where the fuzzy UKF starts: its initial covariance and, without an x0, its first state.

(f) Scale: P0 = None is the stationary Kalman covariance in the state's own units
    (`initial_covariance`); P0 = 1 meant 1 A on a 0.26 A current and 1 rad/s on a
    790 rad/s speed. The fuzzy input is normalised by the whole prior covariance (step 7):
    by P^- alone, the bias-free part, the servo's speed component of x_e swung by 28 of
    its "sigmas" in healthy running.
(h) Start without an x0 (`start_state`): from the fault-free steady state of the first
    input, x_ss = (I - A)^-1 B u with V = d x_ss / d gamma (`steady_start`), only when the
    first output confirms it (a monitor attached to a running motor). Started from there
    in every case, a motor at rest when the first command came -- no current at full
    voltage, what an outage at steady state looks like -- was read as an outage for the
    60-80 ms the filter took to converge, at every start of a replay and after every
    restart. Otherwise the state at the first sample is the steady state whose output is
    nearest the first output, each state's uncertainty the whole range from rest to the
    steady state, conditioned on that output by the update (44)-(49); gamma's common part
    starts at the small variance var_start, so the start-up transient goes to the state
    and not to gamma^, and a fault present from the start is found by the test (20).

"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from monitor.estimation.model import DiscreteModel

Array = NDArray[np.float64]

__all__ = ["StartState", "initial_covariance", "initial_covariance_of", "start_state",
           "steady_start"]


def initial_covariance(model: DiscreteModel) -> Array:
    """A scale-aware initial covariance of the observable state (P0 = None): the Kalman
    filter's stationary posterior covariance at the model's period, else the covariance of
    the state fitted to n noisy output samples (`DiscreteModel.initial_covariance`). The
    model computes it, and refuses to be built without one, when it is made: the rig check
    then guarantees that the estimator starts."""
    return model.initial_covariance()


_P0_CACHE: dict[int, tuple[DiscreteModel, Array]] = {}


def initial_covariance_of(model: DiscreteModel) -> Array:
    """`initial_covariance` once per model object: the pipeline restarts a node's
    estimator after a long gap or a NaN (one per gap under a flood), and the discrete
    Riccati solve must not be paid at each. The model is kept beside its id, so the id
    cannot be reused while the entry lives."""
    hit = _P0_CACHE.get(id(model))
    if hit is not None and hit[0] is model:
        return hit[1]
    P = initial_covariance(model)
    if len(_P0_CACHE) > 64:
        _P0_CACHE.clear()
    _P0_CACHE[id(model)] = (model, P)
    return P


def steady_start(model: DiscreteModel, u: Array, y: Array) -> tuple[Array, Array]:
    """(x^, V) to start from without a known initial state: the fault-free steady state
    (`start_state` uses it when the first output confirms it).

    A monitor attached to a running motor would otherwise start from x = 0 and read its
    own convergence as a fault. The steady state x_ss = (I - A)^-1 B u (1 - gamma) depends
    on the loss of effectiveness, which is not known yet: the filter starts at gamma^ = 0
    with V = d x_ss / d gamma (zero for the known actuators), so that what the first
    samples say about gamma moves the state with it (the two-stage coupling from the
    start); the first sample is then used once, by the filter's update. A model with an
    integrator among its observable states has no steady state: then x^ is the
    least-squares fit of [I - A; C] x = [B u; y - D u] to the first sample, with V = 0.
    """
    A, B, _ = model.at(model.T)
    n = A.shape[0]
    IA = np.eye(n) - A
    dB = -B * u
    dB[:, [a for a in range(model.m) if a not in model.fault_inputs]] = 0.0
    if np.linalg.cond(IA) < 1e12:
        sol = np.linalg.solve(IA, np.column_stack([B @ u, dB]))
    else:
        rhs = np.concatenate([B @ u, y - model.D @ u])
        fit, *_ = np.linalg.lstsq(np.vstack([IA, model.C]), rhs, rcond=None)
        sol = np.column_stack([fit, np.zeros_like(dB)])
    if not np.all(np.isfinite(sol)):
        return np.zeros(n), np.zeros_like(dB)
    x0: Array = np.array(sol[:, 0], dtype=np.float64)
    V0: Array = np.array(sol[:, 1:], dtype=np.float64)
    return x0, V0


# The steady state of the first input explains the first output when the output it predicts
# is within 3 sigma per output (squared whitened distance 9 p): otherwise the plant is
# somewhere else (at rest, in a transient, faulty), and the filter starts from the output.
_START_GATE = 9.0


@dataclass
class StartState:
    """Where the filter starts without an x0 (`start_state`).

    measured False: x, V, P are the state before the first sample, which the kernel then
    processes like any other (time update (35)-(43) and measurement update (44)-(49)).
    measured True: x, P are the estimate at the first sample itself, the prior x_prior
    conditioned on its output, with V = 0; y_prior, nu and S are that update's predicted
    output, innovation and innovation covariance (the kernel does not run on the sample).
    """

    measured: bool
    x: Array
    V: Array
    P: Array
    x_prior: Array | None = None
    y_prior: Array | None = None
    nu: Array | None = None
    S: Array | None = None


def start_state(model: DiscreteModel, u: Array, y: Array, P_base: Array) -> StartState:
    """The start of the filter without a known initial state: what the first output says.

    A monitor meets a plant in one of two ways: attached to one that runs (at the steady
    state of its command, or of an earlier one, healthy or not), or started with it (at
    rest when the first command comes, the first output one period into the response).
    Starting from the fault-free steady state of the first command in every case made a
    start at rest read as an outage -- current 0 at full voltage is what an outage at
    steady state looks like -- until the filter converged. So:

    1. The steady state of the command, x_c = (I - A)^-1 B u, is the prior. If the output
       it predicts explains the first output (within 3 sigma per output, with the predicted
       output covariance C (A P_base A' + Q) C' + R of (44)-(45)) and rest does not (at the
       sample, or one period into the command's response), the filter starts there,
       coupled to the unknown gamma (`steady_start`, V = d x_c / d gamma), and the kernel
       processes the first sample: a monitor attached to a running healthy motor starts
       without a transient, as before. When both explain it -- a back-EMF dominated motor
       whose steady current is within its sensor's noise -- the output cannot tell: case 2.
    2. Otherwise the output is what is known, at the first sample's own time. The prior
       there is the steady state whose output comes nearest to it, x_k = (I - A)^-1 B v
       with C x_k + D u = y fitted for v (least squares; the smallest change from u when
       there are more inputs than outputs), v kept between rest and the command on each
       actuator (an output no steady state gives -- a fast motor's current one period
       after a step -- must not throw the prior far out of the plant's range). Its
       uncertainty is diagonal on top of P_base, s_i = max(|x_c,i|, |x_k,i|, |e_i|) with
       e = C^+ (y - C x_k - D u): each state anywhere from rest to the larger of the two
       steady states, the outputs as far as the fit misses. That prior is conditioned on
       the first output by the measurement update (44)-(49) -- the Kalman update, the
       model being linear -- without a time update, since the input that acted before the
       first sample is not known. The directions the output pins come out at its noise,
       the others stay wide and the next samples narrow them; the state carries no
       sensitivity to gamma (V = 0), being no steady state of the first input.

    A model with an integrator among its observable states has no steady state: x_k is
    then the least-squares fit of [I - A; C] x = [B u; y - D u] (`steady_start`), x_c = x_k.
    In case 2 the filter gives gamma^ = 0 the small variance `var_start`
    (`FuzzyUKF._init_from_sample`), so that the start-up transient goes to the wide state.
    """
    A, B, Q = model.at(model.T)
    C, D, R = model.C, model.D, model.R
    n = A.shape[0]
    x_s, V_s = steady_start(model, u, y)
    IA = np.eye(n) - A
    steady = bool(np.linalg.cond(IA) < 1e12)
    Du = D @ u
    if steady:
        Sp = C @ (A @ P_base @ A.T + Q) @ C.T + R
        gate = _START_GATE * model.p

        def fits(e: Array) -> bool:
            return float(e @ np.linalg.solve(Sp, e)) <= gate

        # rest explains the output too (a back-EMF dominated motor with a noisy sensor: its
        # steady current is within the noise of none): the output cannot tell them apart
        at_rest = fits(y - Du) or fits(y - C @ B @ u - Du)
        if fits(y - C @ (A @ x_s + B @ u) - Du) and not at_rest:
            return StartState(False, x_s, V_s, P_base.copy())
        Gx = np.linalg.solve(IA, B)  # the steady state per unit of each input
        x_c = Gx @ u
        dv, *_ = np.linalg.lstsq(C @ Gx, y - Du - C @ x_c, rcond=None)
        v = np.clip(u + dv, np.minimum(u, 0.0), np.maximum(u, 0.0))
        x_k = Gx @ v
    else:
        x_c = x_k = x_s
    nu = y - C @ x_k - Du
    s = np.maximum(np.maximum(np.abs(x_c), np.abs(x_k)), np.abs(np.linalg.pinv(C) @ nu))
    Pk = P_base + np.diag(s * s)
    S = C @ Pk @ C.T + R
    S = 0.5 * (S + S.T)
    K = np.linalg.solve(S, C @ Pk).T
    IKC = np.eye(n) - K @ C
    P = IKC @ Pk @ IKC.T + K @ R @ K.T  # Joseph form: symmetric, positive definite
    P = 0.5 * (P + P.T)
    x = x_k + K @ nu
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(P))):
        return StartState(False, x_s, V_s, P_base.copy())
    return StartState(True, x, np.zeros_like(V_s), P, x_k, C @ x_k + Du, nu, S)
