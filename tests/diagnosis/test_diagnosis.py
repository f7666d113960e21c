"""Tests for monitor.diagnosis: fuzzy c-means (55)-(62), thresholds and (76) classification."""

from __future__ import annotations

import itertools
import math
import tomllib
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy.stats import chi2

from monitor.diagnosis import (
    DEFAULT_THRESHOLDS,
    DiagnosisError,
    FCMResult,
    HealthState,
    MismatchDetector,
    OnlineClassifier,
    Thresholds,
    calibrate,
    classify,
    fcm_memberships,
    fuzzy_c_means,
    load_thresholds,
    rules,
    save_thresholds,
    thresholds_from_clusters,
    transitions,
)
from monitor.diagnosis.rules import chi2_quantile

FF, FAULT, OUTAGE, NO_DATA = (
    HealthState.FAULT_FREE,
    HealthState.FAULT,
    HealthState.OUTAGE,
    HealthState.NO_DATA,
)


def three_regimes(
    rng: np.random.Generator,
    sizes: tuple[int, int, int] = (1000, 1000, 1000),
    levels: tuple[float, float, float] = (0.0, 0.4, 1.0),
    sigma: float = 0.02,
) -> np.ndarray:
    return np.concatenate(
        [rng.normal(level, sigma, n) for level, n in zip(levels, sizes, strict=True)]
    )


# --------------------------------------------------------------------------------------
# Fuzzy c-means
# --------------------------------------------------------------------------------------

finite_data = hnp.arrays(
    np.float64,
    st.integers(3, 60),
    elements=st.floats(-100.0, 100.0, allow_nan=False, allow_infinity=False, width=32),
)


@settings(max_examples=200, deadline=None)
@given(data=finite_data, m=st.floats(1.05, 5.0), n_clusters=st.integers(2, 3))
def test_memberships_sum_to_one(data: np.ndarray, m: float, n_clusters: int) -> None:
    assume(np.unique(data).size >= n_clusters)
    r = fuzzy_c_means(data, n_clusters=n_clusters, m=m, max_iter=200)
    u = r.memberships
    assert u.shape == (n_clusters, data.size)
    assert np.all(np.isfinite(u))
    assert np.all((u >= 0.0) & (u <= 1.0))
    np.testing.assert_allclose(u.sum(axis=0), 1.0, rtol=0, atol=1e-12)  # (59)
    assert np.all(np.diff(r.centres) >= 0.0)
    assert np.all(np.isfinite(r.centres))
    slack = 1e-12 * (data.max() - data.min())  # centres are convex combinations (57)
    assert data.min() - slack <= r.centres[0] and r.centres[-1] <= data.max() + slack
    assert math.isfinite(r.objective) and r.objective >= 0.0


@settings(max_examples=200, deadline=None)
@given(
    points=hnp.arrays(np.float64, st.integers(1, 30), elements=st.floats(-10, 10, width=32)),
    centres=hnp.arrays(
        np.float64, st.integers(1, 4), elements=st.floats(-10, 10, width=32), unique=True
    ),
    m=st.floats(1.01, 10.0),
    pick=st.integers(0, 3),
)
def test_fcm_memberships_property(
    points: np.ndarray, centres: np.ndarray, m: float, pick: int
) -> None:
    # Put one point exactly on a centre: distance 0 must give membership 1, not NaN.
    points = np.append(points, centres[pick % centres.size])
    u = fcm_memberships(points, centres, m)
    assert np.all(np.isfinite(u))
    np.testing.assert_allclose(u.sum(axis=0), 1.0, rtol=0, atol=1e-12)
    assert u[pick % centres.size, -1] == 1.0


def test_points_on_centres_get_full_membership() -> None:
    r = fuzzy_c_means([0.0, 0.0, 0.0, 0.4, 1.0, 1.0])
    np.testing.assert_array_equal(r.centres, [0.0, 0.4, 1.0])
    np.testing.assert_array_equal(
        r.memberships, [[1, 1, 1, 0, 0, 0], [0, 0, 0, 1, 0, 0], [0, 0, 0, 0, 1, 1]]
    )
    assert r.objective == 0.0


def reference_fcm_loop(
    x: list[float], centres: list[float], m: float, iterations: int
) -> tuple[list[float], list[list[float]]]:
    """Textbook FCM (Bezdek), written with plain loops, independent of the module."""
    c = list(centres)
    n_c = len(c)

    def memberships(c: list[float]) -> list[list[float]]:
        u = [[0.0] * len(x) for _ in range(n_c)]
        for k, xk in enumerate(x):
            d = [abs(xk - ci) for ci in c]
            for i in range(n_c):
                total = 0.0
                for j in range(n_c):
                    total += (d[i] / d[j]) ** (2.0 / (m - 1.0))  # (58)
                u[i][k] = 1.0 / total
        return u

    for _ in range(iterations):
        u = memberships(c)
        c = [
            sum(u[i][k] ** m * x[k] for k in range(len(x)))
            / sum(u[i][k] ** m for k in range(len(x)))  # (57)
            for i in range(n_c)
        ]
    return c, memberships(c)


