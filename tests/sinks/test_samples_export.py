"""`replay --samples FILE.parquet|FILE.csv`: every estimated sample to a file, read back
with pyarrow and the csv module (pandas is not installed here; the Parquet file is what
pandas' `read_parquet` reads through pyarrow).

* One row per estimated sample: as many as the replay's `samples/estimated` counter.
* Columns named after the rig's signals and units (our bus, the press, the two-input
  two-output twin), the units in the Parquet fields' metadata.
* gamma^, f^ and the health state agree with the diagnosis events: each state change between
  a node's rows is a transition at that sample, and each transition an estimate makes is a
  row in that state with that gamma^ and f^.
* Both engines give the same rows, the estimator's noise factors (``noise_<Output>``,
  ``process_noise``) included; the Parquet and the CSV file hold the same values.
* The noise factors say what the estimator learnt: a sensor twice as noisy as the model
  says from 20 s on raises its output's factor well above 1 after it and not before; a
  fitting model keeps both factors near 1.
* The recording the same replay writes (``--rrd``) holds the file's ``gamma_sd`` as
  ``/node/<n>/gamma/sd`` and its noise factors as ``/node/<n>/<Output>/noise`` and
  ``/node/<n>/process_noise``, sample for sample, from either engine.
* Written in batches (row groups) and atomically (no temporary file left), our own file
  replaced, a foreign one or an input refused, a wrong suffix one line (exit 2).
"""

from __future__ import annotations

import csv
import itertools
import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from monitor.app.cli import main
from monitor.archive.engine import ENGINES, ReplaySettings, monitor_setup
from monitor.rig import build_decoder, load_rig
from monitor.sinks.base import Sink
from monitor.sinks.runs import SLOW_ROW_S, bin_starts
from monitor.sinks.samples import PARQUET_KEY, SamplesFileSink, SampleTable
from sim_ecu.rig_ecu import RigECU
from sim_ecu.scenario import load_scenario
from tests.archive.logs import ecu_frames, write_log
from tests.support.identify import T0, our_capture
from tests.support.paths import TEST_RIGS
from tests.support.rrd import read_rrd, series

ENGINE_NAMES = ("columnar", "per-frame")

OUR_COLUMNS = ["t_s", "node", "u_VoltageCommand_V", "y_ArmatureCurrent_A",
               "yhat_ArmatureCurrent_A", "gamma_VoltageCommand", "f_VoltageCommand_V",
               "gamma_sd", "noise_ArmatureCurrent", "process_noise", "nis", "state",
               "model_mismatch"]
TWIN_COLUMNS = ["t_s", "node", "u_U1_V", "u_U2_V", "y_Y1", "y_Y2", "yhat_Y1", "yhat_Y2",
                "gamma_U1", "gamma_U2", "f_U1_V", "f_U2_V", "gamma_sd", "noise_Y1", "noise_Y2",
                "process_noise", "nis", "state", "model_mismatch"]
PRESS_COLUMNS = ["t_s", "node", "u_SupplyVoltage_V", "y_MotorCurrent_A",
                 "yhat_MotorCurrent_A", "gamma_SupplyVoltage", "f_SupplyVoltage_V",
                 "gamma_sd", "noise_MotorCurrent", "process_noise", "nis", "state",
                 "model_mismatch"]
# the estimator's noise factors, and the output each one is of (the recording's entity)
OUR_NOISE = {"noise_ArmatureCurrent": "ArmatureCurrent"}
TWIN_NOISE = {"noise_Y1": "Y1", "noise_Y2": "Y2"}


