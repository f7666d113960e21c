"""`monitor.identify.lti.dsim`, the compiled record simulation every fit repeats, against
scipy.signal.dlsim (the library's Python loop of the same recursion)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

from monitor.identify.lti import dsim


@pytest.mark.parametrize(("n", "m", "p"), [(1, 1, 1), (3, 2, 1), (4, 1, 2), (6, 3, 3)])
def test_dsim_is_scipys_dlsim(n: int, m: int, p: int) -> None:
    rng = np.random.default_rng(n + 10 * m)
    M = rng.normal(size=(n, n))
    A = 0.98 * M / max(abs(np.linalg.eigvals(M)))
    B, C = rng.normal(size=(n, m)), rng.normal(size=(p, n))
    u, x0 = rng.normal(size=(500, m)), rng.normal(size=n)
    _, ref, _ = scipy.signal.dlsim((A, B, C, np.zeros((p, m)), 1.0), u, x0=x0)
    np.testing.assert_allclose(dsim(A, B, C, u, x0), ref, rtol=1e-12, atol=1e-12)
    # from rest when no initial state is given; non-contiguous views are taken as they are
    _, rest, _ = scipy.signal.dlsim((A, B, C, np.zeros((p, m)), 1.0), u)
    np.testing.assert_allclose(dsim(A.T.T, B, C, np.asfortranarray(u)), rest,
                               rtol=1e-12, atol=1e-12)


def test_dsim_refuses_shapes_that_do_not_fit() -> None:
    # the compiled loop does not check indices: a wrong width must not read past an array
    with pytest.raises(ValueError, match="do not fit"):
        dsim(np.eye(2), np.ones((2, 2)), np.ones((1, 2)), np.ones((5, 1)))
    with pytest.raises(ValueError, match="do not fit"):
        dsim(np.eye(2), np.ones((2, 1)), np.ones((1, 3)), np.ones((5, 1)))
