"""The fuzzy UKF's flat buffers, defined once: a named table of fields per buffer.

The step kernel (`monitor.estimation.kernel`) runs on flat float64 buffers allocated once
per estimator, so that a sample allocates nothing:

* `MODEL`: one block per distinct step dt, the ZOH model (63)-(65) of the filter's state,
  followed in the same block by its `FRICTION` (`monitor.estimation.friction`).
* `PRM`: the scalars of a sample (dt, the sigma-point weights (33)-(43), the tuning, the
  per-actuator bounds of (28)).
* `STATE`: the filter's state between samples; followed in the same buffer by the onset
  ring, ``ring_len`` slots of `RING` (one per sample, read by the structure event (20)).
* `OUT`: what a sample gives (`EstimatorOutput` views into it), `WORK` its scratch.

Each field is (name, dims), dims the factors of its size: "n" (the filter's states), "m"
(actuators), "p" (outputs) or a number; two dims make a row-major matrix. Every offset
derives from these tables: the kernel's views (through `offsets`, passed to it as one
int64 array), the estimator's views (`Table.view`), the ring slot's size that sizes the
estimator (`monitor.estimation.model.estimator_bytes`), and `KERNEL_LAYOUT`, the number an
ahead-of-time build of the kernel exports and `select_kernel` checks. Pure Python: the model
check sizes the estimator without importing numba.
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = [
    "FRICTION",
    "KERNEL_LAYOUT",
    "MODEL",
    "OUT",
    "PRM",
    "RING",
    "STATE",
    "TABLES",
    "UKF_SCRATCH",
    "WORK",
    "Table",
    "layout_number",
    "offsets",
]


class Table:
    """The fields of one flat buffer, in order (see the module docstring)."""

    def __init__(self, name: str, fields: Sequence[tuple[str, ...]], base: int) -> None:
        self.name = name
        self.fields: tuple[tuple[str, tuple[str, ...]], ...] = tuple(
            (f[0], tuple(f[1:])) for f in fields)
        self.names = tuple(f[0] for f in self.fields)
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"layout {name}: a field name is repeated")
        self.base = base
        """Where this table's offsets start in the array `offsets` returns."""

    def __len__(self) -> int:
        return len(self.fields)

    def at(self, name: str) -> int:
        """The index of field `name`'s start in the array `offsets` returns (its end is the
        next entry)."""
        return self.base + self.names.index(name)

    def at_each(self, *names: str) -> tuple[int, ...]:
        """`at` of each of `names`, in their order."""
        return tuple(self.at(name) for name in names)

    def shape(self, name: str, n: int, m: int, p: int) -> tuple[int, ...]:
        dims = {"n": n, "m": m, "p": p}
        spec = self.fields[self.names.index(name)][1]
        return tuple(dims[d] if d in dims else int(d) for d in spec)

    def starts(self, n: int, m: int, p: int) -> IntArray:
        """The offset of every field and, last, the buffer's size."""
        sizes = [int(np.prod(self.shape(f, n, m, p))) for f in self.names]
        return np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)

    def size(self, n: int, m: int, p: int) -> int:
        return int(self.starts(n, m, p)[-1])

    def span(self, name: str, n: int, m: int, p: int) -> tuple[int, int]:
        """(start, end) of field `name` within the buffer."""
        s = self.starts(n, m, p)
        i = self.names.index(name)
        return int(s[i]), int(s[i + 1])

    def view(self, buf: Array, name: str, n: int, m: int, p: int) -> Array:
        """Field `name` of `buf` (a view, reshaped to its dims)."""
        a, b = self.span(name, n, m, p)
        return buf[a:b].reshape(self.shape(name, n, m, p))


UKF_SCRATCH: tuple[tuple[str, ...], ...] = (
    ("L", "n", "n"), ("d", "n"), ("xp", "n"), ("Pp", "n", "n"), ("Ls", "p", "p"), ("s", "n"),
    ("dy", "p"), ("Pyy", "p", "p"), ("Pyy_inv", "p", "p"), ("Pxy", "n", "p"), ("K", "n", "p"),
    ("IKC", "n", "n"), ("T1", "n", "n"))
"""The scratch arrays of `ukf.ukf_predict` and `ukf.ukf_update` (n states, p outputs), in
every filter that runs them (`WORK`; the augmented KF of `experiments.akf`)."""


