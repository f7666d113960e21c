"""What the monitor writes is named after the rig's own signals, not after our bus's motor.

A two-input two-output drive whose inputs are current commands (A) and whose outputs are a
speed (rad/s) and a position (rad) is replayed (both engines) and what was written read
back:

* the events' JSON lines carry the fault as ``fault_input`` with the inputs' unit, and no
  ``fault_volts``; a line of an older monitor (``fault_volts``) is still taken as an event;
* the recording's entities are ``/node/<n>/<Output>/measured|estimated|noise`` and
  ``/node/<n>/<Input>`` of the rig's signal names, with their units in the legends (none for
  a noise factor, a ratio), and the tab is "node <n>";
* the metrics count the inputs as ``samples/input`` (and the outputs before any input as
  ``samples/no_input``), and label each output's noise factor with the output's name;
* the built-in rig's names are `PlantSignals`' default, which names our bus's entities.
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Callable
from pathlib import Path

import pytest
from prometheus_client.parser import text_string_to_metric_families
from rerun.chunk import RrdReader

from monitor.app import outputs
from monitor.app.cli import main
from monitor.archive.engine import ENGINES, ReplaySettings, monitor_setup
from monitor.pipeline import PlantSignals
from monitor.rig import build_decoder, builtin_rig, load_rig
from monitor.sinks.base import Sink
from monitor.sinks.blueprint import signal_parts
from monitor.sinks.metrics import MetricsSink
from monitor.sinks.runs import SLOW_ROW_S
from sim_ecu.rig_ecu import RigECU
from sim_ecu.scenario import load_scenario
from tests.archive.logs import write_log
from tests.support.paths import TEST_RIGS
from tests.support.rrd import blueprint_names, read_rrd

ENGINE_NAMES = ("columnar", "per-frame")
NODE = 1  # the twin's node

# the twin's signals renamed: two current commands in, a speed and a position out
RENAMED = {"U1": ("CurrentCmdA", "A"), "U2": ("CurrentCmdB", "A"),
           "Y1": ("Speed", "rad/s"), "Y2": ("Position", "rad")}
INPUTS = ("CurrentCmdA", "CurrentCmdB")
OUTPUTS = ("Speed", "Position")


def _drive_rig(directory: Path) -> Path:
    """tests/rigs/twin.toml with its DBC's signals renamed and given units (`RENAMED`)."""
    dbc = (TEST_RIGS / "twin.dbc").read_text()
    rig = (TEST_RIGS / "twin.toml").read_text()
    for old, (new, unit) in RENAMED.items():
        line = next(x for x in dbc.splitlines() if x.startswith(f" SG_ {old} :"))
        dbc = dbc.replace(line, line.replace(f" SG_ {old} :", f" SG_ {new} :")
                          .rsplit('"', 2)[0].rsplit('"', 1)[0] + f'"{unit}" Monitor')
        rig = rig.replace(f'signal = "{old}" }}', f'signal = "{new}", unit = "{unit}" }}')
    assert all(new in dbc and new in rig for new, _ in RENAMED.values())
    (directory / "twin.dbc").write_text(dbc)
    path = directory / "drive.toml"
    path.write_text(rig)
    return path


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The renamed rig and a log of it: a 40 % loss of the second actuator at 3 s."""
    directory = tmp_path_factory.mktemp("drive")
    rig_path = _drive_rig(directory)
    rig = load_rig(rig_path)
    ecu = RigECU(None, build_decoder(rig), rig, NODE,  # type: ignore[arg-type]
                 load_scenario(TEST_RIGS / "twin_fault.toml"), seed=5)
    return rig_path, write_log(directory / "drive.log", list(ecu.frames(start_time=1000.0)))


def _legends(path: Path) -> dict[str, list[str]]:
    """The series names (legends) of the recording's static entities."""
    out: dict[str, list[str]] = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for chunk in RrdReader(path).stream():
            if not chunk.is_static:
                continue
            rb = chunk.to_record_batch()
            for col in rb.schema.names:
                if col.endswith("SeriesLines:names"):
                    out[chunk.entity_path] = [x for row in rb.column(col).to_pylist()
                                              if row for x in row]
    return out


