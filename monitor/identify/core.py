"""`identify`: arrays in, a model for the estimator and a report out."""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import scipy.signal
from numpy.typing import ArrayLike, NDArray
from threadpoolctl import threadpool_limits

from monitor.errors import one_line
from monitor.estimation.friction import Friction
from monitor.estimation.fuzzy_ukf import FuzzyUKF
from monitor.estimation.model import (
    ContinuousDescriptor,
    DCMotorParameters,
    DiscreteModel,
    ModelError,
    dc_motor,
)
from monitor.identify import validate as V
from monitor.identify.blackbox import ORDER_MARGIN, fit_state_space, subspace_model
from monitor.identify.dcmotor import fit_dc_motor, oe_refit
from monitor.identify.delay import MAX_ESTIMATED_DELAY, estimate_input_delay
from monitor.identify.errors import (
    GrowingModeError,
    IdentifyError,
    PlantChangeError,
    SlowModeError,
    carrying_fit,
)
from monitor.identify.excitation import ONE_CONDITION_ADVICE, RECORDING_ADVICE
from monitor.identify.friction import FRICTION_ITERATIONS, friction_column, speed_estimate
from monitor.identify.load import LOAD_ITERATIONS, LoadSteps, load_steps, settled
from monitor.identify.lti import dsim, integrating, kalman, predict, steady_state_x0
from monitor.identify.noise import process_noise_scale
from monitor.pipeline.samples import MAX_INPUT_DELAY, delayed, fit_rows, no_past

Array = NDArray[np.float64]

__all__ = ["KINDS", "QUANTISATION_VARIANCE", "Identification", "identify", "quantisation_floor"]

KINDS = ("auto", "dc_motor", "state_space")
MAX_ORDER = 10  # the largest state the estimator's rule base holds (`estimator_bytes`)
MAX_GROWING_SHARE = 0.01
"""The largest share of an output's swing over the capture that the input may drive
through a growing mode of a fitted model (`_growing_input_share`): an offset the mode
carries on its initial state drives nothing; a gain it carries drove 25 % (see
`_identify`)."""
LIMIT_SHARE = 0.01
"""`_limit_ambiguity`: the least error, as a share of the output's swing, that counts."""
OFFSET_STRETCHES = 8
"""`_shown_offset`: the stretches whose intercepts a sign test compares."""
LIMIT_NOISE = 1.0
"""`_limit_ambiguity`: the largest error, in innovation standard deviations, that an
actuator limit a two-level capture cannot tell from a smaller gain with an offset may make
in a run at levels between the two (an error within one sample's noise goes unseen)."""
QUANTISATION_VARIANCE = 1.0 / 12.0
"""The variance rounding to whole steps adds to a measurement, in steps squared: the error
is uniform over one step (Widrow's model of uniform quantisation noise), step^2 / 12."""

_log = logging.getLogger(__name__)

# What numpy and scipy raise when a fit meets data it cannot describe (a Riccati equation
# without a stabilising solution, an SVD that does not converge on a degenerate record, an
# optimiser's step that overflows): each becomes one IdentifyError line, never a traceback.
NUMERIC_FAILURES = (np.linalg.LinAlgError, ValueError, FloatingPointError, OverflowError,
                    ZeroDivisionError)


@dataclass(frozen=True)
class Identification:
    """An identified model, ready for `model.discretize(T)` and `FuzzyUKF`.

    model: continuous descriptor model (63)-(67) or black box (E = I), with the noise model
        (1)-(2): Qc = q Q0 (Q0 = E E for the motor, as `dc_motor`), R per sample.
    motor: the fitted DC-motor parameters (kind "dc_motor"); J is the template's (fixed),
        La, Ra, b and Ke = Ki are fitted (report["identifiable"] says which combinations).
    report: plain JSON-serialisable dict (see `identify`).
    input_delay: the rig's `[model] input_delay` the model was fitted for: the estimator's
        step for output sample k applies the input held at sample k - input_delay
        (`monitor.pipeline.samples`).
    """

    model: ContinuousDescriptor
    q: float
    Qc: Array
    R: Array
    T: float
    kind: str
    order: int
    motor: DCMotorParameters | None
    report: dict[str, Any]
    traces: dict[str, Array] = field(default_factory=dict, repr=False)
    input_delay: int = 0

    def to_json(self) -> str:
        return json.dumps(self.report, indent=2, sort_keys=True)

    def to_png(self, path: str | Path) -> None:
        """Measured against simulated output on the hold-out, innovation autocorrelation
        and input cross-correlation with their bands. Needs matplotlib (UsageError if
        missing, from monitor.plotting.pyplot)."""
        from monitor.plotting import pyplot

        plt = pyplot()
        rep = self.report
        names_y = list(self.model.output_names)
        names_u = list(self.model.input_names)
        p = len(names_y)
        fig, axes = plt.subplots(3, p, figsize=(6 * p, 9), squeeze=False)
        t, y, yh = self.traces["t_holdout"], self.traces["y_holdout"], self.traces["y_sim"]
        wh, cc = rep["whiteness"], rep["cross_correlation"]
        for i, name in enumerate(names_y):
            ax = axes[0][i]
            ax.plot(t, y[:, i], lw=0.6, label="measured")
            ax.plot(t, yh[:, i], lw=0.9, label="simulated")
            ax.set_title(f"{name}: hold-out fit {rep['fit']['nrmse_holdout_pct'][i]:.1f} %")
            ax.set_xlabel("time (s)")
            ax.legend(loc="best")
            ax = axes[1][i]
            lags = np.arange(1, wh["lags"] + 1)
            ax.bar(lags, wh["autocorrelation"][i], width=0.6)
            for s in (-1, 1):
                ax.axhline(s * wh["band"], color="r", ls="--", lw=0.8)
            ax.set_title(f"innovation autocorrelation, Ljung-Box p = {wh['p_value'][i]:.3g}")
            ax.set_xlabel("lag (samples)")
            ax = axes[2][i]
            lags0 = np.arange(0, cc["lags"] + 1)
            for j, un in enumerate(names_u):
                ax.plot(lags0, cc["correlation"][i][j], marker=".", label=un)
            for s in (-1, 1):
                ax.axhline(s * cc["band"], color="r", ls="--", lw=0.8)
            ax.set_title(f"innovation x input correlation, p = {cc['p_value'][i]:.3g}")
            ax.set_xlabel("lag (samples)")
            ax.legend(loc="best")
        fig.suptitle(f"identified {self.kind} model, order {self.order}, T = {self.T:g} s")
        fig.tight_layout()
        fig.savefig(str(path), dpi=100)
        plt.close(fig)


@dataclass
class _Candidate:
    kind: str
    model: ContinuousDescriptor
    q: float
    order: int
    motor: DCMotorParameters | None
    params: dict[str, Any]
    extra: dict[str, Any]


def _floats(a: Array) -> list[Any]:
    out: list[Any] = np.asarray(a, dtype=float).tolist()
    return out


