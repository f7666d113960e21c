"""Captures for `motor-monitor identify` and the command itself, as the identify tests run
them: the press rig's twin (`press_capture`), node 0 of our bus under a PRBS command
(`our_capture`), `identify` in a subprocess (`run_identify`), and on a rig of the rig zoo
(`identify_zoo_rig`); `replay` of what it wrote (`run_replay`)."""

from __future__ import annotations

import json
import re
import subprocess
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import can
import numpy as np

from monitor.bus.codec import load_database
from monitor.bus.rigcodec import RigCodec
from monitor.rig import build_decoder, load_rig
from sim_ecu.ecu import VirtualECU
from sim_ecu.rig_ecu import RigECU
from sim_ecu.scenario import load_scenario, scenario_from_dict
from tests.bench.zoo.gen import identify_files
from tests.support import motor_monitor
from tests.support.paths import TEST_RIGS
from tests.support.pipeline import changed_currents

__all__ = ["PRESS", "T0", "identify_zoo_rig", "our_capture", "press_capture", "run_identify",
           "run_replay"]

PRESS = TEST_RIGS / "press.toml"
T0 = 1.7e9


def press_capture(path: Path, scenario_toml: Path | None = None, *,
                  steady: bool = False) -> Path:
    """A minute of the press rig's node 1 (its excitation scenario, or a steady command),
    written to `path` by python-can."""
    rig = load_rig(PRESS)
    scenario = (scenario_from_dict({"name": "steady", "duration": 60.0}) if steady
                else load_scenario(scenario_toml or PRESS.parent / "press_excite.toml"))
    codec = build_decoder(rig)
    assert isinstance(codec, RigCodec)  # a rig of its own DBC
    ecu = RigECU(None, codec, rig, 1, scenario, seed=4)
    with can.Logger(str(path)) as log:
        for msg in ecu.frames(start_time=T0):
            log(msg)
    return path


def our_capture(path: Path, *, noisy_from: float | None = None) -> Path:
    """40 s of node 0 on our bus under a PRBS command; from `noisy_from` seconds on, the
    current sensor adds 1 A of noise (twice the model's sigma): the plant is the same,
    its noise is not."""
    db = load_database()
    sc = scenario_from_dict({"name": "prbs", "duration": 40.0, "voltage": {
        "prbs": {"level": 220.0, "amplitude": 20.0, "clock": 0.5, "seed": 3}}})
    rng = np.random.default_rng(7)
    frames = list(VirtualECU(None, db, 0, sc, seed=5).frames(start_time=T0))
    if noisy_from is not None:
        frames = changed_currents(db, frames, lambda v, t: (
            v + float(rng.normal(0.0, 1.0)) if t - T0 >= noisy_from else v))
    with can.Logger(str(path)) as log:
        for m in frames:
            log(m)
    return path


def run_identify(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """`motor-monitor identify ARGS` in `cwd`, its output captured."""
    return motor_monitor("identify", *args, cwd=cwd)


def run_replay(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    """`motor-monitor replay ARGS` in `cwd` (None: here), its output captured: how the
    identify tests replay what identify wrote."""
    return motor_monitor("replay", *args, cwd=cwd)


def identify_zoo_rig(seed: int, d: Path, *args: str, binary_prbs: bool = False
                     ) -> tuple[subprocess.CompletedProcess[str], dict[str, Any]]:
    """`identify` as the rig zoo runs it on rig `seed`'s healthy minute (written to `d`; a
    PRBS rig's of two levels with `binary_prbs`), its first node, into learned.toml (more
    options `args`): the command's result and the report it wrote (empty where none)."""
    rig = identify_files(seed, d, binary_prbs=binary_prbs)
    res = run_identify("identify.log", "--rig", "rig.toml", "--out", "learned.toml",
                       "--node", str(rig.nodes[0]), *args, cwd=d)
    report = d / "learned.identify.json"
    return res, (json.loads(report.read_text()) if report.exists() else {})


def monitor_only(rig: Path, node: int, listed: Sequence[int]) -> None:
    """Rewrite the rig file `rig`, which lists the nodes `listed` (as the zoo writes it: one
    ``nodes = [...]`` line, its `[bus]` list), to monitor node `node` alone."""
    line = f"nodes = [{', '.join(map(str, listed))}]"
    text, n = re.subn(rf"(?m)^{re.escape(line)}$", f"nodes = [{node}]", rig.read_text())
    assert n == 1, f"{rig}: {n} lines {line!r}"
    rig.write_text(text)
