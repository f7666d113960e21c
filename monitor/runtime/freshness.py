"""Periodic saving of the SecOC freshness counters (`--secoc-state`), for the monitor (its
receive counters) and the virtual ECU (its send counters) alike."""

from __future__ import annotations

import logging
import time

from monitor.bus.secoc import SecOC, SecOCError

__all__ = ["FreshnessSaver"]

log = logging.getLogger(__name__)


class FreshnessSaver:
    """Saves `secoc`'s counters to `path` every `period_s` (`maybe_save`) and at exit
    (`final`). A failing periodic save is logged once per burst of failures and retried at
    the next period; the program keeps running."""

    def __init__(self, secoc: SecOC, path: str, period_s: float) -> None:
        self.secoc = secoc
        self.path = path
        self.period_s = period_s
        self.failing = False
        self._last = time.monotonic()

    def maybe_save(self, now_monotonic: float) -> None:
        if now_monotonic - self._last >= self.period_s:
            self._last = now_monotonic
            self.save()

    def save(self) -> None:
        try:
            self.secoc.save_state(self.path)
        except SecOCError as exc:
            if not self.failing:
                log.error("%s (retrying every %g s)", exc, self.period_s)
            self.failing = True
        else:
            if self.failing:
                log.warning("SecOC state saved again to %s", self.path)
            self.failing = False

    def final(self) -> str | None:
        """The save at exit: None, or the one-line error."""
        try:
            self.secoc.save_state(self.path)
        except SecOCError as exc:
            return str(exc)
        return None
