"""The two robustness boots: bad input against the real monitor daemon on a real vcan bus,
shared by ``tests/integration/test_robustness_vcan.py`` (assertions) and
``tests/bench/bad_input.py`` (the matrix).

Two User-Mode Linux boots (or native vcan, see tests/support/vcan_harness.py) do everything;
their shell scripts are ``scripts/boot_a.sh`` and ``scripts/boot_b.sh`` beside this file (with
``scripts/common.sh``), read here and given their parameters as environment variables:

* **Boot A** -- the daemon (``motor-monitor -v run --nodes 0 --rrd --events``), a healthy
  ``sim-ecu`` of node 0 and ``candump -L any`` (error frames included; bound to every
  interface, so it survives the interface being deleted). Then, one after the other:
  every kind of bad frame, sent with ``cansend`` in its own time window (see
  `tests.support.bad_frames.frame_kinds`; the frames go to the script as a file, one line
  a kind); the interface set down for 1 s and up again with the ECU running; the
  ECU stopped (a silent node); the last captured current frame of the ECU sent again
  (a replay: same alive counter); the interface deleted and re-created
  (``ip link del/add``) and a new ECU started; SIGTERM. Plus, in the background while the
  daemon starts, the two programs pointed at a CAN channel that does not exist.
* **Boot B** -- the daemon and a healthy ECU, then ``cangen`` at full rate for 10 s (random
  standard frames, and a mix of extended, remote and CAN FD frames) while the daemon's RSS
  is sampled every 0.5 s, 3 s of calm once the daemon has caught up, and a SIGKILL.

What the host reads afterwards: the scripts' ``key=value`` lines (``mark_*`` times in the
guest's clock, which is the clock of the kernel's frame time stamps), the candump capture,
the daemon's ``.rrd`` recording (samples, and the counters it logs about once per second of
bus time: `Snapshots`), its ``--events`` JSON lines and its stderr.

Counter windows: the daemon logs all its counters together, at the first estimated sample
at least 1 s after the previous log, so each bad-frame window (a few hundred ms) is
bracketed by the last snapshot before it and the first one after it; the kinds are 1.5 s
apart so that no bracket holds two windows (checked by `BootA.bracket`).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from monitor.bus.codec import Decoded, MotorDatabase
from tests.support.bad_frames import NODE, FrameKind, frame_kinds
from tests.support.candump import Captured, Frame, parse_frame, read_candump
from tests.support.rrd import Array, Snapshots, read_rrd, series
from tests.support.vcan_harness import VcanResult
from tests.support.vcan_scripts import (
    RunOnVcan,
    logs_tail,
    monitor_summary,
    run_script,
    script_values,
)

__all__ = [
    "F1",
    "FLOOD_S",
    "KIND_GAP_S",
    "MAX_KILL_LOSS_S",
    "NO_DATA",
    "REPLAYS",
    "SILENCE_S",
    "BootA",
    "BootB",
    "RunOnVcan",
    "load_boot_a",
    "load_boot_b",
    "logs_tail",
    "run_boot_a",
    "run_boot_b",
]

F1 = 0.15  # default thresholds: the healthy ECU must stay below F1
NO_DATA = 3  # HealthState raw value
SILENCE_S = 0.5  # the daemon's silence timeout
MAX_KILL_LOSS_S = 0.25  # after SIGKILL, readable up to this long before the kill
REPLAYS = 10
KIND_GAP_S = 1.5  # between bad-frame windows (> the 1 s counter period)
FLOOD_S = 10.0
TIME_TOL_S = 3e-6  # candump prints microseconds; the .rrd has float seconds -> ns


# ----------------------------------------------------------------------------- script runs


def read_events(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _run(vcan: RunOnVcan, name: str, out: Path, timeout: float,
         params: Mapping[str, str]) -> tuple[VcanResult, float]:
    """Run ``scripts/<name>`` with OUT, GAP and `params` in its environment, and save its
    outcome into ``out/script.json``."""
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    res = run_script(vcan, name, env={"OUT": str(out), "GAP": f"{KIND_GAP_S:g}", **params},
                     timeout=timeout)
    wall = time.monotonic() - t0
    (out / "script.json").write_text(json.dumps({
        "returncode": res.returncode, "stdout": res.stdout, "stderr": res.stderr,
        "backend": res.backend, "duration": res.duration, "wall_s": wall}))
    return res, wall


def _load_result(out: Path) -> tuple[VcanResult, float]:
    """The outcome of a boot as `_run` saved it (to read a kept directory again)."""
    d = json.loads((out / "script.json").read_text())
    return VcanResult(d["returncode"], d["stdout"], d["stderr"], d["backend"],
                      d["duration"]), float(d["wall_s"])


# ----------------------------------------------------------------------------- readback


class _BootReadback:
    """What both boots' results offer: script marks, readiness, and the node's series."""

    result: VcanResult
    values: dict[str, str]
    rrd: dict[str, tuple[Array, Array]]
    snaps: Snapshots
    events: list[dict[str, Any]]
    mon_err: str

    def mark(self, name: str) -> float:
        return float(self.values[f"mark_{name}"])

    @property
    def ok(self) -> bool:
        return self.values.get("ready") == "1"

    def gamma(self) -> tuple[Array, Array]:
        return series(self.rrd, f"/node/{NODE}/gamma/estimate")

    def measured(self) -> tuple[Array, Array]:
        return series(self.rrd, f"/node/{NODE}/ArmatureCurrent/measured")

    def _read_back(self, out: Path, rrd_name: str) -> None:
        """What both boots leave: script values, recording, counters, events, stderr."""
        self.values = script_values(self.result.stdout)
        if (out / rrd_name).exists():
            self.rrd = read_rrd(out / rrd_name)
            self.snaps = Snapshots.from_rrd(self.rrd)
        self.events = read_events(out / "ev.jsonl")
        self.mon_err = (out / "mon.err").read_text(errors="replace") if (
            out / "mon.err").exists() else ""


# ----------------------------------------------------------------------------- boot A


@dataclass
class BootA(_BootReadback):
    """Everything boot A left behind, read back on the host."""

    out: Path
    result: VcanResult
    wall_s: float
    kinds: list[FrameKind]
    values: dict[str, str] = field(default_factory=dict)
    capture: list[Captured] = field(default_factory=list)
    rrd: dict[str, tuple[Array, Array]] = field(default_factory=dict)
    snaps: Snapshots = field(default_factory=lambda: Snapshots(np.zeros(0), {}))
    events: list[dict[str, Any]] = field(default_factory=list)
    mon_err: str = ""
    summary: dict[str, int] | None = None

    def has(self, name: str) -> bool:
        return f"mark_{name}" in self.values

    def bracket(self, start: float, end: float) -> tuple[int | None, int | None]:
        """Snapshots (last before `start`, first after `end` + 0.2 s: room for frames still
        queued in the daemon's socket at `end`)."""
        return self.snaps.last_before(start), self.snaps.first_after(end + 0.2)

    def injected(self, kind: FrameKind) -> list[Captured]:
        """Captured frames of `kind` inside its window."""
        if not self.has(f"{kind.key}_start"):
            return []
        lo, hi = self.mark(f"{kind.key}_start"), self.mark(f"{kind.key}_end")
        keys = {f.key for f in kind.frames}
        if kind.key == "replay":
            keys = {f.key for f in self.replay_frames()}
        return [c for c in self.capture if lo <= c.t <= hi and c.frame.key in keys]

    def replay_frames(self) -> list[Frame]:
        text = self.values.get("replayed", "")
        return [parse_frame(text)] if "#" in text else []

    def restart_repeats(self, mdb: MotorDatabase) -> int:
        """Streams (current, voltage) whose first frame from the new ECU carries the same alive
        counter as the old ECU's last: the daemon, which keeps the last counter over a
        silence, drops that genuine frame as repeated (a 1 in 16 chance per stream)."""
        if not (self.has("ecu_stopped") and self.has("add")):
            return 0
        stopped, add = self.mark("ecu_stopped"), self.mark("add")
        n = 0
        for kind in ("current", "voltage"):
            fid = mdb.frame_id(kind, NODE)
            old = [c for c in self.capture if c.frame.arbitration_id == fid and c.t <= stopped
                   and not c.frame.extended and not c.frame.remote and not c.frame.error]
            new = [c for c in self.capture if c.frame.arbitration_id == fid and c.t > add]
            counters = []
            for c in (old[-1:] + new[:1]):
                d = mdb.decode_can(c.frame.message(c.t))
                counters.append(d.counter if isinstance(d, Decoded) else None)
            n += len(counters) == 2 and counters[0] is not None and counters[0] == counters[1]
        return n

    def genuine_current(self, mdb: MotorDatabase) -> list[tuple[float, float]]:
        """(t, amps) of the ECUs' own current frames of node 0 in the capture."""
        bad: set[tuple[int, bytes, bool, bool, bool, bool]] = set()
        for k in self.kinds:
            bad.update(f.key for f in k.frames)
        lo = self.mark("replay_start") if self.has("replay_start") else math.inf
        hi = self.mark("replay_end") if self.has("replay_end") else -math.inf
        cur_id = mdb.frame_id("current", NODE)
        out: list[tuple[float, float]] = []
        for c in self.capture:
            f = c.frame
            if f.arbitration_id != cur_id or f.key in bad or lo <= c.t <= hi:
                continue
            d = mdb.decode_can(f.message(c.t))
            if isinstance(d, Decoded):
                out.append((c.t, d.value))
        return out

    def diagnosis_frames(self, mdb: MotorDatabase) -> list[tuple[float, int, float]]:
        """(t, HealthState, GammaEstimate) of the daemon's MonitorDiagnosis_N0 frames."""
        fake = {f.key for k in self.kinds if k.key == "fake_diagnosis" for f in k.frames}
        out: list[tuple[float, int, float]] = []
        for c in self.capture:
            if c.frame.key in fake or c.frame.arbitration_id != mdb.frame_id("diagnosis", NODE):
                continue
            d = mdb.decode_can(c.frame.message(c.t))
            if isinstance(d, Decoded) and d.kind == "diagnosis":
                out.append((c.t, int(d.raw["HealthState"]), d.value))
        return out

    def classify_rows(self, mdb: MotorDatabase) -> dict[str, int]:
        """Each recorded measured-current row matched to the captured frame it came from:
        {'genuine': n, '<kind>': n (an injected frame reached the estimator!), 'unmatched': n,
        'value_mismatch': n}."""
        t_rows, v_rows = self.measured()
        labelled: list[tuple[float, str, float]] = [(t, "genuine", a)
                                                    for t, a in self.genuine_current(mdb)]
        for k in [*self.kinds, FrameKind("replay", "replay", (), {})]:
            labelled.extend((c.t, k.key, math.nan) for c in self.injected(k))
        labelled.sort()
        ts = np.array([x[0] for x in labelled])
        out: dict[str, int] = {"genuine": 0, "unmatched": 0, "value_mismatch": 0}
        for t, v in zip(t_rows, v_rows, strict=True):
            i = int(np.searchsorted(ts, t - TIME_TOL_S))
            hits = [labelled[j] for j in range(i, len(ts)) if ts[j] <= t + TIME_TOL_S]
            if not hits:
                out["unmatched"] += 1
                continue
            genuine = [h for h in hits if h[1] == "genuine"]
            if genuine:
                out["genuine"] += 1
                if not any(abs(h[2] - v) < 0.006 for h in genuine):
                    out["value_mismatch"] += 1
            else:
                out[hits[0][1]] = out.get(hits[0][1], 0) + 1
        return out

    def rows_between(self, i: int | None, j: int | None) -> int:
        """Recorded gamma rows with snapshot i's time < t <= snapshot j's time."""
        t, _ = self.gamma()
        lo = -math.inf if i is None else self.snaps.t[i]
        hi = math.inf if j is None else self.snaps.t[j]
        return int(np.count_nonzero((t > lo) & (t <= hi)))

    def nan_between(self, lo: float, hi: float) -> int:
        t, g = self.gamma()
        return int(np.count_nonzero(np.isnan(g[(t >= lo) & (t <= hi)])))


def run_boot_a(vcan: RunOnVcan, mdb: MotorDatabase, out: Path, timeout: float = 900.0) -> BootA:
    """Boot A: the bad frames of `frame_kinds` go to the script as ``out/inject.txt``, one
    line ``KEY FRAME...`` (cansend syntax) a kind."""
    out.mkdir(parents=True, exist_ok=True)
    inject = out / "inject.txt"
    inject.write_text("".join(f"{k.key} {' '.join(f.cansend() for f in k.frames)}\n"
                              for k in frame_kinds(mdb)))
    _run(vcan, "boot_a.sh", out, timeout, {"INJECT": str(inject), "REPLAYS": str(REPLAYS)})
    return load_boot_a(mdb, out)


def load_boot_a(mdb: MotorDatabase, out: Path) -> BootA:
    res, wall = _load_result(out)
    boot = BootA(out=out, result=res, wall_s=wall, kinds=frame_kinds(mdb))
    boot._read_back(out, "a.rrd")
    boot.capture = read_candump(out / "cap.log")
    boot.summary = monitor_summary(boot.mon_err)
    return boot


# ----------------------------------------------------------------------------- boot B


@dataclass
class BootB(_BootReadback):
    """Everything boot B left behind, read back on the host."""

    out: Path
    result: VcanResult
    wall_s: float
    values: dict[str, str] = field(default_factory=dict)
    rrd: dict[str, tuple[Array, Array]] = field(default_factory=dict)
    snaps: Snapshots = field(default_factory=lambda: Snapshots(np.zeros(0), {}))
    events: list[dict[str, Any]] = field(default_factory=list)
    rss: list[tuple[float, float]] = field(default_factory=list)  # (t, MB)
    mon_err: str = ""

    def rss_at(self, t: float) -> float:
        """RSS (MB) of the sample nearest to guest time t."""
        if not self.rss:
            return math.nan
        return min(self.rss, key=lambda x: abs(x[0] - t))[1]

    def kill_margin(self) -> float:
        """Kill time minus the time of the last measured sample on disk (s)."""
        t, _ = self.measured()
        return self.mark("kill") - float(t[-1]) if len(t) else math.inf

    def bus_frames(self) -> int:
        try:
            return int(self.values["tx_after"]) - int(self.values["tx_before"])
        except (KeyError, ValueError):
            return 0


def run_boot_b(vcan: RunOnVcan, out: Path, flood_s: float = FLOOD_S,
               timeout: float = 300.0) -> BootB:
    _run(vcan, "boot_b.sh", out, timeout, {"FLOOD_S": f"{flood_s:g}"})
    return load_boot_b(out)


def load_boot_b(out: Path) -> BootB:
    res, wall = _load_result(out)
    boot = BootB(out=out, result=res, wall_s=wall)
    boot._read_back(out, "b.rrd")
    rss_path = out / "rss.txt"
    if rss_path.exists():
        for line in rss_path.read_text().splitlines():
            parts = line.split()
            if len(parts) == 2 and parts[1].isdigit():
                boot.rss.append((float(parts[0]), int(parts[1]) / 1024.0))
    return boot