@pytest.fixture(scope="module")
def our_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Our bus: node 0 faulty, with an outage and a recovery; node 1 healthy."""
    path = tmp_path_factory.mktemp("ours") / "bus.log"
    return write_log(path, ecu_frames(("fault-outage-recovery", "healthy"), seed=2,
                                      duration=20.0))


def _rig_log(directory: Path, rig: str, scenario: str) -> Path:
    r = load_rig(TEST_RIGS / rig)
    codec = build_decoder(r)
    ecu = RigECU(None, codec, r, 1, load_scenario(TEST_RIGS / scenario), seed=5)  # type: ignore[arg-type]
    return write_log(directory / "rig.log", list(ecu.frames(start_time=1000.0)))


@pytest.fixture(scope="module")
def twin_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _rig_log(tmp_path_factory.mktemp("twin"), "twin.toml", "twin_fault.toml")


@pytest.fixture(scope="module")
def press_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _rig_log(tmp_path_factory.mktemp("press"), "press.toml", "press_excite.toml")


def _replay(capsys: pytest.CaptureFixture[str], log: Path, out: Path, engine: str,
            *extra: str) -> tuple[int, list[dict[str, Any]]]:
    """`replay` in-process: the `samples/estimated` count it reports and its events."""
    events = out.with_suffix(out.suffix + ".events.jsonl")
    rc = main(["replay", str(log), "--samples", str(out), "--events", str(events),
               "--engine", engine, *extra])
    err = capsys.readouterr().err
    assert rc == 0, err
    m = re.search(r"(\d+) estimated", err)
    assert m is not None, err
    lines = events.read_text().splitlines()
    return int(m.group(1)), [json.loads(x) for x in lines]


def _read(path: Path) -> tuple[list[str], list[dict[str, Any]]]:
    """Column names and rows: pyarrow for Parquet; the csv module for CSV, numbers parsed
    (an empty field is NaN)."""
    if path.suffix == ".parquet":
        table = pq.read_table(path)
        return table.column_names, table.to_pylist()
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.reader(f)
        names = next(reader)
        rows = []
        for values in reader:
            row: dict[str, Any] = {}
            for k, v in zip(names, values, strict=True):
                if k == "state":
                    row[k] = v
                elif k == "node":
                    row[k] = int(v)
                elif k == "model_mismatch":
                    row[k] = bool(int(v))
                else:
                    row[k] = float(v) if v else float("nan")
            rows.append(row)
    return names, rows


def _key(row: dict[str, Any]) -> tuple[int, float]:
    return row["node"], row["t_s"]


def _check_against_events(rows: list[dict[str, Any]], events: list[dict[str, Any]],
                          gammas: list[str], fs: list[str]) -> None:
    """The states in the rows change exactly where the events say, and each transition an
    estimate makes shows that gamma^ and f^ at its sample."""
    health = [e for e in events if e.get("kind", "health") == "health"]
    at = {(e["node"], e["t"]): e for e in health}
    by_node: dict[int, list[dict[str, Any]]] = {}
    for r in sorted(rows, key=_key):
        by_node.setdefault(r["node"], []).append(r)
    changes = 0
    for node, rs in by_node.items():
        for prev, r in itertools.pairwise(rs):
            if r["state"] != prev["state"]:
                ev = at.get((node, r["t_s"]))
                assert ev is not None and ev["state"] == r["state"], (node, r)
                changes += 1
    by_time = {_key(r): r for r in rows}
    estimated = [e for e in health if e["cause"] != "silence"]
    assert estimated, "the capture has no transition made by an estimate"
    for e in estimated:
        r = by_time[(e["node"], e["t"])]
        assert r["state"] == e["state"]
        assert max(r[g] for g in gammas) == pytest.approx(e["gamma"], abs=1e-12)
        assert max(r[f] for f in fs) == pytest.approx(e["fault_input"], rel=1e-12, abs=1e-12) \
            or len(fs) > 1  # f^ of the worst input; with several, the largest gamma^'s
    assert changes >= 1


@pytest.mark.parametrize("engine", ENGINE_NAMES)
@pytest.mark.parametrize("suffix", [".parquet", ".csv"])
def test_our_bus_one_row_per_estimated_sample(our_log: Path, tmp_path: Path, engine: str,
                                              suffix: str,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / f"x{suffix}"
    estimated, events = _replay(capsys, our_log, out, engine)
    names, rows = _read(out)
    assert names == OUR_COLUMNS
    assert len(rows) == estimated > 1000
    assert {r["node"] for r in rows} == {0, 1}
    assert {r["state"] for r in rows} >= {"fault_free", "fault"}
    for r in rows:  # f^ is gamma^ times the input held at the sample
        assert r["f_VoltageCommand_V"] == pytest.approx(
            r["gamma_VoltageCommand"] * r["u_VoltageCommand_V"], rel=1e-12, abs=1e-12)
    _check_against_events(rows, events, ["gamma_VoltageCommand"], ["f_VoltageCommand_V"])
    # gamma^'s standard deviation: a variance's root, below the consequents' cap
    sd = np.array([r["gamma_sd"] for r in rows])
    assert np.all((sd >= 0.0) & (sd <= 0.5)) and np.mean(sd > 0.0) > 0.99
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [out.name, out.name + ".events.jsonl"])  # no temporary file left


def test_our_bus_parquet_metadata(our_log: Path, tmp_path: Path,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "x.parquet"
    _replay(capsys, our_log, out, "columnar")
    schema = pq.read_schema(out)
    assert schema.metadata[PARQUET_KEY] == b"2"
    field = schema.field("y_ArmatureCurrent_A")
    assert field.metadata == {b"unit": b"A", b"signal": b"ArmatureCurrent"}
    assert schema.field("t_s").metadata == {b"unit": b"s"}
    assert str(schema.field("state").type) == "string"
    assert str(schema.field("model_mismatch").type) == "bool"
    # a noise factor is a ratio: no unit, the output it is of as its signal
    assert schema.field("noise_ArmatureCurrent").metadata == {b"signal": b"ArmatureCurrent"}
    assert schema.field("process_noise").metadata is None


def test_engines_and_formats_give_the_same_rows(our_log: Path, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    got = {}
    for engine in ENGINE_NAMES:
        for suffix in (".parquet", ".csv"):
            out = tmp_path / f"{engine}{suffix}"
            _replay(capsys, our_log, out, engine)
            got[engine, suffix] = sorted(_read(out)[1], key=_key)
    first = got["columnar", ".parquet"]
    for key, rows in got.items():
        assert rows == first, key  # exact: the CSV holds each float's shortest repr
    # the noise factors are in what was compared: a factor on the model's noise, >= 1, that
    # moves (the adaptation writes every sample's, not a constant)
    for name in ("noise_ArmatureCurrent", "process_noise"):
        v = np.array([r[name] for r in first])
        assert np.all(np.isfinite(v) & (v >= 1.0)), name
        assert len(np.unique(v)) > 100, name


@pytest.mark.parametrize("engine", ENGINE_NAMES)
def test_two_input_two_output_rig(twin_log: Path, tmp_path: Path, engine: str,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    rows_of = {}
    for suffix in (".parquet", ".csv"):
        out = tmp_path / f"twin{suffix}"
        estimated, events = _replay(capsys, twin_log, out, engine, "--rig",
                                    str(TEST_RIGS / "twin.toml"))
        names, rows = _read(out)
        assert names == TWIN_COLUMNS
        assert len(rows) == estimated > 500
        rows_of[suffix] = sorted(rows, key=_key)
        # the 40 % loss of the second actuator at 3 s: gamma^ of U2 finds it, U1's stays low
        late = [r for r in rows if r["t_s"] > 1000.0 + 6.0]
        assert late and min(r["gamma_U2"] for r in late) > 0.25
        assert max(r["gamma_U1"] for r in late) < 0.15
        assert all(r["y_Y1"] != r["y_Y2"] for r in rows[:50])  # two outputs, not one twice
        _check_against_events(rows, events, ["gamma_U1", "gamma_U2"], ["f_U1_V", "f_U2_V"])
        schema_units = None
        if suffix == ".parquet":
            schema_units = {f.name: (f.metadata or {}).get(b"unit")
                            for f in pq.read_schema(out)}
            assert schema_units["u_U2_V"] == b"V" and schema_units["y_Y2"] is None
    assert rows_of[".parquet"] == rows_of[".csv"]


@pytest.mark.parametrize("engine", ENGINE_NAMES)
@pytest.mark.parametrize("rig", [None, "twin.toml"])
def test_recording_holds_the_files_gamma_sd_and_noise(request: pytest.FixtureRequest,
                                                      tmp_path: Path, engine: str,
                                                      rig: str | None,
                                                      capsys: pytest.CaptureFixture[str]
                                                      ) -> None:
    """``replay --samples --rrd``: the recording's ``/node/<n>/gamma/sd`` is the samples
    file's ``gamma_sd``, the very floats at the same times, on our bus (two nodes) and on the
    twin, whose two inputs may both lose effectiveness (the larger gamma^'s); so are its
    ``/node/<n>/<Output>/noise`` (one per output, the twin's two) and
    ``/node/<n>/process_noise`` the file's noise factors, at the samples that open each
    tenth of a second (`bin_starts`: they move over the noise window, seconds)."""
    log = request.getfixturevalue("our_log" if rig is None else "twin_log")
    out, rrd = tmp_path / "x.parquet", tmp_path / "x.rrd"
    extra = ["--rrd", str(rrd)] + ([] if rig is None else ["--rig", str(TEST_RIGS / rig)])
    estimated, _ = _replay(capsys, log, out, engine, *extra)
    _, rows = _read(out)
    recording = read_rrd(rrd)
    nodes = sorted({r["node"] for r in rows})
    assert nodes == ([0, 1] if rig is None else [1])
    assert sum(len(series(recording, f"/node/{n}/gamma/sd")[1]) for n in nodes) == estimated
    for node in nodes:
        rs = sorted((r for r in rows if r["node"] == node), key=_key)
        t, sd = series(recording, f"/node/{node}/gamma/sd")
        np.testing.assert_array_equal(sd, [r["gamma_sd"] for r in rs])
        np.testing.assert_allclose(t, [r["t_s"] for r in rs], rtol=0, atol=1e-6)
        assert np.all(sd >= 0.0) and np.mean(sd > 0.0) > 0.99  # a variance's root, no NaN
        # the slowly varying noise factors: the file's rows that open a SLOW_ROW_S bin
        t_file = np.array([r["t_s"] for r in rs])
        kept = bin_starts(t_file, -math.inf, SLOW_ROW_S)
        assert 5 < kept.sum() < 0.2 * len(rs)
        noise = {**(OUR_NOISE if rig is None else TWIN_NOISE), "process_noise": None}
        for column, output in noise.items():
            entity = f"/node/{node}/" + (f"{output}/noise" if output else column)
            t, v = series(recording, entity)
            np.testing.assert_array_equal(v, np.array([r[column] for r in rs])[kept],
                                          err_msg=entity)
            np.testing.assert_allclose(t, t_file[kept], rtol=0, atol=1e-6)
            assert np.all(v >= 1.0), entity  # a factor on the model's noise, no NaN


def test_noise_factors_say_what_the_estimator_learnt(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """Node 0 of our bus under a PRBS command, its current sensor with 1 A of noise added
    from 20 s on (the model says 0.5 A: the variance becomes 5 times the model's), read
    back with pyarrow: ``noise_ArmatureCurrent`` stays near 1 before 20 s and is well
    above 1 at the end (the estimator learns over its 2 s noise window); the process
    noise's factor stays near 1, the added noise being white. The same capture without the
    added noise keeps both near 1 throughout."""
    frames = {}
    for name, noisy_from in (("noisy", 20.0), ("healthy", None)):
        cap = our_capture(tmp_path / f"{name}.log", noisy_from=noisy_from)
        out = tmp_path / f"{name}.parquet"
        _replay(capsys, cap, out, "columnar")
        table = pq.read_table(out)
        frames[name] = {k: np.array(table.column(k).to_pylist())
                        for k in ("t_s", "noise_ArmatureCurrent", "process_noise")}
    noisy = frames["noisy"]
    t = noisy["t_s"] - T0
    noise = noisy["noise_ArmatureCurrent"]
    before, end = t < 20.0, t >= 38.0
    assert before.sum() > 1000 and end.sum() > 100
    assert np.all((noise[before] >= 1.0) & (noise[before] < 1.5))
    assert noise[end].min() > 3.0  # 5 in truth
    assert np.all(noisy["process_noise"][t >= 25.0] < 2.0)
    healthy = frames["healthy"]
    assert np.all((healthy["noise_ArmatureCurrent"] >= 1.0)
                  & (healthy["noise_ArmatureCurrent"] < 1.5))
    assert np.all((healthy["process_noise"] >= 1.0) & (healthy["process_noise"] < 2.5))
    assert float(np.median(healthy["process_noise"])) < 1.5


def test_rig_names_and_units(press_log: Path, tmp_path: Path,
                             capsys: pytest.CaptureFixture[str]) -> None:
    rows = {}
    for engine in ENGINE_NAMES:
        out = tmp_path / f"{engine}.csv"
        estimated, _ = _replay(capsys, press_log, out, engine, "--rig",
                               str(TEST_RIGS / "press.toml"))
        names, rows[engine] = _read(out)
        assert names == PRESS_COLUMNS
        assert len(rows[engine]) == estimated > 0
    assert sorted(rows["columnar"], key=_key) == sorted(rows["per-frame"], key=_key)


def test_written_in_row_groups_through_either_engine(our_log: Path, tmp_path: Path) -> None:
    """A small batch: several row groups, the rows the same as one batch gives."""
    setup = monitor_setup(ReplaySettings())
    table = SampleTable(inputs=(("VoltageCommand", "V"),), outputs=(("ArmatureCurrent", "A"),),
                        fault_inputs=(0,))
    for engine in ENGINE_NAMES:
        out = tmp_path / f"{engine}.parquet"

        def sinks(out: Path = out) -> list[Sink]:
            return [SamplesFileSink(out, table, batch_rows=500)]

        run = ENGINES[engine](our_log, setup, sinks)
        meta = pq.ParquetFile(out).metadata
        assert meta.num_rows == run.counters["samples/estimated"]
        assert meta.num_row_groups >= meta.num_rows // 1000 > 1
        assert pq.read_table(out).column_names == OUR_COLUMNS


def test_outputs_checked(our_log: Path, tmp_path: Path,
                         capsys: pytest.CaptureFixture[str]) -> None:
    def run(*args: str) -> tuple[int, str]:
        rc = main(["replay", str(our_log), "--events", str(tmp_path / "e.jsonl"), *args])
        return rc, capsys.readouterr().err

    rc, err = run("--samples", str(tmp_path / "x.txt"))
    assert rc == 2 and ".parquet or .csv" in err and err.count("\n") == 1
    rc, err = run("--samples")
    assert rc == 2 and "--samples" in err and err.count("\n") == 1
    rc = main(["replay", str(our_log), "--samples", str(tmp_path / "x.csv"), "--out",
               str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and "--samples" in err and err.count("\n") == 1
    link = tmp_path / "log.csv"
    link.symlink_to(our_log)
    rc, err = run("--samples", str(link))
    assert rc == 2 and "same file as PATH" in err
    for suffix in (".csv", ".parquet"):
        foreign = tmp_path / f"foreign{suffix}"
        foreign.write_text("a,b\n1,2\n")
        rc, err = run("--samples", str(foreign))
        assert rc == 2 and "not written by motor-monitor" in err and "--force" in err
        assert foreign.read_text() == "a,b\n1,2\n"
        rc, err = run("--samples", str(foreign), "--force")
        assert rc == 0, err
        rc, err = run("--samples", str(foreign))  # ours now: replaced without --force
        assert rc == 0, err
        assert _read(foreign)[0] == OUR_COLUMNS
    other = tmp_path / "other.parquet"  # a Parquet file with our columns, not our mark
    pq.write_table(pa.table({"t_s": [1.0], "node": [0]}), other)
    rc, err = run("--samples", str(other))
    assert rc == 2 and "not written by motor-monitor" in err
