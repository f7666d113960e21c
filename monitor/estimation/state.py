"""The fuzzy UKF's state as its parts see it: `FilterState` declares, for the type checker,
what `monitor.estimation.fuzzy_ukf.FuzzyUKF.__init__` sets up, so that the parts of the
filter written in modules of their own (`structure.StructureLearning`,
`many.ManyStepping`) are methods of the filter reading its own state, not functions reading
another object's private members."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from monitor.estimation.fuzzy import SelfConstructingFuzzySystem
    from monitor.estimation.fuzzy_ukf import EstimatorOutput, FuzzyUKFConfig
    from monitor.estimation.model import BiasPlan

__all__ = ["FilterState"]

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


class FilterState:
    """The attributes and methods of `FuzzyUKF` its parts use (declarations only)."""

    if TYPE_CHECKING:
        config: FuzzyUKFConfig
        fuzzy: SelfConstructingFuzzySystem
        bias_plan: BiasPlan
        out: EstimatorOutput
        kernel_name: str
        x: Array
        P: Array
        V: Array
        z: Array
        common_var: Array
        noise_excess: Array
        _process_log_scale: Array
        _w_prev: Array
        _w_mean: Array
        steps: int
        structure_events: int
        bias_events: int
        _dims: tuple[int, int, int]
        _nx: int
        _known: list[int]
        _faulty: list[int]
        _faulty_idx: IntArray
        _lay: IntArray
        _prm: Array
        _st: Array
        _wk: Array
        _out: Array
        _ring: Array
        _ring_len: int
        _lower: Array
        _upper: Array
        _zall: Array
        _ebar: Array
        _ebar_slow: Array
        _gamma_slow: Array
        _var_slow: Array
        _bias_var0: Array
        _u: Array
        _y: Array
        _time: float
        _last_event: float
        _onset_floor: int
        _bias_armed_until: float

        def _field(self, k: int, name: str) -> Array: ...
        def _block(self, dt: float) -> tuple[Array, float]: ...
        def _matrices(self, dt: float) -> tuple[Array, Array, Array, Array, Array]: ...
        def _run(self, k: int, dt: float, mode: float) -> None: ...
        _needs_init: bool
        _blocks: dict[float, tuple[Array, float]]
        _stats: Array

        def step(self, u: Sequence[float] | Array | float, y: Sequence[float] | Array | float,
                 dt: float) -> EstimatorOutput: ...
        def _structure_event(self) -> bool: ...