def _fit_motor(u: Array, y: Array, T: float, template: DCMotorParameters,
               names: tuple[tuple[str, ...], tuple[str, ...]]) -> _Candidate:
    try:
        sub, _ = subspace_model(u, y, 2)
        fit = fit_dc_motor(u, y, T, template, sub)
        prm = fit.params
        base = dc_motor(prm, q=fit.q, r=fit.r, speed_noise_ratio=fit.kappa)
        model = ContinuousDescriptor(E=base.E, A=base.A, B=base.B, C=base.C, Qc=base.Qc,
                                     R=base.R, state_names=base.state_names,
                                     input_names=names[0], output_names=names[1])
    except IdentifyError:
        raise
    except NUMERIC_FAILURES as exc:  # ModelError is a ValueError too
        raise IdentifyError(f"the DC-motor model does not fit this capture "
                            f"({one_line(exc, 160)}): {MOTOR_ADVICE}") from None
    params = {k: {"value": float(getattr(prm, k)),
                  "std": float(getattr(prm, k)) * fit.log_std[k]} for k in
              ("La", "Ra", "b", "Ke", "Ki")}
    params["J"] = {"value": prm.J, "std": 0.0}
    extra = {
        "identifiable": ["La", "Ra", "b/J", "Ke*Ki/J"],
        "fixed": {"J": prm.J},
        "note": "from the current alone J, b and Ke*Ki are known only up to a common scale: "
                "J is fixed to the template's, Ke = Ki = sqrt(Ke*Ki); another J gives the "
                "same current, filter and gamma estimate",
        "noise_ratio_rho": fit.rho,
        "speed_noise_ratio_kappa": fit.kappa,
        "function_evaluations": fit.nfev,
    }
    return _Candidate("dc_motor", model, fit.q, 2, prm, params, extra)


def _fit_black_box(u: Array, y: Array, ntr: int, T: float, order: int | None,
                   names: tuple[tuple[str, ...], tuple[str, ...]],
                   fault_inputs: tuple[int, ...] | None = None) -> _Candidate:
    """The black box fitted on the first ntr rows; the rest chooses its order.
    `fault_inputs`: the inputs that may lose effectiveness (None: all; the friction's
    phi is a known input, `_friction_box`)."""
    advice = ("the black-box fit found no usable model: record a longer capture with the "
              "input varying more (steps or a PRBS), or give --order")
    try:
        fit = fit_state_space(u, y, T, order, ntr)
        n = fit.order
        Ac, Bc, C, Qc = _balanced_scale(fit.Ac, fit.Bc, fit.C, 0.5 * (fit.Qc + fit.Qc.T))
        model = ContinuousDescriptor(
            E=np.eye(n), A=Ac, B=Bc, C=C, Qc=Qc, R=fit.R,
            state_names=tuple(f"x{i + 1}" for i in range(n)), input_names=names[0],
            output_names=names[1], fault_inputs=fault_inputs)
    except IdentifyError:
        raise
    except NUMERIC_FAILURES as exc:  # ModelError (a NaN noise intensity, say) included
        raise IdentifyError(f"{advice} ({one_line(exc, 100)})") from None
    extra = {
        "order_selection": {"holdout_fit_pct": {str(k): v for k, v in fit.holdout_fit.items()},
                            "bic": {str(k): v for k, v in fit.bic.items()},
                            "subspace_singular_values": fit.singular_values,
                            "selected": n, "given": order is not None,
                            "holdout_error_input_p": {str(k): v for k, v in
                                                      fit.holdout_input_p.items()},
                            "rule": "the lowest order whose hold-out simulation fit is "
                                    f"within {ORDER_MARGIN} points of the best"},
        "form": fit.form,
        "function_evaluations": fit.nfev,
    }
    return _Candidate("state_space", model, float(np.trace(Qc)) / n, n, None,
                      dict(fit.invariants), extra)


def _balanced_scale(Ac: Array, Bc: Array, C: Array, Qc: Array
                    ) -> tuple[Array, Array, Array, Array]:
    """The same model in states scaled so that each state's row of B and column of C have
    the same norm: x = S z with S diagonal gives S^-1 Ac S, S^-1 B, C S and S^-1 Qc S^-1.

    The fit's coordinates can leave B some 1e-4 and C some 1e2 (the subspace's state
    scale); the estimator's test that a loss shows in the outputs (the rank of
    [[A - I, B], [C, D]] against a tolerance relative to its largest entry) then calls a
    slow plant sampled fast unobservable (a smallest singular value of 1e-10 of the
    largest where the balanced states give 1e-4). A diagonal scale changes neither the
    input-output behaviour nor the filter: the estimator normalises each state by its own
    standard deviation."""
    b = np.linalg.norm(Bc, axis=1)
    c = np.linalg.norm(C, axis=0)
    ok = (b > 0) & (c > 0) & np.isfinite(b) & np.isfinite(c)
    s = np.where(ok, np.sqrt(np.where(ok, b, 1.0) / np.where(ok, c, 1.0)), 1.0)
    return (Ac * s[None, :] / s[:, None], Bc / s[:, None], C * s[None, :],
            Qc / np.outer(s, s))


def _black_box(u: Array, y: Array, ntr: int, T: float, order: int | None,
               names: tuple[tuple[str, ...], tuple[str, ...]]
               ) -> tuple[_Candidate, dict[str, Any], dict[str, Array]]:
    """The black box of the chosen order and its evaluation; where the estimator cannot
    run the chosen order (a spurious zero at DC hides the fault, say) and the order was not
    given, the next orders around it in turn: the first that serves, else the first
    refusal."""
    c = _fit_black_box(u, y, ntr, T, order, names)
    try:
        ev, tr = _evaluate(c.model, u, y, ntr, T)
        return c, ev, tr
    except IdentifyError as first:
        if order is not None:
            raise
        for n in (c.order - 1, c.order + 1, c.order - 2, c.order + 2):
            if not 1 <= n <= MAX_ORDER:
                continue
            try:
                other = _fit_black_box(u, y, ntr, T, n, names)
                ev, tr = _evaluate(other.model, u, y, ntr, T)
            except IdentifyError:
                continue
            other.extra["order_fallback"] = {"refused_order": c.order,
                                             "why": one_line(first, 300)}
            return other, ev, tr
        raise


def _friction_box(held: Array, y_held: Array, delay: int, ntr: int, T: float,
                  order: int | None, names: tuple[tuple[str, ...], tuple[str, ...]],
                  speed: str) -> tuple[_Candidate, dict[str, Any], dict[str, Array], Array,
                                       dict[str, Any]]:
    """The black box with Coulomb friction (`monitor.identify.friction`): the linear fit,
    then FRICTION_ITERATIONS refits with the friction's phi (from the previous model's
    filter) as a known last input. Returns the candidate (its model's last input the
    friction), its evaluation, traces, the held inputs with phi appended (rows as
    `held`) and the report's "friction" entry."""
    m = held.shape[1]
    u, y, _ = fit_rows(held, y_held, delay)
    cand = _fit_black_box(u, y, ntr, T, order, names)
    linear_fit = float(cand.extra["order_selection"]["holdout_fit_pct"][str(cand.order)])
    _, width = speed_estimate(cand.model, held, y_held, T, delay, speed)
    names_f = (names[0] + ("friction",), names[1])
    fits: list[float] = []
    held_f = held
    for _ in range(FRICTION_ITERATIONS):
        held_f = np.column_stack([held, friction_column(cand.model, m, held, y_held, T,
                                                        delay, speed, width)])
        u_f, y_f, _ = fit_rows(held_f, y_held, delay)
        cand = _fit_black_box(u_f, y_f, ntr, T, order, names_f,
                              fault_inputs=tuple(range(m)))
        fits.append(float(cand.extra["order_selection"]["holdout_fit_pct"][str(cand.order)]))
    u_f, y_f, _ = fit_rows(held_f, y_held, delay)
    ev, tr = _evaluate(cand.model, u_f, y_f, ntr, T)
    if ev["dc_gain"] is not None:  # the settled output's loss: the rig's inputs only
        ev["steady_state_loss"] = _steady_state_loss([row[:m] for row in ev["dc_gain"]],
                                                     u_f[:, :m], ev["innovation_std"])
    # the friction's own share of the output: the model's response to phi alone, its
    # standard deviation over the capture in innovation standard deviations
    A, B, _ = cand.model.discretize(T).at(T)
    share = dsim(A, B[:, m:], cand.model.C, u_f[:, m:])
    share_sd = np.std(share, axis=0) / np.asarray(ev["innovation_std"], dtype=float)
    info = {"speed": speed, "width": width, "iterations": FRICTION_ITERATIONS,
            "response_noise_units": float(np.max(share_sd)),
            "linear_holdout_fit_pct": linear_fit,
            "holdout_fit_pct_per_iteration": fits,
            # the share of the linear model's hold-out error that the friction removes
            "holdout_error_cut": (fits[-1] - linear_fit) / max(100.0 - linear_fit, 1e-9),
            "phi_mean": float(np.mean(held_f[:, m])),
            "phi_sign_changes": int(np.count_nonzero(np.diff(np.sign(held_f[:, m])))),
            "rule": "Coulomb friction b_f phi, phi = -tanh(v / width), v the model's "
                    "speed over the step; fitted by refitting with phi from the previous "
                    "model's filter"}
    return cand, ev, tr, held_f, info


