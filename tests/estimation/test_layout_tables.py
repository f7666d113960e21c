"""The fuzzy UKF's flat buffers are defined once (`monitor.estimation.layout`): the tables
tile their buffers, the estimator's views and the compiled kernel read the same places, and
the layout number follows the tables."""

from __future__ import annotations

import numpy as np
import pytest

from monitor.estimation import layout
from monitor.estimation.fuzzy_ukf import FuzzyUKF
from monitor.estimation.kernel import kernel_layout
from monitor.estimation.model import ContinuousDescriptor, dc_motor, estimator_bytes


@pytest.mark.parametrize(("n", "m", "p"), [(1, 1, 1), (3, 2, 2), (5, 3, 4)])
def test_tables_tile_their_buffers(n: int, m: int, p: int) -> None:
    lay = layout.offsets(n, m, p)
    for table in layout.TABLES:
        buf = np.arange(table.size(n, m, p), dtype=np.float64)
        seen = np.concatenate([table.view(buf, f, n, m, p).ravel() for f in table.names])
        assert np.array_equal(seen, buf)  # in order, no gap, no overlap
        for f in table.names:
            a, b = table.span(f, n, m, p)
            assert (lay[table.at(f)], lay[table.at(f) + 1]) == (a, b)
    assert estimator_bytes(n, m, p, 0.01, onset_window=0.0)[1] == 8 * layout.RING.size(n, m, p)


def _multi_output() -> ContinuousDescriptor:
    return ContinuousDescriptor(
        E=np.eye(2), A=np.array([[-2.0, 0.5], [0.3, -3.0]]),
        B=np.array([[1.0, 0.4, 0.2], [0.1, 0.3, 1.0]]), C=np.eye(2),
        D=np.array([[0.05, 0.0, 0.0], [0.0, 0.0, 0.02]]), Qc=np.eye(2) * 0.01,
        R=np.eye(2) * 0.01, state_names=("a", "b"), fault_inputs=(0, 2))


@pytest.mark.parametrize("model", [dc_motor(), _multi_output()], ids=["dc_motor", "3in2out"])
def test_the_kernel_writes_where_the_estimator_reads(model: ContinuousDescriptor) -> None:
    # The kernel's own output y^ = C x^ + D u (1 - gamma^), read through the estimator's
    # views of x^ and gamma^ (the tables): a kernel that took another field for either, or
    # wrote y_est elsewhere, fails this.
    md = model.discretize(0.01)
    est = FuzzyUKF(md, x0=[0.0] * md.n_full)
    rng = np.random.default_rng(1)
    u = rng.uniform(1.0, 5.0, md.m)
    for _ in range(30):
        out = est.step(u, md.C @ est.out.x_hat + rng.normal(0.0, 0.1, md.p), 0.01)
        nx = md.n
        Ca = est._matrices(0.01)[3]
        want = Ca @ est.x + md.D @ (u * (1.0 - out.gamma))
        assert np.allclose(out.y_est, want, rtol=1e-12, atol=1e-12)
        assert np.array_equal(out.x_hat, est.x[:nx])
    assert est.steps == 30


def test_the_layout_number_follows_the_tables() -> None:
    assert kernel_layout() == layout.KERNEL_LAYOUT == layout.layout_number(layout.TABLES)
    # reordering two fields changes it, so that an ahead-of-time build of the old order is
    # refused (`select_kernel`)
    w = layout.WORK
    swapped = layout.Table(w.name, [(f, *d) for f, d in (w.fields[1], w.fields[0],
                                                          *w.fields[2:])], w.base)
    other = [swapped if t is w else t for t in layout.TABLES]
    assert layout.layout_number(other) != layout.KERNEL_LAYOUT