@pytest.mark.parametrize("m", [1.5, 2.0, 3.0])
def test_agrees_with_loop_reference(m: float) -> None:
    rng = np.random.default_rng(11)
    x = three_regimes(rng, sizes=(60, 40, 30), sigma=0.05)
    init = [0.1, 0.5, 0.9]
    r = fuzzy_c_means(x, m=m, tol=1e-13, max_iter=5000, init_centres=init)
    assert r.converged
    c_ref, u_ref = reference_fcm_loop(x.tolist(), init, m, iterations=300)
    np.testing.assert_allclose(r.centres, c_ref, rtol=0, atol=1e-6)
    np.testing.assert_allclose(r.memberships, np.array(u_ref), rtol=0, atol=1e-6)


@pytest.mark.parametrize("m", [1.5, 2.0, 3.0])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_agrees_with_scikit_fuzzy(m: float, seed: int) -> None:
    cluster = pytest.importorskip("skfuzzy.cluster")
    rng = np.random.default_rng(100 + seed)
    x = three_regimes(rng, sizes=(200, 150, 100), sigma=0.05)
    r = fuzzy_c_means(x, m=m, tol=1e-13, max_iter=5000)
    centres, u, *_ = cluster.cmeans(x[np.newaxis, :], 3, m, 1e-13, 10000, seed=seed)
    order = np.argsort(centres.ravel())
    np.testing.assert_allclose(r.centres, centres.ravel()[order], rtol=0, atol=1e-6)
    np.testing.assert_allclose(r.memberships, u[order], rtol=0, atol=1e-6)


def test_centres_are_a_fixed_point_of_57_58() -> None:
    rng = np.random.default_rng(5)
    x = three_regimes(rng, sigma=0.05)
    r = fuzzy_c_means(x, m=2.0, tol=1e-13, max_iter=5000)
    np.testing.assert_allclose(r.memberships, fcm_memberships(x, r.centres, 2.0), atol=1e-13)
    w = r.memberships**2.0
    np.testing.assert_allclose(r.centres, (w @ x) / w.sum(axis=1), rtol=0, atol=1e-10)


def test_reproducible_and_order_independent() -> None:
    rng = np.random.default_rng(6)
    x = three_regimes(rng, sizes=(500, 200, 300))
    a = fuzzy_c_means(x)
    b = fuzzy_c_means(x)
    np.testing.assert_array_equal(a.centres, b.centres)
    np.testing.assert_array_equal(a.memberships, b.memberships)
    p = rng.permutation(x.size)
    c = fuzzy_c_means(x[p])
    np.testing.assert_allclose(c.centres, a.centres, rtol=0, atol=1e-9)
    np.testing.assert_allclose(c.memberships, a.memberships[:, p], rtol=0, atol=1e-9)


def test_imbalanced_run_finds_the_small_clusters() -> None:
    # Long fault-free period, short fault and outage: quantile init alone would split the
    # fault-free cluster; the range initialisation and the lowest-J choice avoid that.
    rng = np.random.default_rng(7)
    x = three_regimes(rng, sizes=(20000, 300, 300))
    np.testing.assert_allclose(fuzzy_c_means(x).centres, [0.0, 0.4, 1.0], atol=0.01)