LOAD_FIT_GAIN = 0.1
"""The load's refits stop once one improves the hold-out fit by less than this (points)."""

LOAD_INPUT_CORRELATION = 0.2
"""A load refit whose innovations correlate with the input by more than this is refused:
a load does not follow the command, a change of the input's effect does."""


def _load_box(u: Array, y: Array, ntr: int, T: float, order: int | None,
              names: tuple[tuple[str, ...], tuple[str, ...]]
              ) -> tuple[_Candidate, dict[str, Any], dict[str, Array], Array, dict[str, Any]]:
    """The black box with unmeasured load steps (`monitor.identify.load`): the linear fit,
    then refits on u + d, d from the previous model's filter, until d settles or a refit
    improves the hold-out fit by less than LOAD_FIT_GAIN (at most LOAD_ITERATIONS; the
    order chosen by the first refit, which the rest keep: a fit of one order instead of
    six, and no order hopping while the load settles). Returns the candidate, its
    evaluation and traces on u + d, u + d itself and the report's "load" entry. d is
    estimated over the whole capture, the hold-out part too: the monitor's bias states
    follow a load online the same way."""
    cand = _fit_black_box(u, y, ntr, T, order, names)
    linear_fit = float(cand.extra["order_selection"]["holdout_fit_pct"][str(cand.order)])
    fits: list[float] = []
    found: LoadSteps | None = None
    chosen = order  # the first refit chooses the order (unless given), the rest keep it
    selection: dict[str, Any] | None = None
    confirmed = order is not None
    for _ in range(LOAD_ITERATIONS):
        last, found = found, load_steps(cand.model, u, y, T)
        if last is not None and settled(last, found):
            if confirmed:
                break
            # settled at the order the first refit chose: chosen once more on the settled
            # load (a slow mode that carried the steps early on has given way), and the
            # iteration goes on at that order where it differs
            confirmed = True
            cand = _fit_black_box(u + found.d, y, ntr, T, None, names)
            fits.append(float(cand.extra["order_selection"]["holdout_fit_pct"][
                str(cand.order)]))
            selection = cand.extra["order_selection"]
            if cand.order == chosen:
                break
            chosen = cand.order
            continue
        cand = _fit_black_box(u + found.d, y, ntr, T, chosen, names)
        if chosen is None:
            chosen, selection = cand.order, cand.extra["order_selection"]
        fits.append(float(cand.extra["order_selection"]["holdout_fit_pct"][str(cand.order)]))
        if len(fits) > 1 and fits[-1] - fits[-2] < LOAD_FIT_GAIN:
            # the refits no longer improve the fit: more of them cost minutes at kHz rates
            # (the rig zoo's seed 41, 2 kHz: 10 minutes) and change nothing a check sees
            break
    assert found is not None
    if selection is not None:  # the refits after the first were of its order
        cand.extra["order_selection"] = selection
    u_d = u + found.d
    ev, tr = _evaluate(cand.model, u_d, y, ntr, T)
    info = {"changes": len(found.changes),
            "change_times_s": [round(r * T, 4) for r in found.changes],
            "levels": _floats(found.levels),
            "q_d": found.q_d, "refits": len(fits),
            # a load step of this share of the input's mean level looks like a loss of
            # that size until the input next changes
            "largest_step_of_input": _floats(
                np.max(np.abs(np.diff(found.levels, axis=0)), axis=0, initial=0.0)
                / np.maximum(np.mean(np.abs(u), axis=0), 1e-300)),
            "linear_holdout_fit_pct": linear_fit, "holdout_fit_pct_per_iteration": fits,
            "rule": "a piecewise-constant input bias d (y = G (u + d)): the augmented "
                    "model's RTS smoother, change points by binary segmentation, levels "
                    "(with a correction of the input's gain) by least squares on the "
                    "model's innovations, their count by BIC; refitted with u + d"}
    return cand, ev, tr, u_d, info


def _without_friction_input(model: ContinuousDescriptor, m: int, friction: Friction
                            ) -> ContinuousDescriptor:
    """The model whose last input (m, the friction's phi) becomes its `friction`."""
    return ContinuousDescriptor(
        E=model.E, A=model.A, B=model.B[:, :m], C=model.C, Qc=model.Qc, R=model.R,
        state_names=model.state_names, input_names=model.input_names[:m],
        output_names=model.output_names, D=model.D[:, :m],
        fault_inputs=tuple(a for a in model.faults if a < m),
        friction=replace(friction, B=model.B[:, m].copy()))


MOTOR_ADVICE = ("the DC-motor model needs the armature voltage as input and the armature "
                "current as output; for another plant use --model state_space")


def _evaluate(model: ContinuousDescriptor, u: Array, y: Array, ntr: int,
              T: float, advice: str = "ask for a larger order or another kind"
              ) -> tuple[dict[str, Any], dict[str, Array]]:
    """Simulation fit on training and hold-out, innovation tests on the hold-out."""
    try:
        dm = model.discretize(T)
    except ModelError as exc:
        # The model's own message whole: cut, it hides why (a fault that does not show).
        if "not observable" in str(exc):
            # too few states for the faulty inputs, or a zero at DC (a speed held by a
            # spring, a high-pass sensor), which no order removes: then it is the signals
            advice += ("; or, where the output does not answer a constant input (its "
                       "steady-state gain is zero), monitor an output that settles at a "
                       "level the input sets (a position, a current)")
        raise IdentifyError(f"the fitted model cannot serve the estimator ({one_line(exc, 400)}): "
                            f"{advice}") from exc
    A, B, Qd = dm.at(T)
    C, R = dm.C, dm.R
    kf = kalman(A, C, Qd, R)
    utr, ytr, uva, yva = u[:ntr], y[:ntr], u[ntr:], y[ntr:]
    # From the initial state that fits the training part best: a capture need not start at
    # rest (an integrator's has no rest), and the state is fitted on training samples only.
    ysim_tr = V.fitted_x0_sim(A, B, C, utr, ytr)
    x0 = steady_state_x0(A, B, C, utr[0], ytr[0])
    Ap = A - kf.K @ C
    n = A.shape[0]
    X = dsim(Ap, np.hstack([B, kf.K]), np.eye(n), np.hstack([utr, ytr]), x0)
    xs = Ap @ X[-1] + B @ utr[-1] + kf.K @ ytr[-1]
    ysim_va = dsim(A, B, C, uva, xs)
    e = predict(A, B, C, kf.K, uva, yva, xs)
    w = e @ np.linalg.inv(np.linalg.cholesky(kf.S)).T
    lam = _poles(dm)
    # An integrator's pole (fitted a hair off s = 0) is no time constant the capture must
    # span.
    integ = integrating(lam, ntr * T)
    stable = lam[(lam.real < -1e-12) & ~integ]
    tau = float(1.0 / np.min(-stable.real)) if stable.size else math.inf
    res: dict[str, Any] = {
        "fit": {"nrmse_holdout_pct": V.nrmse(yva, ysim_va),
                "nrmse_training_pct": V.nrmse(ytr, ysim_tr),
                "definition": "100 (1 - |y - y_sim| / |y - mean y|), simulation from the "
                              "Kalman state at the start of the hold-out"},
        "whiteness": V.whiteness_test(w),
        "cross_correlation": V.cross_correlation_test(w, uva),
        "mean_nis_kalman_holdout": float(np.mean(np.sum(w * w, axis=1))),
        "innovation_std": _floats(np.sqrt(np.diag(kf.S))),
        "slowest_time_constant_s": tau,
        "poles_continuous": [[float(z.real), float(z.imag)] for z in np.sort_complex(lam)],
        "dc_gain": None if integ.any() else _dc_gain(dm),
    }
    res["steady_state_loss"] = _steady_state_loss(res["dc_gain"], u, res["innovation_std"])
    t_va = np.asarray((ntr + np.arange(yva.shape[0])) * T, dtype=float)
    traces: dict[str, Array] = {"t_holdout": t_va, "y_holdout": yva, "y_sim": ysim_va}
    return res, traces