def _tables() -> tuple[Table, ...]:
    specs: list[tuple[str, list[tuple[str, ...]]]] = [
        # the ZOH model of one step (63)-(65), as `FuzzyUKF._block` packs it
        ("MODEL", [("A", "n", "n"), ("B", "n", "m"), ("Q", "n", "n"), ("C", "p", "n"),
                   ("D", "p", "m"), ("R", "p", "p")]),
        # delta, wi: the sigma-point spread (33) and weight (42)-(43); nis_coef: the weight of
        # the innovation average; mode 0: no structure test, 1: test, 2: a structure event at
        # the start of the sample; slot: the sample's place in the onset ring; lower, upper:
        # the bounds of (28) (lower == upper: a known actuator); noise_coef: the forgetting
        # weight of the adaptive output noise (0: the model's R); slow_ratio, slow_threshold:
        # the slow average's window as a power of the innovation average's weight, and its
        # threshold (`monitor.estimation.kernel`, step 5); process_coef: the learning weight
        # of the adaptive process noise (0: the model's Q; step 5c)
        ("PRM", [("dt", "1"), ("delta", "1"), ("wi", "1"), ("q_gamma", "1"),
                 ("var_max", "1"), ("nis_coef", "1"), ("var_reopen", "1"),
                 ("nis_threshold", "1"), ("mode", "1"), ("growth_share", "1"), ("slot", "1"),
                 ("var_rule", "1"), ("lower", "m"), ("upper", "m"), ("noise_coef", "1"),
                 ("slow_ratio", "1"), ("slow_threshold", "1"), ("process_coef", "1")]),
        # x^, P, V = d x^ / d gamma, the averaged fuzzy input z, the consequents' common
        # variance vc (per actuator), the adapted output-noise excess rx (per output), the
        # log of the adapted process-noise scale qs, the previous whitened innovation w and
        # w's long-run mean
        ("STATE", [("x", "n"), ("P", "n", "n"), ("V", "n", "m"), ("z", "n"), ("vc", "m"),
                   ("rx", "p"), ("qs", "1"), ("w_prev", "p"), ("w_mean", "p")]),
        # one sample of the onset ring: the state before it (x, P, V, z, the innovation
        # average, gamma^, vc), the sample (u, y, dt), the filter's view of it under the old
        # fault (K, S_tot^-1, nu), the adapted noises and the slow average before it
        ("RING", [("x", "n"), ("P", "n", "n"), ("V", "n", "m"), ("z", "n"), ("ebar", "p"),
                  ("gamma", "m"), ("vc", "m"), ("u", "m"), ("y", "p"), ("dt", "1"),
                  ("K", "n", "p"), ("Sti", "p", "p"), ("nu", "p"), ("rx", "p"),
                  ("ebar_slow", "p"), ("gamma_slow", "m"), ("var_slow", "p"), ("qs", "1"),
                  ("w_prev", "p"), ("w_mean", "p")]),
        # stats: [NIS, test statistic, Cholesky repairs, structure test fired (1: the short
        # average, 2: the slow one alone)]; gamma_sd: the standard deviation of gamma^ after
        # the sample (what the diagnosis weighs it by); ebar_slow: the slow average of the
        # innovation as gamma^'s slow average gamma_slow would have left it, and var_slow the
        # long-run mean of its square; output_noise: each output's noise variance as the
        # filter adapted it, a multiple of the model's, (R_ii + rx_i) / R_ii (1 where R_ii is
        # 0); process_noise: the factor exp(qs) on the plant's part of Q. Both after the
        # sample's adaptation (steps 5b, 5c): the noises the next sample's filter uses
        ("OUT", [("gamma", "m"), ("fault", "n"), ("x_tilde", "n"), ("x_e", "n"),
                 ("y_hat", "p"), ("innovation", "p"), ("stats", "4"), ("ebar", "p"),
                 ("y_est", "p"), ("gamma_sd", "m"), ("ebar_slow", "p"),
                 ("gamma_slow", "m"), ("var_slow", "p"), ("output_noise", "p"),
                 ("process_noise", "1")]),
        ("WORK", [("uf", "m"), ("dg", "m"), ("pg", "m"), ("b", "n"), ("xq", "n"),
                  ("yoff", "p"), ("nu", "p"), ("Pq", "n", "n"), ("St", "p", "p"),
                  ("Sti", "p", "p"), ("Vp", "n", "m"), ("M", "p", "m"), ("Ra", "p", "p"),
                  ("w_slow", "p"), ("Qa", "n", "n"),
                  *UKF_SCRATCH]),
        # the Coulomb friction of one step (`monitor.estimation.friction`), packed into the
        # model block after MODEL's fields: the step's column of phi, the speed's row over
        # the states and [code, width] (code 0: none). Last of the tables, so that adding
        # it moved no offset of the others: numba's cache keeps a module's compiled
        # functions, with the offsets they read frozen in, until that module's own file
        # changes (a layout module edited alone leaves them stale)
        ("FRICTION", [("F", "n"), ("S", "n"), ("fr", "2")]),
    ]
    out: list[Table] = []
    base = 0
    for name, fields in specs:
        out.append(Table(name, fields, base))
        base += len(fields) + 1
    return tuple(out)


TABLES = _tables()
MODEL, PRM, STATE, RING, OUT, WORK, FRICTION = TABLES


def offsets(n: int, m: int, p: int) -> IntArray:
    """Every table's `Table.starts`, one after the other: the int64 array the kernel takes
    its views by (field f of table T spans ``[T.at(f)]`` to ``[T.at(f) + 1]``)."""
    return np.concatenate([t.starts(n, m, p) for t in TABLES]).astype(np.int64)


# What the buffers mean beyond their fields' order and sizes (bump it when that changes:
# 10 added OUT's output_noise and process_noise, the adapted noises as factors on the
# model's; 9 added the adaptive process noise; 8 added the structure test's slow average
# and its stats[3] = 2; 7 added the FRICTION table after the model block; 6, the layout of
# these tables; 5 added the bias states after the plant's in x, P, V, z).
_SEMANTICS = 10



def layout_number(tables: Sequence[Table]) -> int:
    """The semantics version and a checksum of the tables' names and fields."""
    return _SEMANTICS * 2**32 + zlib.crc32(repr([(t.name, t.fields) for t in tables]).encode())


KERNEL_LAYOUT: int = layout_number(TABLES)
"""The buffer layout the kernel reads, so that an ahead-of-time build of another layout,
which has the same signature but would misread the buffers, is refused
(`monitor.estimation.kernel.select_kernel`)."""