@pytest.mark.parametrize(
    ("data", "kwargs", "match"),
    [
        ([], {}, "empty"),
        ([0.0, 0.5, math.nan, 1.0], {}, "non-finite"),
        ([0.0, 0.5, math.inf, 1.0], {}, "non-finite"),
        ([[0.0, 0.5], [1.0, 0.2]], {}, "1-D"),
        ([0.0, 0.0, 1.0, 1.0], {}, "2 distinct value"),
        ([0.0, 0.5, 1.0], {"m": 1.0}, "fuzzifier"),
        ([0.0, 0.5, 1.0], {"n_clusters": 1}, "n_clusters"),
        ([0.0, 0.5, 1.0], {"init_centres": [0.1, 0.1, 0.9]}, "distinct"),
    ],
)
def test_fcm_input_errors(data: object, kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(DiagnosisError, match=match) as info:
        fuzzy_c_means(data, **kwargs)  # type: ignore[arg-type]
    assert isinstance(info.value, ValueError)
    assert "\n" not in str(info.value)


# --------------------------------------------------------------------------------------
# Thresholds and calibration
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("m", [1.3, 2.0, 4.0])
def test_threshold_is_the_equal_membership_point(m: float) -> None:
    rng = np.random.default_rng(8)
    # Asymmetric clusters: the third centre must not shift the equal-membership point.
    x = three_regimes(rng, sizes=(400, 300, 200), levels=(0.05, 0.3, 0.95), sigma=0.04)
    r = fuzzy_c_means(x, m=m)
    th = thresholds_from_clusters(r)
    c = r.centres
    assert th.f1 == pytest.approx((c[0] + c[1]) / 2, abs=1e-15)
    assert th.f2 == pytest.approx((c[1] + c[2]) / 2, abs=1e-15)
    assert th.centres == tuple(c)
    u = fcm_memberships([th.f1, th.f2], c, m)
    assert u[0, 0] == pytest.approx(u[1, 0], rel=1e-12)  # clusters 0 and 1 equal at f1
    assert u[1, 1] == pytest.approx(u[2, 1], rel=1e-12)  # clusters 1 and 2 equal at f2
    assert u[2, 0] > 0.0 and u[0, 1] > 0.0  # ... although the third cluster has a share
    # Off the midpoint, the nearer cluster wins.
    eps = 1e-3
    u_off = fcm_memberships([th.f1 - eps, th.f1 + eps], c, m)
    assert u_off[0, 0] > u_off[1, 0] and u_off[1, 1] > u_off[0, 1]


@pytest.mark.parametrize("clip", [False, True])
@pytest.mark.parametrize("sizes", [(1000, 1000, 1000), (9000, 500, 1500), (300, 3000, 300)])
def test_calibration_recovers_midpoints(clip: bool, sizes: tuple[int, int, int]) -> None:
    rng = np.random.default_rng(9)
    gamma_hat = three_regimes(rng, sizes=sizes)
    if clip:  # an estimator that clips gamma^ to [0, 1]
        gamma_hat = np.clip(gamma_hat, 0.0, 1.0)
    th = calibrate(gamma_hat)
    assert th.quantity == "gamma"
    assert th.f1 == pytest.approx(0.2, abs=0.01)
    assert th.f2 == pytest.approx(0.7, abs=0.01)
    assert len(th.centres) == 3


def test_calibration_ignores_nan_samples() -> None:
    rng = np.random.default_rng(10)
    gamma_hat = three_regimes(rng)
    with_gaps = np.concatenate([gamma_hat, np.full(50, math.nan)])
    assert calibrate(with_gaps) == calibrate(gamma_hat)


@pytest.mark.parametrize(
    "case", ["fault_free_only", "constant_zero", "no_outage", "outage_outlier"]
)
def test_calibrate_requires_all_three_regimes(case: str) -> None:
    rng = np.random.default_rng(12)
    data = {
        "fault_free_only": rng.normal(0.0, 0.02, 5000),
        "constant_zero": np.zeros(5000),
        "no_outage": three_regimes(rng, sizes=(3000, 3000, 0)),
        "outage_outlier": np.append(three_regimes(rng, sizes=(3000, 3000, 0)), [1.0, 1.0]),
    }[case]
    with pytest.raises(DiagnosisError, match="fault-free, fault and outage periods") as info:
        calibrate(data)
    assert "\n" not in str(info.value)


def test_thresholds_validation() -> None:
    assert Thresholds(0.2, 0.7).quantity == "gamma"
    with pytest.raises(DiagnosisError, match="less than"):
        Thresholds(0.7, 0.7)
    with pytest.raises(DiagnosisError, match="finite"):
        Thresholds(math.nan, 0.7)
    with pytest.raises(DiagnosisError, match="number"):
        Thresholds(True, 0.7)
    with pytest.raises(DiagnosisError, match="increasing"):
        Thresholds(0.2, 0.7, centres=(1.0, 0.4, 0.0))
    th = Thresholds(0, 1, quantity="fault_volts")  # other quantities are not bounded
    assert isinstance(th.f1, float)
    # on gamma^ in [0, 1], f1 = 0 leaves no fault-free region and f2 = 1 no outage region
    for f1, f2 in ((0.0, 0.5), (0.5, 1.0), (-0.5, 2.0)):
        with pytest.raises(DiagnosisError, match="0 < f1 < f2 < 1"):
            Thresholds(f1, f2)
    with pytest.raises(AttributeError):
        th.f1 = 0.3  # type: ignore[misc]


def test_default_thresholds() -> None:
    assert Thresholds(0.15, 0.85, "gamma") == DEFAULT_THRESHOLDS


def test_thresholds_from_clusters_needs_three() -> None:
    r = fuzzy_c_means([0.0, 0.1, 0.9, 1.0], n_clusters=2)
    assert isinstance(r, FCMResult)
    with pytest.raises(DiagnosisError, match="3 clusters"):
        thresholds_from_clusters(r)


# --------------------------------------------------------------------------------------
# TOML file
# --------------------------------------------------------------------------------------


def test_save_load_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(13)
    th = calibrate(three_regimes(rng))
    path = tmp_path / "thresholds.toml"
    source = 'run "bench 3"\nC:\\logs\\run3.csv \u00e9\x01'
    save_thresholds(path, th, source=source)
    assert load_thresholds(path) == th
    doc = tomllib.loads(path.read_text(encoding="utf-8"))
    assert set(doc) == {"quantity", "f1", "f2", "centres", "source", "created"}
    assert doc["source"] == source
    assert isinstance(doc["created"], datetime) and doc["created"].tzinfo is not None
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left behind


def test_save_load_hand_set_thresholds(tmp_path: Path) -> None:
    path = tmp_path / "t.toml"
    save_thresholds(path, DEFAULT_THRESHOLDS)
    assert load_thresholds(path) == DEFAULT_THRESHOLDS
    path.write_text('quantity = "gamma"\nf1 = 0.1\nf2 = 0.9\n', encoding="utf-8")
    assert load_thresholds(path) == Thresholds(0.1, 0.9)
    path.write_text('quantity = "gamma"\nf1 = -0.5\nf2 = 2\n', encoding="utf-8")
    with pytest.raises(DiagnosisError, match="0 < f1 < f2 < 1"):
        load_thresholds(path)


BAD_FILES = {
    "missing_file": (None, "no such file"),
    "not_toml": ("quantity = gamma\nf1 = \n", "not valid TOML"),
    "not_utf8": (b'quantity = "\xff"\n', "not UTF-8 text"),
    "missing_f1": ('quantity = "gamma"\nf2 = 0.7\n', "missing key 'f1'"),
    "missing_f2": ('quantity = "gamma"\nf1 = 0.2\n', "missing key 'f2'"),
    "missing_quantity": ("f1 = 0.2\nf2 = 0.7\n", "missing key 'quantity'"),
    "f1_ge_f2": ('quantity = "gamma"\nf1 = 0.7\nf2 = 0.2\n', "less than"),
    "f1_eq_f2": ('quantity = "gamma"\nf1 = 0.5\nf2 = 0.5\n', "less than"),
    "nan": ('quantity = "gamma"\nf1 = nan\nf2 = 0.7\n', "finite"),
    "inf": ('quantity = "gamma"\nf1 = 0.2\nf2 = inf\n', "finite"),
    "not_a_number": ('quantity = "gamma"\nf1 = "0.2"\nf2 = 0.7\n', "number"),
    "wrong_quantity": ('quantity = "f_hat"\nf1 = 0.3\nf2 = 1.0\n', "quantity 'f_hat'"),
    "bad_centres": ('quantity = "gamma"\nf1 = 0.2\nf2 = 0.7\ncentres = 3\n', "centres"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_load_errors_are_one_line(tmp_path: Path, case: str) -> None:
    content, expected = BAD_FILES[case]
    path = tmp_path / f"{case}.toml"
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif content is not None:
        path.write_text(content, encoding="utf-8")
    with pytest.raises(DiagnosisError) as info:
        load_thresholds(path)
    message = str(info.value)
    assert "\n" not in message
    assert str(path) in message
    assert expected in message


def test_load_directory_is_one_line_error(tmp_path: Path) -> None:
    with pytest.raises(DiagnosisError, match="is a directory") as info:
        load_thresholds(tmp_path)
    assert "\n" not in str(info.value)


# --------------------------------------------------------------------------------------
# Health states and (76)
# --------------------------------------------------------------------------------------


def test_health_state_numbers_and_labels() -> None:
    # 0..3 on the bus; the model-mismatch flag is a signal of its own, beside the state
    assert [int(s) for s in HealthState] == [0, 1, 2, 3]
    assert [s.label for s in HealthState] == ["fault_free", "fault", "outage", "no_data"]


def test_classify_regions_of_eq_76() -> None:
    th = Thresholds(0.2, 0.7)
    assert classify(-0.1, th) is FF
    assert classify(math.nextafter(0.2, 0.0), th) is FF
    assert classify(0.2, th) is FAULT  # F1 <= F
    assert classify(0.7, th) is FAULT  # F <= F2
    assert classify(math.nextafter(0.7, 1.0), th) is OUTAGE
    assert classify(1.3, th) is OUTAGE
    assert classify(math.nan, th) is NO_DATA


# --------------------------------------------------------------------------------------
# Online classifier
# --------------------------------------------------------------------------------------

DT = 1e-3


def run(
    oc: OnlineClassifier, values: list[float], t0: float = 0.0
) -> list[tuple[float, HealthState]]:
    """Feed values at 1 kHz (t = t0 + k * DT); return the reported transitions."""
    out = []
    for k, v in enumerate(values):
        t = t0 + k * DT
        new = oc.update(t, v)
        if new is not None:
            out.append((t, new))
    return out


def test_noise_near_threshold_does_not_flicker() -> None:
    th = Thresholds(0.2, 0.7)
    rng = np.random.default_rng(14)
    values = (th.f1 + rng.normal(0.0, 0.02, 20_000)).tolist()  # 20 s at 1 kHz
    times = [k * DT for k in range(len(values))]
    raw = transitions(times, [classify(v, th) for v in values])
    oc = OnlineClassifier(th, dwell_s=0.05, hysteresis=0.02)
    online = run(oc, values)
    assert len(raw) > 5000  # the raw (76) decision flips on almost every other sample
    assert len(online) <= 3  # first classification, then at most a couple of changes
    assert len(online) * 1000 < len(raw)


@pytest.mark.parametrize(("level", "state"), [(0.5, FAULT), (1.0, OUTAGE)])
def test_clean_step_is_reported_after_exactly_the_dwell(level: float, state: HealthState) -> None:
    th = Thresholds(0.2, 0.7)
    oc = OnlineClassifier(th, dwell_s=0.05, hysteresis=0.02)
    step = 1000  # sample index of the step, t = 1.0 s
    values = [0.0] * step + [level] * 1000
    got = run(oc, values)
    assert got[0] == (0.0, FF)  # first sample accepted at once
    dwell_samples = 50
    assert got[1] == ((step + dwell_samples) * DT, state)
    assert len(got) == 2
    assert oc.state is state
    assert oc.since == (step + dwell_samples) * DT
    assert oc.onset == step * DT


def test_dwell_uses_sample_timestamps_not_wall_clock() -> None:
    oc = OnlineClassifier(Thresholds(0.2, 0.7), dwell_s=0.05)
    assert oc.update(0.0, 0.0) is FF
    assert oc.update(10.0, 0.5) is None  # candidate appears at t = 10
    assert oc.update(10.049, 0.5) is None
    assert oc.update(10.06, 0.5) is FAULT  # first sample at or after 10 + dwell
    # Irregular sampling: a single sample far after the onset is enough.
    assert oc.update(20.0, 0.0) is None
    assert oc.update(25.0, 0.0) is FF
    assert oc.since == 25.0 and oc.onset == 20.0


def test_short_glitch_is_not_reported() -> None:
    oc = OnlineClassifier(Thresholds(0.2, 0.7), dwell_s=0.05)
    got = run(oc, [0.0] * 100 + [1.0] * 49 + [0.0] * 100)
    assert got == [(0.0, FF)]


def test_hysteresis_band() -> None:
    th = Thresholds(0.2, 0.7)
    oc = OnlineClassifier(th, dwell_s=0.0, hysteresis=0.05)
    assert oc.update(0.0, 0.0) is FF
    assert oc.update(0.1, 0.24) is None  # above F1 but inside the band: stays fault-free
    assert oc.update(0.2, 0.26) is FAULT  # crossed F1 by the hysteresis
    assert oc.update(0.3, 0.16) is None  # below F1 but inside the band: stays fault
    assert oc.update(0.4, 0.14) is FF
    assert oc.update(0.5, 0.76) is OUTAGE  # fault-free straight to outage
    assert oc.update(0.6, 0.66) is None  # below F2 but inside the band
    assert oc.update(0.7, 0.64) is FAULT  # crossed F2 downwards by the hysteresis
    assert oc.update(0.8, 0.75) is None
    assert oc.update(0.9, 0.76) is OUTAGE


def test_zero_dwell_zero_hysteresis_is_eq_76() -> None:
    th = Thresholds(0.2, 0.7)
    rng = np.random.default_rng(15)
    values = rng.uniform(-0.2, 1.2, 5000).tolist()
    oc = OnlineClassifier(th, dwell_s=0.0, hysteresis=0.0)
    states = []
    for k, v in enumerate(values):
        oc.update(k * DT, v)
        states.append(oc.state)
    assert states == [classify(v, th) for v in values]


def test_alternating_candidates_move_one_step() -> None:
    # Fault-free, then noise straddling F2: neither fault nor outage persists on its own,
    # but the value has clearly left fault-free.
    th = Thresholds(0.2, 0.7)
    oc = OnlineClassifier(th, dwell_s=0.05, hysteresis=0.02)
    got = run(oc, [0.0] * 100 + [0.65, 0.75] * 100)
    assert got == [(0.0, FF), (150 * DT, FAULT)]


def test_nan_is_ignored_and_counted() -> None:
    th = Thresholds(0.2, 0.7)
    oc = OnlineClassifier(th, dwell_s=0.05)
    assert oc.update(0.0, math.nan) is None
    assert oc.state is NO_DATA and oc.n_ignored_nan == 1
    values = [0.0] * 100 + [0.5] * 20 + [math.nan] * 10 + [0.5] * 100
    got = run(oc, values, t0=1.0)
    # NaN neither resets the dwell timer nor causes a transition.
    assert got == [(1.0, FF), (1.0 + 150 * DT, FAULT)]
    assert oc.n_ignored_nan == 11


def test_no_data_then_resume() -> None:
    th = Thresholds(0.2, 0.7)
    oc = OnlineClassifier(th, dwell_s=0.05)
    assert oc.state is NO_DATA and oc.since is None  # nothing received yet
    run(oc, [0.5] * 10)
    assert oc.state is FAULT
    assert oc.mark_no_data(0.5) is NO_DATA
    assert oc.mark_no_data(0.6) is None  # already no_data
    assert oc.state is NO_DATA and oc.since == 0.5
    # The first valid sample after no_data is accepted at once (no dwell, no hysteresis).
    assert oc.update(0.7, 0.95) is OUTAGE
    assert oc.since == 0.7
    assert oc.update(0.701, 0.5) is None  # normal debouncing again


def test_out_of_order_timestamps_are_ignored() -> None:
    oc = OnlineClassifier(Thresholds(0.2, 0.7), dwell_s=0.0)
    assert oc.update(1.0, 0.0) is FF
    assert oc.update(0.5, 0.9) is None
    assert oc.update(math.nan, 0.9) is None
    assert oc.n_ignored_time == 2 and oc.state is FF
    assert oc.update(1.0, 0.9) is OUTAGE  # equal timestamps are fine


def test_online_parameter_validation() -> None:
    th = Thresholds(0.2, 0.7)
    with pytest.raises(DiagnosisError, match="dwell_s"):
        OnlineClassifier(th, dwell_s=-1.0)
    with pytest.raises(DiagnosisError, match="hysteresis"):
        OnlineClassifier(th, hysteresis=0.25)
    with pytest.raises(DiagnosisError, match="hysteresis"):
        OnlineClassifier(th, hysteresis=math.nan)


def test_transitions_helper() -> None:
    times = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5]
    states = [0, 0, 1, 1, 2, HealthState.NO_DATA]
    assert transitions(times, states) == [
        (0.2, FF, FAULT),
        (0.4, FAULT, OUTAGE),
        (0.5, OUTAGE, NO_DATA),
    ]
    assert transitions([], []) == []
    with pytest.raises(DiagnosisError, match="entries"):
        transitions([0.0], [0, 1])
    with pytest.raises(DiagnosisError, match="health state"):
        transitions([0.0], [7])


# --------------------------------------------------------------------------------------
# The compiled rules: one step at a time (the per-frame pipeline) and in a loop (replay)
# --------------------------------------------------------------------------------------


def _stream(seed: int) -> dict[str, np.ndarray]:
    """A node's samples and ticks in bus order: gamma^ wandering across F1 and F2 with
    noise and a standard deviation that comes and goes (0, NaN: none known), NIS in and out
    of its band, restarts, failed estimates, silences."""
    rng = np.random.default_rng(seed)
    n = 6000
    is_tick = rng.random(n) < 0.15
    dt = rng.choice([0.0, 0.001, 0.01, 0.01, 0.01, 0.02, 0.7], n,
                    p=[0.05, 0.05, 0.3, 0.3, 0.2, 0.08, 0.02])
    t = 100.0 + np.cumsum(dt)
    level = np.repeat(rng.choice([0.0, 0.15, 0.5, 0.85, 1.0], n // 200 + 1), 200)[:n]
    gamma = level + rng.normal(0.0, 0.03, n)
    gamma_sd = np.repeat(rng.choice([0.0, 0.01, 0.05, 0.2, math.nan], n // 150 + 1), 150)[:n]
    nis_scale = np.repeat(rng.choice([1.0, 1.0, 4.0, 0.05], n // 300 + 1), 300)[:n]
    nis = nis_scale * rng.chisquare(1, n)
    nis[rng.random(n) < 0.01] = math.nan
    restarted = (rng.random(n) < 0.005) & ~is_tick
    failed = (rng.random(n) < 0.003) & ~is_tick
    return {"is_tick": is_tick, "t": t, "gamma": gamma, "gamma_sd": gamma_sd, "nis": nis,
            "restarted": restarted, "failed": failed}


@pytest.mark.parametrize(("seed", "withhold"), [(1, False), (2, True), (3, True)])
def test_the_loop_and_the_single_steps_give_the_same_states(seed: int, withhold: bool) -> None:
    """`rules.run` (the columnar replay's classify) and `on_sample` / `on_tick` called one
    at a time (the per-frame pipeline) go through the same states and report the same."""
    from monitor.columnar import kernels
    from monitor.diagnosis import rules

    prm = rules.params(Thresholds(0.2, 0.7), dwell_s=0.03, hysteresis=0.02, outputs=1,
                       rate=100.0, window_s=0.2, mismatch_dwell_s=0.1, publish_period_s=0.1,
                       silence_timeout_s=0.5, withhold=withhold)
    x = _stream(seed)
    n = len(x["t"])
    # one step at a time
    s = rules.new_state(prm)
    out = rules.new_out()
    states = np.zeros((n, len(rules.STATE)))
    outs = np.zeros((n, len(rules.OUT)), np.int64)
    for i in range(n):
        if x["is_tick"][i]:
            rules.on_tick(s, prm, float(x["t"][i]), out)
        else:
            rules.on_sample(s, prm, float(x["t"][i]), float(x["gamma"][i]),
                            float(x["gamma_sd"][i]), float(x["nis"][i]),
                            bool(x["restarted"][i]), bool(x["failed"][i]), out)
        states[i] = s
        outs[i] = out
    # the loop, in chunks of uneven length (as the replay's chunks split a node's items)
    s2 = rules.new_state(prm)
    st, ev, prev, cause, fev = (np.zeros(n, np.int64) for _ in range(5))
    flag = np.zeros(n, np.bool_)
    counts = np.zeros(2, np.int64)
    cuts = [0, 1, 777, 3000, 3001, n]
    ends = []
    for a, b in itertools.pairwise(cuts):
        kernels.classify(x["is_tick"][a:b], x["t"][a:b], x["gamma"][a:b],
                         x["gamma_sd"][a:b], x["nis"][a:b], x["restarted"][a:b],
                         x["failed"][a:b], s2, prm, st[a:b], ev[a:b], prev[a:b], cause[a:b],
                         fev[a:b], flag[a:b], counts)
        ends.append(s2.copy())
    assert np.array_equal(ends[-1], states[-1], equal_nan=True)
    for b, end in zip(cuts[1:], ends, strict=True):
        assert np.array_equal(end, states[b - 1], equal_nan=True)
    assert np.array_equal(st, states[:, rules.REPORTED].astype(np.int64))
    assert np.array_equal(flag, states[:, rules.FLAGGED] != 0.0)
    assert np.array_equal(ev, outs[:, rules.EV])
    assert np.array_equal(prev, outs[:, rules.PREV])
    assert np.array_equal(cause, outs[:, rules.CAUSE])
    assert np.array_equal(fev, outs[:, rules.FLAG])
    assert counts.tolist() == [int(outs[:, rules.MISMATCH].sum()), int(outs[:, rules.SILENT].sum())]
    # the stream reaches every rule: each state, each kind of event and cause
    assert set(st.tolist()) == {0, 1, 2, 3}
    assert {0, 1, 2} <= set(ev.tolist())
    assert {1, 2, 3} <= set(fev.tolist())
    changed = (ev == 1) & (st != prev)
    assert {0, 2} <= set(cause[changed].tolist())
    assert counts.min() > 0
    if withhold:
        assert 1 in cause[changed].tolist()  # an alarm the flag held, reported as it fell


def test_the_views_step_the_rules_of_the_pipeline() -> None:
    """`OnlineClassifier` and `MismatchDetector` give the state and the flag that the
    rules' step gives on the same samples."""
    from monitor.diagnosis import MismatchDetector, rules

    th = Thresholds(0.2, 0.7)
    prm = rules.params(th, dwell_s=0.03, hysteresis=0.02, outputs=1, rate=100.0,
                       window_s=0.2, mismatch_dwell_s=0.1)
    oc = OnlineClassifier(th, dwell_s=0.03, hysteresis=0.02)
    md = MismatchDetector(1, 100.0, window_s=0.2, dwell_s=0.1)
    x = _stream(5)
    s = rules.new_state(prm)
    out = rules.new_out()
    seen = set()
    for i in np.flatnonzero(~x["is_tick"] & ~x["failed"] & ~x["restarted"]).tolist():
        t, g, nis = float(x["t"][i]), float(x["gamma"][i]), float(x["nis"][i])
        sd = float(x["gamma_sd"][i])
        rules.on_sample(s, prm, t, g, sd, nis, False, False, out)
        oc.update(t, g, sd)
        md.update(t, nis)
        assert int(oc.state) == int(s[rules.ST])
        assert md.flagged == (s[rules.FLAGGED] != 0.0)
        seen.add((int(oc.state), md.flagged))
    assert len(seen) >= 6


@given(q=st.floats(1e-9, 1.0 - 1e-9), dof=st.floats(0.5, 1e5))
@settings(max_examples=300, deadline=None, derandomize=True, database=None)
def test_the_mismatch_bands_quantile_is_scipy_stats(q: float, dof: float) -> None:
    """`rules.chi2_quantile` (the mismatch band's bounds) against scipy.stats.chi2, its peer."""
    assert chi2_quantile(q, dof) == pytest.approx(float(chi2.ppf(q, dof)), rel=1e-12, abs=0.0)


@pytest.mark.parametrize(("rate", "outputs"), [(10.0, 1), (100.0, 1), (1000.0, 1),
                                               (2000.0, 3)])
def test_the_mismatch_band_is_chi_square_but_never_narrower_than_the_tolerance(
        rate: float, outputs: int) -> None:
    """At a low rate the band is the chi-square average's quantiles; at a high rate, where
    they would flag a filter a few percent off its noise level, [p / 1.5, 1.25 p]."""
    lo, hi = MismatchDetector(outputs, rate).band
    a = 1.0 / (2.0 * rate)
    dof = outputs * (2.0 - a) / a
    q_lo = float(chi2.ppf(0.0005, dof)) * outputs / dof
    q_hi = float(chi2.ppf(0.9995, dof)) * outputs / dof
    floor_lo, floor_hi = rules.NIS_BAND_FLOOR
    assert lo == pytest.approx(min(q_lo, outputs * floor_lo), rel=1e-9)
    assert hi == pytest.approx(max(q_hi, outputs * floor_hi), rel=1e-9)
    assert lo <= outputs / 1.5 and hi >= outputs * 1.25


def test_a_filter_within_its_tolerance_is_not_flagged_at_a_high_rate() -> None:
    """1 kHz, one output: a windowed NIS of 0.78 (a learned model's Q pessimistic at another
    operating point, the rig zoo's seed 5) and 1.15 stay down; 0.5, 1.35 (an unmodelled load)
    and 2.5 are flagged after the dwell."""
    rng = np.random.default_rng(3)
    for level, flagged in ((0.78, False), (1.15, False), (0.5, True), (1.35, True),
                           (2.5, True)):
        md = MismatchDetector(1, 1000.0)
        t = np.arange(20000) / 1000.0
        nis = level * rng.chisquare(1, t.size)
        for k in range(t.size):
            md.update(float(t[k]), float(nis[k]))
        assert md.flagged is flagged, level


def test_an_alarm_must_be_significant_and_recovery_is_not_weighed() -> None:
    """Fault-free is left only where gamma^ reaches F1 + max(hysteresis, `significance`
    times its standard deviation); once alarmed, the state follows gamma^ with the hysteresis
    alone, whatever its standard deviation."""
    th = Thresholds(0.15, 0.85)
    t = np.arange(200) * 0.01
    # gamma^ 0.25 held: 0.1 over F1
    uncertain = OnlineClassifier(th, dwell_s=0.03, hysteresis=0.02, significance=1.0)
    sure = OnlineClassifier(th, dwell_s=0.03, hysteresis=0.02, significance=1.0)
    plain = OnlineClassifier(th, dwell_s=0.03, hysteresis=0.02, significance=0.0)
    unknown = OnlineClassifier(th, dwell_s=0.03, hysteresis=0.02)
    out = OnlineClassifier(th, dwell_s=0.03, hysteresis=0.02, significance=2.0)
    for c in (uncertain, sure, plain, unknown, out):
        c.update(-0.01, 0.0, 0.0)  # from no data: fault-free at once
    for k in range(100):
        uncertain.update(float(t[k]), 0.25, 0.12)  # 0.15 + 0.12 > 0.25: not significant
        sure.update(float(t[k]), 0.25, 0.05)  # 0.15 + 0.05 < 0.25
        plain.update(float(t[k]), 0.25, 0.12)
    assert uncertain.state is FF
    assert sure.state is FAULT and plain.state is FAULT
    # a NaN or zero standard deviation is none known: the edge of the hysteresis alone
    for k in range(100):
        unknown.update(float(t[k]), 0.25, math.nan if k % 2 else 0.0)
    assert unknown.state is FAULT
    # recovery: gamma^ 0.1 (below 0.13) with a large spread still clears the alarm
    for k in range(100, 200):
        sure.update(float(t[k]), 0.1, 0.5)
    assert sure.state is FF
    # an outage from fault-free: the same edge, raised
    for k in range(50):
        out.update(float(t[k]), 0.95, 0.5)  # 0.15 + 1.0 > 0.95
    assert out.state is FF
    for k in range(50, 100):
        out.update(float(t[k]), 0.95, 0.05)
    assert out.state is OUTAGE
    with pytest.raises(DiagnosisError, match="significance"):
        OnlineClassifier(th, significance=-1.0)
