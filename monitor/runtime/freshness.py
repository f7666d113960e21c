"""Periodic saving of the SecOC freshness counters (`--secoc-state`), for the monitor (its
receive counters) and the virtual ECU (its send counters) alike."""

from __future__ import annotations

import time

from monitor.bus.secoc import SecOC, SecOCError
from monitor.files import PeriodicWrite

__all__ = ["FreshnessSaver"]


class FreshnessSaver(PeriodicWrite):
    """Saves `secoc`'s counters to `path` every `period_s` (`maybe_write`, the first a period
    after start: the state was just loaded) and at exit (`final`). A failing periodic save is
    logged once per burst of failures and retried at the next period; the program keeps
    running."""

    def __init__(self, secoc: SecOC, path: str, period_s: float) -> None:
        super().__init__(lambda: secoc.save_state(path), f"the SecOC state to {path}",
                         period_s, start=time.monotonic())
        self.secoc = secoc
        self.path = path

    def final(self) -> str | None:
        """The save at exit: None, or the one-line error."""
        try:
            self.secoc.save_state(self.path)
        except SecOCError as exc:
            return str(exc)
        return None
