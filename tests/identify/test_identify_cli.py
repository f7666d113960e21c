"""`motor-monitor identify` on captures a virtual twin recorded: it writes a rig that loads
and runs, a report beside it, and refuses a capture it cannot use in one line."""

from __future__ import annotations

import json
import os
import pty
import subprocess
import threading
from pathlib import Path

import can
import pytest

from monitor.bus.rigcodec import RigCodec
from monitor.rig import build_decoder, load_rig
from sim_ecu.rig_ecu import RigECU
from sim_ecu.scenario import load_scenario
from tests.support import BIN
from tests.support.identify import PRESS, press_capture, run_identify, run_replay


def test_identify_writes_a_rig_that_runs(tmp_path: Path) -> None:
    cap = press_capture(tmp_path / "healthy.log")
    out = tmp_path / "learned.toml"
    res = run_identify(str(cap), "--rig", str(PRESS), "--node", "1", "--out", str(out),
                    cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "hold-out fit" in res.stdout
    # to a pipe nothing says what it is doing (`test_identify_says_what_it_does_on_a_terminal`)
    assert "motor-monitor: identify:" not in res.stderr, res.stderr
    rig = load_rig(out)  # every key checked
    assert rig.rate == pytest.approx(100.0)
    report = json.loads(out.with_suffix(".identify.json").read_text())
    assert {"fit", "whiteness", "cross_correlation"} <= set(report)
    # run --rig RIG_OUT works at once: the learned rig replays a capture
    rep = run_replay(str(cap), "--rig", str(out))
    assert rep.returncode == 0, rep.stderr
    assert "0 rejected" in rep.stderr


def _drain(fd: int, into: list[bytes]) -> None:
    """Everything written to a pseudo-terminal, read from its master until it closes."""
    while True:
        try:
            chunk = os.read(fd, 4096)
        except OSError:  # EIO: the last writer closed the terminal
            return
        if not chunk:
            return
        into.append(chunk)


def test_identify_says_what_it_does_on_a_terminal(tmp_path: Path) -> None:
    """With standard error on a terminal identify says what it is doing (at 1-2 kHz a fit
    and its checks take minutes): the fit and the replay check, one line each."""
    cap = press_capture(tmp_path / "healthy.log")
    master, slave = pty.openpty()
    proc = subprocess.Popen([str(BIN / "motor-monitor"), "identify", str(cap), "--rig",
                             str(PRESS), "--node", "1", "--out", str(tmp_path / "learned.toml")],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=slave)
    os.close(slave)
    chunks: list[bytes] = []
    reader = threading.Thread(target=_drain, args=(master, chunks), daemon=True)
    reader.start()
    try:
        out, _ = proc.communicate(timeout=300)
        reader.join(timeout=30)
    finally:
        os.close(master)
    shown = b"".join(chunks).decode(errors="replace")
    assert proc.returncode == 0, shown
    assert b"hold-out fit" in out
    lines = [ln for ln in shown.splitlines() if ln.startswith("motor-monitor: identify: ")]
    assert any("fitting node 1's model" in ln and "samples at 100 Hz" in ln for ln in lines), shown
    assert any("the monitor replays the capture" in ln for ln in lines), shown


def test_identify_refuses_a_capture_without_excitation(tmp_path: Path) -> None:
    cap = press_capture(tmp_path / "steady.log", steady=True)
    res = run_identify(str(cap), "--rig", str(PRESS), "--node", "1", "--out",
                    str(tmp_path / "x.toml"), cwd=tmp_path)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in res.stderr, res.stderr
    assert "record" in lines[0], lines[0]
    assert not (tmp_path / "x.toml").exists()


def test_identify_wants_a_node_when_the_capture_has_several(tmp_path: Path) -> None:
    rig = load_rig(PRESS)
    codec = build_decoder(rig)
    assert isinstance(codec, RigCodec)
    cap = tmp_path / "two.log"
    scenario = load_scenario(PRESS.parent / "press_excite.toml")
    with can.Logger(str(cap)) as log:
        for node in (1, 2):
            for msg in RigECU(None, codec, rig, node, scenario, seed=node).frames(10.0, 1.7e9):
                log(msg)
    res = run_identify(str(cap), "--rig", str(PRESS), "--out", str(tmp_path / "x.toml"),
                    cwd=tmp_path)
    assert res.returncode == 2 and "--node" in res.stderr, res.stderr
