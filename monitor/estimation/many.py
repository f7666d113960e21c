"""Many samples of one estimator in one compiled loop: `FuzzyUKF.step_many`, bit-identical to
`FuzzyUKF.step` row by row (the same kernel, eqs (50)-(54) around (15)-(49) of Liu, Bao,
Xue, Du, Int. J. Fuzzy Systems 22(1), 2020), for a replay's columns."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from monitor.estimation.kernel import step_loop
from monitor.estimation.state import FilterState

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["ManyStepping", "ManySteps"]


@dataclass
class ManySteps:
    """What `step_many` ran: samples [0, count) of its input, per sample gamma^ (count, m)
    and its standard deviation gamma_sd (count, m), the output estimate y_est (count, p),
    the NIS, the rule count after the sample and whether a structure-learning event
    followed it, the adapted noise factors output_noise (count, p) and process_noise
    (count,) (`EstimatorOutput`). `stopped_on_nan`: sample count - 1 gave a NaN gamma^ (the
    caller restarts the estimator, as the pipeline does)."""

    count: int
    gamma: Array
    y_est: Array
    nis: Array
    rules: IntArray
    structure_event: NDArray[np.bool_]
    stopped_on_nan: bool
    gamma_sd: Array
    output_noise: Array
    process_noise: Array


class ManyStepping(FilterState):
    """The fuzzy UKF's many samples in one compiled loop, a method of the filter
    (`monitor.estimation.fuzzy_ukf.FuzzyUKF` inherits it)."""

    def step_many(self, u: Array, y: Array, dt: Array) -> ManySteps:
        """`self.step(u[i], y[i], dt[i])` for every row i, with the same results, the samples
        stepped in one compiled loop (`step_loop`: the same kernel, eqs (50)-(54) around
        (15)-(49)) that returns to Python only when the structure test (20) fires (the onset
        search and re-processing, `monitor.estimation.structure.structure_event`) and stops at
        a NaN gamma^.
        Without the JIT (AOT or interpreted kernel) it calls `self.step` row by row. Leaves
        `self` as the last `step` would, `self.out` included.
        """
        N = int(u.shape[0])
        n, m, p = self._dims
        gamma = np.zeros((N, m))
        gamma_sd = np.zeros((N, m))
        y_est = np.zeros((N, p))
        nis = np.zeros(N)
        rules = np.zeros(N, np.int64)
        event = np.zeros(N, np.bool_)
        output_noise = np.zeros((N, p))
        process_noise = np.zeros(N)

        def ran(count: int, stopped_on_nan: bool) -> ManySteps:
            return ManySteps(count, gamma, y_est, nis, rules, event, stopped_on_nan, gamma_sd,
                             output_noise, process_noise)

        def record(i: int, nis_i: float) -> bool:
            """Row i from `self.out` (what `step` left); whether its gamma^ is NaN."""
            out = self.out
            gamma[i] = out.gamma
            gamma_sd[i] = out.gamma_sd
            y_est[i] = out.y_est
            output_noise[i] = out.output_noise
            process_noise[i] = out.process_noise[0]
            nis[i] = nis_i
            rules[i] = out.rules
            return bool(out.gamma.max() != out.gamma.max())

        if N == 0:
            return ran(0, False)
        if np.any(~(dt > 0.0)):
            raise ValueError(f"dt must be positive, got {dt[~(dt > 0.0)][0]}")
        if self.kernel_name != "jit":
            for i in range(N):
                out = self.step(u[i], y[i], float(dt[i]))
                event[i] = out.structure_event
                if record(i, out.nis):
                    return ran(i + 1, True)
            return ran(N, False)
        U = np.ascontiguousarray(u, dtype=np.float64)
        Y = np.ascontiguousarray(y, dtype=np.float64)
        dts = np.ascontiguousarray(dt, dtype=np.float64)
        first = 0
        if self._needs_init:  # the start (`start_state`) and the first sample, as step() does
            out = self.step(U[0], Y[0], float(dts[0]))
            event[0] = out.structure_event
            first = 1
            if record(0, out.nis):
                return ran(1, True)
            if N == 1:
                return ran(1, False)
        uniq, inv = np.unique(dts, return_inverse=True)
        entries = []
        for d in uniq.tolist():
            blk = self._blocks.get(d)
            entries.append(blk if blk is not None else self._block(d))
        blocks = np.ascontiguousarray(np.stack([e[0] for e in entries]))
        coefs = np.array([e[1] for e in entries])
        bidx = inv.astype(np.int64).reshape(-1)
        clock = np.array([self._time, self._last_event, 0.0, float(self.steps)])
        fz = self.fuzzy
        cfg = self.config
        i = first
        nan = False
        while i < N:
            start = i
            i = step_loop(blocks, coefs, bidx, dts, U, Y, self._prm, self._st, fz.centres,
                          fz.counts, fz.cons, fz.var, fz.rule_idx, fz.rule_w, self._wk, self._out,
                          self._lay, n, m, p, fz.max_mf, clock, cfg.dwell, self._ring_len, start,
                          gamma, y_est, nis, gamma_sd, output_noise, process_noise)
            rules[start:i] = self.out.rules
            self._time = float(clock[0])
            self.out.structure_event = False
            if clock[2] == 1.0:  # the test fired on sample i - 1: the event, as in step()
                self.steps = int(clock[3])
                self._u[:] = U[i - 1]
                self._y[:] = Y[i - 1]
                if self._structure_event():
                    self.out.structure_event = True
                    self.out.rules = fz.rule_count
                    event[i - 1] = True
                # the event may have re-processed: the output of sample i - 1 is the new one
                nan = record(i - 1, float(self._stats[0]))
                clock[1] = self._last_event
                clock[3] += 1.0
            elif clock[2] == 2.0:
                nan = True
            if nan:
                break
        self.steps = int(clock[3])
        self.out.nis = float(nis[i - 1])
        self._u[:] = U[i - 1]
        self._y[:] = Y[i - 1]
        return ran(i, nan)