def _growing_input_share(dm: DiscreteModel, u: Array, y: Array, T: float, duration: float
                         ) -> tuple[complex, float] | None:
    """The growing mode of the part of `dm` the outputs see (a continuous pole with a
    positive real part that is no integrator over `duration`, `integrating`) whose
    response to the capture's input u moves an output the most, as that pole and the
    peak-to-peak of the response over the peak-to-peak of the measured output y; None
    without a growing mode. Modal: x_i(k+1) = z_i x_i(k) + g_i u(k), y_i = (C v_i) x_i,
    from rest (a conjugate pair's responses summed)."""
    ss = dm.standard
    A = dm.Wobs @ ss.A @ dm.Wobs.T
    B = dm.Wobs @ ss.B
    lam, V = np.linalg.eig(A)
    grows = (lam.real > 0.0) & ~integrating(lam, duration)
    if not grows.any():
        return None
    W = np.linalg.inv(V)
    swing = np.ptp(y, axis=0)
    swing = np.where(swing > 0, swing, 1.0)
    worst: tuple[complex, float] | None = None
    for i in np.flatnonzero(grows):
        z = np.exp(lam[i] * T)
        drive = u @ (W[i] @ B * (z - 1.0) / lam[i])  # the zero-order hold's input gain
        x = scipy.signal.lfilter([0.0, 1.0], [1.0, -z], drive)
        resp = np.outer(x, dm.C @ V[:, i])
        resp = resp.real * (2.0 if abs(lam[i].imag) > 0 else 1.0)
        share = float(np.max(np.ptp(resp, axis=0) / swing))
        if worst is None or share > worst[1]:
            worst = (complex(lam[i]), share)
    return worst


