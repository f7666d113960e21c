"""Self-constructing fuzzy system (15)-(29): partition, inference, insertion, projection."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from monitor.estimation.fuzzy import FuzzyConfig, SelfConstructingFuzzySystem, memberships


@pytest.fixture(scope="module")
def compiled_memberships() -> None:
    """Compile `memberships` (a numba kernel) for the argument types the property uses
    (float, float64 array, int) before it runs: the first call compiles, 0.3-1 s, which
    hypothesis would otherwise time as that of its first example."""
    memberships(0.5, np.array([0.0, 1.0]), 2)


# deadline=None as well: each example takes microseconds once compiled, but a loaded machine
# can stall any one of them past hypothesis' 200 ms default; timing is not what this
# property tests.
@pytest.mark.usefixtures("compiled_memberships")
@settings(deadline=None)
@given(
    centres=st.lists(st.floats(-10, 10, allow_nan=False), min_size=1, max_size=7, unique=True),
    z=st.floats(-20, 20, allow_nan=False),
)
def test_memberships_form_a_partition_of_unity(centres: list[float], z: float) -> None:
    cs = np.array(sorted(centres))
    if len(cs) > 1 and np.min(np.diff(cs)) < 1e-6:
        return
    _j0, _j1, m0, m1 = memberships(z, cs, len(cs))
    assert m0 + m1 == pytest.approx(1.0)
    assert 0 <= m0 <= 1 and 0 <= m1 <= 1
    # triangular: the MF of a centre is 1 at the centre
    for j, c in enumerate(cs):
        a0, a1, w0, w1 = memberships(float(c), cs, len(cs))
        assert (a0 == j and w0 == pytest.approx(1.0)) or (a1 == j and w1 == pytest.approx(1.0))


def _system(seed: int, n_inputs: int = 2) -> SelfConstructingFuzzySystem:
    rng = np.random.default_rng(seed)
    fz = SelfConstructingFuzzySystem(n_inputs, 2, FuzzyConfig(max_mf=6, min_spacing=0.2))
    fz.cons[:] = rng.uniform(0, 1, fz.cons.shape)
    return fz


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 10_000), n_inputs=st.integers(1, 3))
def test_basis_functions_sum_to_one_and_output_is_weighted_mean(seed: int, n_inputs: int) -> None:
    fz = _system(seed, n_inputs)
    rng = np.random.default_rng(seed + 1)
    for _ in range(20):
        z = rng.uniform(-8, 8, n_inputs)
        xi = fz.basis(z)
        assert sum(xi.values()) == pytest.approx(1.0)
        expect = sum(w * fz.cons[j] for j, w in xi.items())
        assert fz.evaluate(z) == pytest.approx(expect)  # (17)


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 10_000), n_inputs=st.integers(1, 3))
def test_insertion_leaves_output_unchanged_everywhere(seed: int, n_inputs: int) -> None:
    fz = _system(seed, n_inputs)
    rng = np.random.default_rng(seed + 2)
    probes = rng.uniform(-8, 8, (200, n_inputs))
    before = np.array([fz.evaluate(z) for z in probes])
    rules = fz.rule_count
    inserted = 0
    for _ in range(4):
        v = int(rng.integers(n_inputs))
        if fz.insert(v, float(rng.uniform(-7, 7)), new_variance=0.3):
            inserted += 1
    after = np.array([fz.evaluate(z) for z in probes])
    assert after == pytest.approx(before, abs=1e-12)  # (23)-(27)
    assert fz.rule_count >= rules
    assert fz.insertions == inserted


def test_growth_is_bounded_by_count_and_spacing() -> None:
    fz = SelfConstructingFuzzySystem(1, 1, FuzzyConfig(initial_mf=((0.0,),), max_mf=3,
                                                       min_spacing=1.0))
    assert fz.rule_count == 1
    assert not fz.insert(0, 0.5, 0.1)  # too close to 0
    assert fz.insert(0, 2.0, 0.1)
    assert fz.insert(0, -2.0, 0.1)
    assert not fz.insert(0, 4.0, 0.1)  # bound reached
    assert fz.rule_count == 3
    assert list(fz.centres[0, :3]) == [-2.0, 0.0, 2.0]


def test_rule_count_is_product_of_mf_counts() -> None:
    fz = SelfConstructingFuzzySystem(2, 1, FuzzyConfig(initial_mf=((-3.0, 3.0), (0.0,))))
    assert fz.rule_count == 2  # the paper's Fig. 3 starts with two rules
    fz.insert(1, 2.0, 0.1)
    assert fz.rule_count == 4
    fz.insert(0, 0.0, 0.1)
    assert fz.rule_count == 6
