"""Bus logs for the archive tests and benchmark: virtual ECUs' runs written by python-can's
writers (candump .log, Vector .asc, .blf), and damaged files."""

from __future__ import annotations

import heapq
from collections.abc import Sequence
from pathlib import Path

import can

from monitor.bus.codec import load_database
from sim_ecu.ecu import VirtualECU
from sim_ecu.scenario import load_scenario
from tests.support.log_readers import WRITERS, write_log

__all__ = ["SCENARIOS", "WRITERS", "corrupt_blf", "corrupt_candump", "ecu_frames", "write_log"]

T0 = 1.7e9
SCENARIOS = ("healthy", "fault-outage-recovery", "incipient", "intermittent")

def ecu_frames(scenarios: Sequence[str], *, seed: int = 0, duration: float | None = None,
               start_time: float = T0) -> list[can.Message]:
    """The frames of one virtual ECU per scenario (nodes 0, 1, ...) on one bus, in time
    order."""
    db = load_database()
    runs = [list(VirtualECU(None, db, node, load_scenario(name), seed=seed + node)
                 .frames(duration=duration, start_time=start_time))
            for node, name in enumerate(scenarios)]
    return list(heapq.merge(*runs, key=lambda m: m.timestamp))


def corrupt_blf(path: Path) -> Path:
    """A file named .blf that is no BLF (python-can: "Unexpected file format")."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(bytes(range(255, -1, -1)) * 8)
    return path


def corrupt_candump(path: Path, frames: Sequence[can.Message]) -> Path:
    """A candump .log whose middle is overwritten by bytes that are no text: python-can
    reads the first frames, then fails."""
    write_log(path, frames)
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 64] = bytes(range(192, 256))
    path.write_bytes(bytes(data))
    return path