@pytest.mark.parametrize("engine", ENGINE_NAMES)
def test_events_and_recording_carry_the_rigs_names(drive: tuple[Path, Path], tmp_path: Path,
                                                   engine: str) -> None:
    rig, log = drive
    events, rrd = tmp_path / "events.jsonl", tmp_path / "run.rrd"
    rc = main(["replay", str(log), "--rig", str(rig), "--events", str(events), "--rrd",
               str(rrd), "--engine", engine])
    assert rc == 0
    lines = [json.loads(x) for x in events.read_text().splitlines()]
    faults = [e for e in lines if e["state"] == "fault"]
    assert faults, lines
    for e in lines:
        assert "fault_volts" not in e
        assert e["fault_input_unit"] == "A"
    assert all(e["fault_input"] > 0 for e in faults)

    series = read_rrd(rrd)
    n = f"/node/{NODE}"
    for name in OUTPUTS:
        t_m, _ = series[f"{n}/{name}/measured"]
        t_e, _ = series[f"{n}/{name}/estimated"]
        assert len(t_m) == len(t_e) > 100
    # the first input of each command frame, at the frame's own rate
    assert len(series[f"{n}/{INPUTS[0]}"][0]) > 10
    assert f"{n}/gamma/estimate" in series and f"{n}/gamma/sd" in series
    assert not [e for e in series if e.startswith("/motor/") or "current" in e
                or "voltage" in e]
    legends = _legends(rrd)
    for name in OUTPUTS:
        assert legends[f"{n}/{name}/noise"] == [f"{name} noise factor"]
        # a slowly varying factor: a row every SLOW_ROW_S, not every sample
        t_noise, t_all = series[f"{n}/{name}/noise"][0], series[f"{n}/{name}/measured"][0]
        assert 0 < len(t_noise) <= (t_all[-1] - t_all[0]) / SLOW_ROW_S + 2 < len(t_all)
    assert legends[f"{n}/process_noise"] == ["process noise factor"]
    assert legends[f"{n}/Speed/measured"] == ["Speed measured (rad/s)"]
    assert legends[f"{n}/Position/estimated"] == ["Position estimated (rad)"]
    assert legends[f"{n}/CurrentCmdA"] == ["CurrentCmdA (A)"]
    assert legends[f"{n}/CurrentCmdB"] == ["CurrentCmdB (A)"]
    tabs = blueprint_names(rrd)
    assert {f"node {NODE}", "Speed: measured vs estimated", "CurrentCmdA (A)",
            "noise factors (1: the model's)"} <= tabs, tabs


def test_both_engines_write_the_same_entities(drive: tuple[Path, Path],
                                              tmp_path: Path) -> None:
    rig, log = drive
    got = {}
    for engine in ENGINE_NAMES:
        rrd = tmp_path / f"{engine}.rrd"
        assert main(["replay", str(log), "--rig", str(rig), "--rrd", str(rrd), "--engine",
                     engine, "--events", str(tmp_path / f"{engine}.jsonl")]) == 0
        got[engine] = read_rrd(rrd)
    a, b = got["columnar"], got["per-frame"]
    assert set(a) == set(b)
    n = f"/node/{NODE}"
    for e in [f"{n}/{o}/{k}" for o in OUTPUTS for k in ("measured", "estimated", "noise")] + \
             [f"{n}/{INPUTS[0]}", f"{n}/gamma/sd", f"{n}/process_noise"]:
        assert list(a[e][0]) == list(b[e][0]) and list(a[e][1]) == list(b[e][1]), e


@pytest.mark.parametrize("engine", ENGINE_NAMES)
def test_metrics_count_inputs(drive: tuple[Path, Path], tmp_path: Path, engine: str) -> None:
    rig, log = drive
    prom = tmp_path / "monitor.prom"
    setup = monitor_setup(ReplaySettings(rig=str(rig)))
    open_sinks: Callable[[], list[Sink]] = lambda: [  # noqa: E731
        MetricsSink(prom, live=False, signals=outputs.plant_signals(load_rig(rig)))]
    run = ENGINES[engine](log, setup, open_sinks)
    fams = {f.name: f for f in text_string_to_metric_families(prom.read_text())}
    events = {s.labels["name"]: s.value for s in fams["motor_monitor_events"].samples
              if s.name.endswith("_total")}
    # the counters as last handed to the sinks (the per-frame engine's about once a second)
    assert 0 < events["samples/input"] <= run.counters["samples/input"]
    assert not [name for name in events if "voltage" in name]
    noise = {s.labels["output"]: s.value
             for s in fams["motor_monitor_node_output_noise_factor"].samples}
    assert list(noise) == list(OUTPUTS)  # the rig's names, in its order
    assert all(v >= 1.0 and math.isfinite(v) for v in noise.values()), noise


def test_old_event_lines_are_still_events(tmp_path: Path) -> None:
    from monitor.runtime.paths import is_own_file

    old = {"t": 1.0, "node": 0, "state": "fault", "previous": "fault_free", "gamma": 0.5,
           "fault_volts": 12.0, "rules": 3, "cause": "estimate", "model_mismatch": False,
           "kind": "health"}
    new = {**{k: v for k, v in old.items() if k != "fault_volts"}, "fault_input": 12.0,
           "fault_input_unit": "V"}
    ev = tmp_path / "ev.jsonl"
    ev.write_text(f"{json.dumps(old)}\n{json.dumps(new)}\n")
    assert is_own_file(ev, "events")


def test_builtin_names_are_the_default() -> None:
    """`PlantSignals()` (the sinks' default) is what the built-in rig names, so our bus's
    recording is named the same with or without a rig."""
    assert outputs.plant_signals(builtin_rig()) == PlantSignals() == outputs.plant_signals(None)
    assert signal_parts(PlantSignals()) == (("VoltageCommand",), ("ArmatureCurrent",))


def test_signal_parts_never_take_a_series_name() -> None:
    signals = PlantSignals(inputs=(("gamma", None), ("a b/c", "V")),
                           outputs=(("nis", None), ("gamma", None)))
    ins, outs = signal_parts(signals, 3, 2)
    assert ins[0] == "gamma_signal" and outs == ("nis_signal", "gamma_signal_2")
    assert ins[2] == "u3" and len(set(ins + outs)) == 5
    assert ins[1] == "a\\ b\\/c"  # escaped: one entity path part