def _shown_offset(rest: Array, settled: NDArray[np.bool_], y: Array, tail: slice) -> Array:
    """Per output, the offset of the data's own line through the model's settled response:
    the intercept c of y = s r + c over the samples of the stretch `tail` where the
    model's response from rest r (`rest`) has settled (`settled`, a mask per sample and
    output), as far as the capture shows it: the least |c| of OFFSET_STRETCHES stretches
    where all have one sign (a sign test: were the median 0, all of 8 would share a sign
    with chance 2^-7, 0.8 %, and the median is at least the least), 0 otherwise.

    A fit that averages a limit into its gain leaves no offset of its own (the rig zoo's
    seed 52: a second-order speed, the top level of two clipped by 5 %, fitted through
    zero at 97 %): the data keep it, a fraction of a noise unit on the capture that the
    monitor's bias state takes up, and runs at other levels meet the model up to a noise
    unit wrong (the mismatch flag up 69 % of a healthy run, 14 false alarms). The slope s
    takes the fit's gain error, so only what no line through zero gives is left. Settled
    samples only: within the transients a slightly wrong pole leaves errors that a line
    through r takes partly as an offset (a quantised first-order plant read 8 noise units
    that way). Stretches, since a slow mode's wander under process noise also moves a
    stretch's intercept (the paper's motor: -2 to 8 noise units from stretch to stretch);
    a sign test rather than the stretches' mean, since one stretch can be far off (the
    zoo's seed 85: seven at -1.2 to -3.4, one at -71)."""
    N, p = y.shape
    shown = np.zeros(p)
    for i in range(p):
        cs = []
        for rows in np.array_split(np.arange(N)[tail], OFFSET_STRETCHES):
            rows = rows[settled[rows, i]]
            r = rest[rows, i]
            if r.size < 8:
                continue
            upper = r > 0.5 * (float(np.min(r)) + float(np.max(r)))
            if min(int(np.sum(upper)), int(np.sum(~upper))) < max(4, r.size // 10):
                continue  # a line through one level's samples is no line
            X = np.column_stack([rest[rows, i], np.ones(rows.size)])
            coef, *_ = np.linalg.lstsq(X, y[rows, i], rcond=None)
            cs.append(float(coef[1]))
        # the sign test's bound on the median: all of them one sign has chance 2^(1 - n)
        # if the median is 0 (0.8 % for 8), and then the median is at least the least
        if len(cs) == OFFSET_STRETCHES and (min(cs) > 0.0 or max(cs) < 0.0):
            shown[i] = min(abs(c) for c in cs)
    return shown


def _limit_ambiguity(dm: DiscreteModel, u: Array, y: Array, m: int, T: float,
                     innovation_std: Sequence[float], dc_gain: list[Any] | None
                     ) -> tuple[float, float, float, bool] | None:
    """Whether a two-level capture hides an actuator limit behind a gain and an offset.

    With an input that took two levels a and b alone, a limit L of the actuator between
    |a| and |b| (|u| clipped at L: the rig zoo's saturation, a drive's current or voltage
    limit) makes the output's levels g a and g clip(b), which a line s u + c through the
    two levels fits as well as g u: the capture cannot tell the limit from a smaller gain
    s with an offset c. The offset is what gives it away, since a model through zero
    (the monitor's models have no offsets) fits only through zero; the fit carries it
    anyway, on the initial state of a slow or growing mode or on a friction's constant
    term (the rig zoo's seeds 200 and 6). If it is a limit, a run at a level between the
    two meets the model wrong by g (clip(b) - a)(b - clip(b)) / (b - a) at the knee, which
    is c (clip(b) - a) / a, at most |c| |b - a| / |a| and at most the output's swing.

    c is the larger of two offsets. The model's own: the median, over the capture's last
    three quarters (past the start's transient), of its simulation from the initial state
    that fits the capture (with every input: a friction's phi, a further input of `dm`,
    adds its constant) less its response from rest to the rig's first m inputs. And the
    data's, where a fit through zero averaged the limit into its gain and carries no offset
    (`_shown_offset`): not the median of the output less the model's response, which also
    holds the fit's gain error, process noise's wander and the residue of the samples'
    timing (the paper's motor and a quantised first-order plant read 1-8 noise units that
    way), but the intercept of a line through the model's response, as far as the capture
    shows it at 99 % confidence.
    Where the output does not settle at a level the input sets (the model's DC gain
    `dc_gain` moves the settled output by less than LIMIT_NOISE innovation standard
    deviations between the two levels: a speed held by a spring, a high-pass sensor), no
    offset shows either: every change of the input is a step of b - a, whose response a
    limit only makes smaller, so nothing in the capture tells the limit from a smaller
    gain (the rig zoo's seed 39: a false alarm in a healthy run with the limit, none
    re-made without it). Then it is `blind`.

    Only for one input (m == 1) whose two levels differ in size (||b| - |a|| above a tenth
    of |b - a|: a limit clips both of +-A alike, as a smaller gain through zero). Returns
    the largest such error over the outputs, in innovation standard deviations, the two
    levels and whether the capture is blind to a limit; None where the check does not
    apply."""
    if m != 1:
        return None
    col = u[:, 0]
    if V.level_count(col) != 2:
        return None
    a, b = float(np.min(col)), float(np.max(col))
    if abs(a) > abs(b):
        a, b = b, a  # a: the level of the smaller size, the one a limit leaves alone
    if abs(abs(b) - abs(a)) <= 0.1 * abs(b - a) or a == 0.0:
        return None
    A, B, _ = dm.at(T)
    rest = dsim(A, B[:, :m], dm.C, u[:, :m])
    tail = slice(y.shape[0] // 4, None)
    # the model's own offset: its simulation from the initial state that fits the
    # capture, with every input (a friction's phi too), less its response from rest to the
    # rig's inputs; what a slow mode's initial state or a friction's constant adds
    own = V.fitted_x0_sim(A, B, dm.C, u, y) - rest
    c = np.abs(np.median(own[tail], axis=0))
    sd = np.asarray(innovation_std, dtype=float)
    if dc_gain is not None:
        # the model's response within a noise unit of where it settles at each input level
        final = np.outer(col, np.asarray(dc_gain, dtype=float)[:, 0])
        c = np.maximum(c, _shown_offset(rest, np.abs(rest - final) < sd, y, tail))
    error = np.minimum(c * abs(b - a) / abs(a), np.ptp(y, axis=0))
    # below LIMIT_SHARE of the output's swing an error is within a fit's own gain error
    error = np.where(error > LIMIT_SHARE * np.ptp(rest[tail], axis=0), error, 0.0)
    worst = float(np.max(error / sd))
    blind = False
    if dc_gain is not None:
        settled = np.abs(np.asarray(dc_gain, dtype=float)[:, 0]) * abs(b - a)
        blind = bool(np.all(settled / sd < LIMIT_NOISE))
    return worst, a, b, blind


def _poles(dm: DiscreteModel) -> Array:
    """Continuous poles of the part of the model the outputs see."""
    return np.asarray(np.linalg.eigvals(dm.Wobs @ dm.standard.A @ dm.Wobs.T))


def _steady_state_loss(dc_gain: list[Any] | None, u: Array, innovation_std: list[float]
                       ) -> dict[str, Any]:
    """How far a total loss of each actuator moves the settled outputs, at the capture's
    input level, in units of the innovations' standard deviation: per input j,
    max_i |G0_ij| rms(u_j) / std_i (G0 the model's DC gain). A loss gamma at a constant
    input shows at steady state as gamma times this. Near zero, the output does not settle
    at a level the input sets (a speed held by a spring, a high-pass sensor): a loss then
    shows only in the transients after the input changes, so gamma^ learns nothing while
    the input holds and whatever the model misses there (an input frame's timing,
    friction at a reversal) is read as a loss. None for a model with an integrator (its
    output ramps under a loss: observable)."""
    out: dict[str, Any] = {"per_input": None, "input_rms": _floats(np.sqrt(np.mean(u**2, axis=0))),
                           "definition": "max over outputs of |dc_gain| rms(input) / "
                                         "innovation std: the settled output's change under a "
                                         "total loss of the input, in noise units"}
    if dc_gain is None:
        return out
    G0 = np.abs(np.asarray(dc_gain, dtype=float))
    sd = np.asarray(innovation_std, dtype=float)[:, None]
    out["per_input"] = _floats(np.max(G0 * np.asarray(out["input_rms"])[None, :] / sd, axis=0))
    return out


def _dc_gain(dm: DiscreteModel) -> list[Any] | None:
    """The model's DC gain, None for a model with an integrator (it has none)."""
    try:
        return _floats(dm.dc_gain)
    except np.linalg.LinAlgError:
        return None


def quantisation_floor(R: ArrayLike, steps: Sequence[float | None]) -> Array:
    """R (p x p, per sample) with the variance of each output i whose step is known raised
    to step_i^2 / 12 where it lies below (`QUANTISATION_VARIANCE`).

    An output decoded from whole counts of `step` carries at least that much noise, so an R
    below it (a fit that gave the rounding to the process noise) makes the estimator trust
    a measurement more than the sensor resolves: its estimate of y follows y, and the NIS
    is inflated by the rounding it was not told about. Raising diagonal entries adds a
    positive semidefinite matrix: a symmetric positive definite R stays so, its covariances
    kept. A step of None (a float-coded signal, or no rig to say) leaves its output as it
    is."""
    out = np.array(R, dtype=float, copy=True)
    if out.ndim != 2 or out.shape[0] != out.shape[1] or out.shape[0] != len(steps):
        raise ValueError(f"R of shape {out.shape} for {len(steps)} output step(s)")
    out = 0.5 * (out + out.T)
    for i, step in enumerate(steps):
        if step is not None:
            out[i, i] = max(out[i, i], QUANTISATION_VARIANCE * float(step) ** 2)
    return out


def _floored(cand: _Candidate, steps: Sequence[tuple[float, str] | None],
             names: Sequence[str], u: Array, y: Array, T: float
             ) -> tuple[_Candidate, list[dict[str, Any]]]:
    """The candidate with its R floored at each output's quantisation
    (`quantisation_floor`) and, where the floor applied, its Qc scaled to the likelihood's
    best with that R on the training rows u, y (`monitor.identify.noise`: the rounding the
    fit gave the process noise leaves it), and a report entry per output whose step is
    known."""
    learned = np.asarray(cand.model.R, dtype=float)
    R = quantisation_floor(learned, [None if s is None else s[0] for s in steps])
    rows = [{"output": names[i], "step": float(s[0]), "source": s[1],
             "learned": float(learned[i, i]), "floor": QUANTISATION_VARIANCE * float(s[0]) ** 2,
             "applied": bool(R[i, i] > learned[i, i])}
            for i, s in enumerate(steps) if s is not None]
    if not any(r["applied"] for r in rows):
        return cand, rows
    model = replace(cand.model, R=R)
    scale = process_noise_scale(model, u, y, T)
    return replace(cand, model=replace(model, Qc=scale * np.asarray(model.Qc)),
                   q=cand.q * scale), rows


def nis_calibrated(ident: Identification, mean_nis: float,
                   steps: Sequence[float | None]) -> Identification:
    """`ident` with its process and output noise (Qc, q, R) scaled by s = `mean_nis` / p,
    the mean NIS the monitor's own filter gave on the capture per output (p of them), where
    that lies below 1: the filter the monitor runs (gamma^ of (51), the bias states)
    explains the capture better than the steady-state Kalman filter the noise was fitted
    with, and its innovations are smaller than Q and R say. Scaling both by one factor
    leaves the linear filter's gain as it is (the Riccati solution scales with them) and
    divides the NIS by it: the consistency tuning of a Kalman filter by its NIS (Bar-Shalom,
    Li and Kirubarajan, Estimation with Applications to Tracking and Navigation, 2001, 5.4).
    R stays at or above each output's quantisation (`quantisation_floor`). The report's
    noise entry says so (``calibrated``)."""
    p = np.asarray(ident.R).shape[0]
    s = float(mean_nis) / p
    if not (math.isfinite(s) and 0.0 < s < 1.0):
        raise ValueError(f"mean NIS {mean_nis!r} is not below the {p} output(s)")
    R = quantisation_floor(s * np.asarray(ident.R, dtype=float), steps)
    model = replace(ident.model, Qc=s * np.asarray(ident.model.Qc, dtype=float), R=R)
    report = dict(ident.report)
    report["noise"] = {**report.get("noise", {}), "q": ident.q * s, "Qc": _floats(model.Qc),
                       "R": _floats(R),
                       "calibrated": {"replay_mean_nis": float(mean_nis), "scale": s,
                                      "q_fitted": ident.q, "R_fitted": _floats(ident.R)}}
    return replace(ident, model=model, q=ident.q * s, Qc=model.Qc, R=R, report=report)


def _fuzzy_ukf(model: ContinuousDescriptor, held: Array, y: Array, ntr: int,
               T: float, delay: int) -> dict[str, Any]:
    """The monitor's own filter on the capture's rows (held inputs, outputs), paired as the
    monitor pairs them with input delay `delay`: mean NIS and gamma^ on the hold-out (the
    rows from `ntr`)."""
    est = FuzzyUKF(model.discretize(T))
    N = held.shape[0]
    u, _ = delayed(held, delay, no_past(held.shape[1]))
    nis = np.empty(N)
    gam = np.empty((N, u.shape[1]))
    for k in range(N):
        out = est.step(u[k], y[k], T)
        nis[k] = out.nis
        gam[k] = out.gamma
    return {"mean_nis_holdout": float(np.mean(nis[ntr:])),
            "gamma_mean_holdout": _floats(np.mean(gam[ntr:], axis=0)),
            "gamma_max_holdout": _floats(np.max(gam[ntr:], axis=0)),
            "structure_events": int(est.structure_events)}


def _consistency(cand: _Candidate, u: Array, y: Array, T: float) -> list[float]:
    """`validate.consistency_drop` of the candidate's structure fitted on each half; for a
    model with an integrator the simulations are compared without offset and ramp."""
    N = u.shape[0]
    trend = bool(np.any(integrating(_poles(cand.model.discretize(T)), N * T / 2)))
    h = N // 2
    halves = ((u[:h], y[:h]), (u[h:], y[h:]))
    fits = []
    for uu, yy in halves:
        if cand.motor is not None:
            fits.append(oe_refit(uu, yy, T, cand.motor))
        else:
            sub, _ = subspace_model(uu, yy, cand.order)
            fits.append((sub.A, sub.B, sub.C))
    return V.consistency_drop(fits[0], fits[1], halves, trend)


def identify(
    u: ArrayLike,
    y: ArrayLike,
    T: float,
    *,
    kind: str = "auto",
    order: int | None = None,
    holdout: float = 0.3,
    template: DCMotorParameters | None = None,
    input_names: Sequence[str] | None = None,
    output_names: Sequence[str] | None = None,
    run_filter: bool = True,
    input_delay: int | None = None,
    output_steps: Sequence[tuple[float, str] | None] | None = None,
    friction: str | None = None,
    load: bool = False,
) -> Identification:
    """Identify a model of one node from a healthy capture of inputs u (N, m) and outputs
    y (N, p) sampled every T seconds.

    Row k is an output sample with the inputs held at it (`monitor.pipeline.samples`: the
    latest of each received before, or with, the output). `input_delay` is the monitor's
    delay d, None to estimate it (`monitor.identify.delay`, 0..MAX_ESTIMATED_DELAY, on the
    training part); the model is fitted for the monitor's rule with that d: the state
    equation's input v(j) is the held input of row j + 1 - d (`fit_rows`, rows without a
    partner dropped), so the estimator's step for sample k, which applies v(k-1), gets the
    held input of sample k - d, as the monitor gives it.

    kind: "dc_motor" (the Table-1 structure, m = p = 1), "state_space" (black box of
    `order` states, or the lowest of 1..6 that simulates the hold-out about as well as
    the best) or "auto" (the DC motor when m = p = 1 and its residuals are independent of
    the input, else the better hold-out fit of the two; the black box for other shapes).
    The last `holdout` fraction of the capture is not used for fitting: the fit,
    whiteness and cross-correlation figures are measured on it.
    `template` gives J (not identifiable from current) and the fallback initial guess.
    `run_filter` runs the FuzzyUKF over the capture for the report (about 10 us a sample).
    `output_steps` gives, per output, the step its values come in and where that is known
    from (a rig signal's scale: `monitor.bus.rigcodec.output_quantisation`), None where it
    is not (a float-coded signal): the learned R is floored at step^2 / 12
    (`quantisation_floor`) before the model is evaluated, so every figure of the report is
    the returned model's.
    `friction` ("output": the output is a speed; "rate": a position; None: none) fits the
    black box with Coulomb friction (`monitor.estimation.friction`, `_friction_box`), of one
    output only; the model's `friction` then holds it and the report's "friction" says how.
    `load` fits the black box with unmeasured load steps (`monitor.identify.load`, `_load_box`):
    a piecewise-constant input bias estimated from the model's filter and added to the
    input for the fit and every check; the model written lacks it (the monitor's bias
    states carry a load at run time) and the report's "load" says what was found.

    report keys: fit (hold-out and training NRMSE %, by simulation), whiteness (innovation
    autocorrelation, 99 % band, Ljung-Box p), cross_correlation (innovation x input, band,
    joint chi-square p), parameters (value and std; black box: DC gain and poles with std),
    identifiable / fixed (motor), noise (q, Qc, R; with output_steps, R_learned and
    quantisation_floor: per output with a known step, its step, source, floor, learned R and
    whether the floor applied), mean_nis_kalman_holdout, fuzzy_ukf (its
    mean NIS and gamma^ on the hold-out), consistency (halves NRMSE drop), excitation,
    order_selection (black box), dc_gain, steady_state_loss (per input, a total loss's
    change of the settled outputs in innovation standard deviations; None with an
    integrator), poles_continuous, auto, seconds, timing_s,
    input_delay (samples, given or estimated, with each candidate's ARX loss and F-test p).

    Raises IdentifyError (one line: what to record instead) for a capture that is too
    short, not exciting enough, contains non-finite samples or shows a fault or outage.
    """
    t0 = time.perf_counter()
    # One BLAS thread (the brief's one core; threads only slow the tiny matrices down);
    # overflow in a trial step of an optimiser is caught by the finiteness checks.
    with threadpool_limits(limits=1, user_api="blas"), np.errstate(over="ignore",
                                                                   invalid="ignore"):
        try:
            ident = _identify(u, y, T, kind, order, holdout, template or DCMotorParameters(),
                              input_names, output_names, run_filter, input_delay,
                              output_steps, friction, load)
        except IdentifyError:
            raise
        except NUMERIC_FAILURES as exc:  # a degenerate record no check above foresaw
            raise IdentifyError(
                f"the identification failed numerically ({one_line(exc, 100)}): the capture "
                f"does not describe a linear plant driven by its input; {RECORDING_ADVICE}"
            ) from None
    ident.report["seconds"] = time.perf_counter() - t0
    return ident


def _identify(u_in: ArrayLike, y_in: ArrayLike, T: float, kind: str, order: int | None,
              holdout: float, template: DCMotorParameters, input_names: Sequence[str] | None,
              output_names: Sequence[str] | None, run_filter: bool,
              input_delay: int | None = None,
              output_steps: Sequence[tuple[float, str] | None] | None = None,
              friction: str | None = None, load: bool = False,
              ) -> Identification:
    requested = kind
    if kind not in KINDS:
        raise IdentifyError(f"kind must be one of {', '.join(KINDS)}, got {kind!r}")
    if order is not None and not (isinstance(order, int) and 1 <= order <= MAX_ORDER):
        raise IdentifyError(f"order must be an integer from 1 to {MAX_ORDER} (the estimator's "
                            f"fuzzy rule base spans the state: 5^n rules), got {order!r}")
    held, y_held = V.check_capture(np.asarray(u_in), np.asarray(y_in), T, holdout)
    delay = _input_delay(held, y_held, holdout, input_delay)
    u, y, rows = fit_rows(held, y_held, delay["samples"])
    N, m = u.shape
    p = y.shape[1]
    siso = m == 1 and p == 1
    if kind == "dc_motor" and not siso:
        raise IdentifyError(f"the DC-motor model has one input (voltage) and one output "
                            f"(current), the capture has {m} and {p}: use kind state_space")
    names = (tuple(input_names) if input_names else
             (("u1",) if siso else tuple(f"u{j + 1}" for j in range(m))),
             tuple(output_names) if output_names else
             (("y1",) if siso else tuple(f"y{i + 1}" for i in range(p))))
    if len(names[0]) != m or len(names[1]) != p:
        raise IdentifyError(f"{len(names[0])} input and {len(names[1])} output names for "
                            f"{m} inputs and {p} outputs")
    steps = list(output_steps) if output_steps is not None else [None] * p
    if len(steps) != p or not all(s is None or (math.isfinite(s[0]) and s[0] > 0)
                                  for s in steps):
        raise IdentifyError(f"output_steps must give {p} positive steps or None, got "
                            f"{output_steps!r}")
    ntr = N - round(holdout * N)
    utr, ytr = u[:ntr], y[:ntr]
    timing: dict[str, float] = {}
    t = time.perf_counter()
    excitation = V.check_excitation(utr, 2 if kind != "state_space" or order is None
                                    else order, names[0])
    V.check_holdout_changes(u, ntr, names[0])
    V.check_outputs(y, names[1])
    cands: list[tuple[_Candidate, dict[str, Any], dict[str, Array]]] = []
    auto_note: dict[str, Any] = {}
    motor_failed: str | None = None
    if kind == "dc_motor" or (kind == "auto" and siso):
        try:
            c = _fit_motor(utr, ytr, T, template, names)
            ev, tr = _evaluate(c.model, u, y, ntr, T, MOTOR_ADVICE)
        except (IdentifyError, *NUMERIC_FAILURES) as exc:
            if kind != "auto":
                raise
            # auto tries the motor first; a plant it cannot describe (issue 16) is the
            # black box's: said in one line once the black box has served, or in the
            # black box's own refusal
            motor_failed = one_line(exc, 160)
            auto_note["dc_motor_failed"] = one_line(exc, 400)
        else:
            cands.append((c, ev, tr))
            auto_note["dc_motor_nrmse_holdout_pct"] = ev["fit"]["nrmse_holdout_pct"][0]
            if kind == "auto" and ev["cross_correlation"]["passed"] and \
                    ev["fit"]["nrmse_holdout_pct"][0] >= V.MIN_FIT:
                auto_note["reason"] = "dc_motor residuals independent of the input"
                kind = "dc_motor"
    friction_info: dict[str, Any] | None = None
    load_info: dict[str, Any] | None = None
    if friction is not None:
        if kind != "state_space" or p != 1:
            raise IdentifyError("friction is fitted for a state_space model of one output")
        c, ev, tr, held, friction_info = _friction_box(held, y_held, delay["samples"], ntr, T,
                                                       order, names, friction)
        cands.append((c, ev, tr))
        # every figure below is the friction model's, its phi a known input
        u, y, rows = fit_rows(held, y_held, delay["samples"])
        utr, ytr = u[:ntr], y[:ntr]
    elif load:
        if kind != "state_space" or m != 1:
            raise IdentifyError("a load is fitted for a state_space model of one input")
        c, ev, tr, u, load_info = _load_box(u, y, ntr, T, order, names)
        worst = float(np.max(np.abs(ev["cross_correlation"]["correlation"])))
        load_info["innovation_input_correlation"] = worst
        if worst > LOAD_INPUT_CORRELATION:
            # steps placed to follow the input stand in for a change of its effect: a loss
            # in the middle of a capture gave 0.51, a load's refit 0.05
            raise PlantChangeError(
                f"the load steps a refit finds follow the input (its innovations correlate "
                f"with the input by up to {worst:.2f}): the input's effect changes within "
                "the capture (a fault or outage?); record a capture of the healthy node only")
        cands.append((c, ev, tr))
        # every figure below is the model's with the load added to its input
        held = held.copy()
        first = rows.start + 1 - delay["samples"]
        held[first:first + u.shape[0]] = u
        utr = u[:ntr]
    elif kind == "state_space" or kind == "auto":
        try:
            c, ev, tr = _black_box(u, y, ntr, T, order, names)
        except IdentifyError as exc:
            if motor_failed is None:
                raise
            raise IdentifyError(f"{exc} (the DC-motor model did not fit either: "
                                f"{motor_failed})") from None
        cands.append((c, ev, tr))
        auto_note["state_space_nrmse_holdout_pct"] = float(np.mean(ev["fit"]["nrmse_holdout_pct"]))
    best = max(cands, key=lambda c: float(np.mean(c[1]["fit"]["nrmse_holdout_pct"])))
    if kind == "auto" and "reason" not in auto_note:
        auto_note["reason"] = "better hold-out fit" if siso else "more than one input or output"
    cand, ev, traces = best
    learned_R, learned_q = cand.model.R, cand.q
    # the model written is the one every check below, and the replay's, must judge
    cand, floor = _floored(cand, steps, names[1], utr, ytr, T)
    if cand is not best[0]:
        ev, traces = _evaluate(cand.model, u, y, ntr, T)
    timing["fit"] = time.perf_counter() - t

    # Refusals after the fit: a change inside the capture first (it spoils every figure).
    # what the refit measured of a friction stands whatever refuses its model (the
    # friction probe of `identify` weighs it), and so does the order the data chose
    with carrying_fit(friction_info,
                      cand.order if cand.kind == "state_space" and order is None else None):
        t = time.perf_counter()
        drops = _consistency(cand, u, y, T)
        timing["consistency"] = time.perf_counter() - t
        fit_tr = min(ev["fit"]["nrmse_training_pct"])
        fit_va = min(ev["fit"]["nrmse_holdout_pct"])
        # A structure too small for the plant also fits the halves differently, but far less
        # so than a fault does.
        if fit_tr < V.MIN_FIT and not ev["cross_correlation"]["passed"] and \
                max(drops) < V.STRUCTURE_DROP:
            if cand.kind != "state_space":
                advice = "try --model state_space"
            elif order is None:  # the data chose it: no larger one fitted much better
                advice = (f"no larger order fitted the hold-out more than {ORDER_MARGIN} "
                          f"points better: {RECORDING_ADVICE}")
            else:
                advice = "try a larger --order"
            raise IdentifyError(
                f"the {cand.kind} model of order {cand.order} does not fit (training fit "
                f"{fit_tr:.0f} %, residuals correlated with the input): {advice}")
        if max(drops) > V.CONSISTENCY_DROP:
            half = "first" if drops[0] < drops[1] else "second"
            # what changes is not told by the drop: a fault, and as often a load that steps
            # or a friction the linear model takes differently at each half's inputs (the
            # rig zoo's healthy captures 53, 61, 82, 90)
            raise PlantChangeError(
                f"the halves of the capture fit different models (the plant or its load "
                f"changes within it: a fault, an outage, load steps, friction?): the model of "
                f"the {half} half fits the other half {max(drops):.0f} points worse than its "
                f"own; {ONE_CONDITION_ADVICE}")
        if fit_va < fit_tr - V.HOLDOUT_DROP:
            raise PlantChangeError(
                f"the hold-out fit ({fit_va:.0f} %) is far below the training fit "
                f"({fit_tr:.0f} %): the plant or its load changes near the end of the capture "
                f"(a fault, an outage, a load step?); {ONE_CONDITION_ADVICE}")
        ambiguous = _limit_ambiguity(cand.model.discretize(T), u, y, m, T, ev["innovation_std"],
                                     ev["dc_gain"])
        if ambiguous is not None and ambiguous[3]:
            _, a, b, _ = ambiguous
            raise IdentifyError(
                f"the input took two levels alone ({a:.4g} and {b:.4g}) and the output does not "
                "settle at a level the input sets (a speed held by a spring?): every change is "
                "a step of one size, and nothing in the capture tells an actuator limit at the "
                "larger level from a smaller gain; record steps between several levels (random "
                "steps or a multi-level PRBS) inside the actuator's range")
        if ambiguous is not None and ambiguous[0] > LIMIT_NOISE:
            # a limit at the larger level of two looks like a smaller gain plus an offset (the
            # rig zoo's seed 200: fit 98 %, fresh runs at other levels with the mismatch flag
            # up 97 % of the time and false alarms); no fit of these two levels tells them
            # apart, a friction's refit neither (its constant is the offset): said before a
            # growing mode, which is one way a fit carries it
            worst, a, b, _ = ambiguous
            raise IdentifyError(
                f"the input took two levels alone ({a:.4g} and {b:.4g}) and the output's levels "
                f"are not in their ratio: an actuator limit at the larger, friction or a sensor "
                f"offset, which two levels cannot tell apart (up to {worst:.2g} noise units "
                "wrong at other levels); record steps between several levels (random steps or "
                "a multi-level PRBS) inside the actuator's range")
        grown = _growing_input_share(cand.model.discretize(T), u, y, T, ntr * T)
        if grown is not None and grown[1] > MAX_GROWING_SHARE:
            # After the refusals of a plant that changes within the capture: its fit can
            # leave an integrator a little unstable, and the change is what to say. No
            # healthy drive's current, speed or position grows by itself. A fit makes such a
            # slow mode to carry what a linear model through zero lacks. An offset alone rides
            # on its initial state (harmless: a sensor offset with friction gave one whose
            # input drives 0.05 % of the output's swing). One the input drives stands in for a
            # gain the capture does not show: an actuator that saturates at one level of a
            # two-level input looks like a smaller gain plus an offset; the estimator's state
            # of that mode then takes up part of every loss, and a fresh run at other input
            # levels meets the true gain (the rig zoo's seed 6: 25 % of the swing; accepted
            # at order 5, false alarms in a healthy run and a loss of 0.3 read as 0.2).
            z, share = grown
            raise GrowingModeError(
                f"the fitted model has a growing mode (a pole at s = {z.real:.3g}"
                f"{f' +- {abs(z.imag):.3g}j' if z.imag else ''} 1/s) that the input drives "
                f"({100 * share:.2g} % of the output's swing over the capture); no healthy drive "
                "has one: it stands in for a nonlinearity the linear model lacks (an actuator "
                "that saturates, friction); record with the input stepped between several "
                "levels (not two) inside the actuator's range, or try another --order")
        # the capture must span the slowest time constant the fit resolves; an integrator's
        # pole (`integrating`) is none
        lam = np.array([complex(re, im) for re, im in ev["poles_continuous"]])
        tau = V.resolved_time_constant([[z.real, z.imag] for z in lam[~integrating(lam, ntr * T)]],
                                       cand.params.get("poles_real"),
                                       cand.params.get("poles_real_std"))
        if math.isfinite(tau) and ntr * T < V.MIN_TIME_CONSTANTS * tau:
            need = V.MIN_TIME_CONSTANTS * tau / (1.0 - holdout)
            raise SlowModeError(
                f"capture too short for this plant (slowest time constant {tau:.3g} s): record "
                f"at least {need:.3g} s with the input varying")
        if fit_tr < V.MIN_FIT:
            raise IdentifyError(
                f"not exciting enough: the input moves the output too little against its noise "
                f"(training fit {fit_tr:.0f} %): {RECORDING_ADVICE}, with larger steps")

    report: dict[str, Any] = {
        "kind": cand.kind,
        "order": cand.order,
        "T": T,
        "samples": N,
        "duration_s": N * T,
        "holdout_fraction": holdout,
        "training_samples": ntr,
        "inputs": list(names[0]),
        "outputs": list(names[1]),
        "parameters": cand.params,
        "noise": {"q": cand.q, "Qc": _floats(cand.model.Qc), "R": _floats(cand.model.R),
                  "method": "maximum likelihood of the steady-state Kalman filter's "
                            "innovations (noise model (1)-(2)); mean NIS = p at the optimum",
                  **({"R_learned": _floats(learned_R), "q_learned": learned_q,
                      "quantisation_floor": floor,
                      "quantisation_rule": "R[i][i] >= step_i^2 / 12, the variance of "
                                           "rounding to whole steps (Widrow)"}
                     if floor else {})},
        "excitation": excitation,
        "consistency": {"halves_nrmse_drop_pct": drops, "threshold": V.CONSISTENCY_DROP},
        **ev,
        **cand.extra,
    }
    report["input_delay"] = delay
    model = cand.model
    if friction_info is not None:
        report["friction"] = friction_info
        report["inputs"] = list(names[0])
        model = _without_friction_input(model, m, Friction(
            B=np.zeros(0), speed=friction_info["speed"], output=0,
            width=friction_info["width"]))
        friction_info["B"] = _floats(model.friction.B if model.friction else np.zeros(0))
    if load_info is not None:
        report["load"] = load_info
    if requested == "auto":
        report["auto"] = auto_note
    if run_filter:
        t = time.perf_counter()
        report["fuzzy_ukf"] = _fuzzy_ukf(model, held[:, :m], y_held, rows.start + ntr, T,
                                         delay["samples"])
        timing["fuzzy_ukf"] = time.perf_counter() - t
    report["timing_s"] = timing
    if motor_failed is not None:
        _log.warning("auto: %s; the black box is used", motor_failed)
    return Identification(model=model, q=cand.q, Qc=model.Qc, R=model.R, T=T,
                          kind=cand.kind, order=cand.order, motor=cand.motor, report=report,
                          traces=traces, input_delay=delay["samples"])


def _input_delay(held: Array, y: Array, holdout: float, given: int | None) -> dict[str, Any]:
    """The input delay to fit for, `given` or estimated on the training rows, as the
    report gives it."""
    if given is not None:
        if isinstance(given, bool) or not isinstance(given, int) or \
                not 0 <= given <= MAX_INPUT_DELAY:
            raise IdentifyError(f"input_delay must be a whole number of samples from 0 to "
                                f"{MAX_INPUT_DELAY}, got {given!r}")
        return {"samples": given, "given": True}
    ntr = held.shape[0] - round(holdout * held.shape[0])
    try:
        est = estimate_input_delay(held[:ntr], y[:ntr], MAX_ESTIMATED_DELAY)
    except ValueError as exc:
        raise IdentifyError(f"{exc}: {RECORDING_ADVICE}") from None
    return {"samples": est.delay, "given": False, "placed": est.placed,
            "arx_loss": {str(d): v for d, v in est.loss.items()},
            "p_value": {str(d): v for d, v in est.p_value.items()},
            "method": "ARX models of every candidate delay on the training rows, nested "
                      "(the same last input tap); the largest delay whose dropped input "
                      "taps an F-test does not find, 0 when no candidate's dropped taps "
                      "matter (placed false: the response's start is not seen)"}
