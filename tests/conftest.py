"""Shared pytest fixtures and hooks."""

from __future__ import annotations

import os
from collections.abc import Callable, Generator

import pytest

from tests.support.vcan_harness import VcanResult, run_on_vcan, vcan_unavailable_reason


def _ci_enabled() -> bool:
    return os.environ.get("CI", "").strip().lower() in ("1", "true", "yes", "on")


@pytest.fixture(scope="session")
def vcan() -> Callable[..., VcanResult]:
    """``run_on_vcan`` (see tests/support/vcan_harness.py); skips without vcan, fails if CI is
    set."""
    reason = vcan_unavailable_reason()
    if reason is not None:
        if _ci_enabled():
            pytest.fail(f"CI is set but vcan is unavailable: {reason}", pytrace=False)
        pytest.skip(reason)
    return run_on_vcan


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(
    item: pytest.Item, call: pytest.CallInfo[None]
) -> Generator[None, pytest.TestReport, pytest.TestReport]:
    """With CI set, a ``vcan``-marked test must run: turn any skip of it into a failure."""
    report = yield
    if (
        report.skipped
        and not hasattr(report, "wasxfail")
        and item.get_closest_marker("vcan") is not None
        and _ci_enabled()
    ):
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else report.longrepr
        report.outcome = "failed"
        report.longrepr = f"CI is set, so vcan tests may not be skipped; skip reason: {reason}"
    return report
