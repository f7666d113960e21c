"""The daemon as a process: sd_notify, SIGTERM, and one clear line for every mistake."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import time
from pathlib import Path

import pytest

from tests.support import BIN
from tests.support.daemon import notified_daemon

MONITOR = str(BIN / "motor-monitor")


def _recv_all(sock: socket.socket, until: float, stop_on: bytes) -> list[bytes]:
    got: list[bytes] = []
    while time.monotonic() < until:
        sock.settimeout(max(0.01, until - time.monotonic()))
        try:
            got.append(sock.recv(4096))
        except TimeoutError:
            break
        if stop_on in got[-1]:
            break
    return got


def test_notify_protocol_and_sigterm_leave_a_verified_recording(tmp_path: Path) -> None:
    rrd = tmp_path / "run.rrd"
    env = dict(os.environ, WATCHDOG_USEC="2000000")
    with notified_daemon(["run", "--interface", "virtual", "--channel", "daemon-test",
                          "--rrd", str(rrd)], tmp_path / "notify.sock", env) as (proc, sock):
        first = _recv_all(sock, time.monotonic() + 60, b"READY=1")
        assert any(b"READY=1" in d for d in first), first
        # STATUS with counters, and watchdog pings at half of WATCHDOG_USEC (1 s)
        more = _recv_all(sock, time.monotonic() + 2.5, b"\x00")
        assert any(d.startswith(b"STATUS=") and b"frames" in d for d in more), more
        assert sum(d == b"WATCHDOG=1" for d in first + more) >= 2
        proc.send_signal(signal.SIGTERM)
        last = _recv_all(sock, time.monotonic() + 20, b"STOPPING=1")
        assert any(b"STOPPING=1" in d for d in last)
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "stopped (signal 15)" in err and "Traceback" not in err
    verify = subprocess.run([str(BIN / "rerun"), "rrd", "verify", str(rrd)],
                            capture_output=True, text=True, timeout=60)
    assert verify.returncode == 0, verify.stderr


def _bad(tmp_path: Path, name: str, text: str) -> str:
    p = tmp_path / name
    p.write_text(text)
    return str(p)


@pytest.mark.parametrize(
    ("argv", "expect"),
    [
        (["run", "--interface", "socketcan", "--channel", "nope0"], "cannot open CAN interface"),
        (["run", "--interface", "nosuchbus", "--channel", "x"], "cannot open CAN interface"),
        (["run", "--nodes", "16"], "node numbers must lie in 0..15"),
        (["run", "--nodes", "a,b"], "nodes must be"),
        (["run", "--rate", "fast"], "invalid float"),
        (["run", "--interface", "virtual", "--thresholds", "{missing}"], "thresholds"),
        (["run", "--interface", "virtual", "--thresholds", "{bad_toml}"], "thresholds"),
        (["run", "--interface", "virtual", "--thresholds", "{swapped}"], "f1"),
        (["run", "--interface", "virtual", "--dbc", "{missing}"], "missing"),
        (["run", "--interface", "virtual", "--dbc", "{bad_dbc}"], "bad.dbc"),
        (["run", "--interface", "virtual", "--rrd", "/nonexistent/dir/x.rrd"], "does not exist"),
        (["replay", "{missing}.log"], "no such file"),
        (["replay", "{bad_toml}"], "unsupported log format"),
        (["demo", "--scenario", "nosuch"], "unknown scenario"),
        (["demo", "--scenario", "{bad_scenario}"], "gamma values must lie in [0, 1]"),
        (["reproduce", "--period", "0"], "must be positive"),
        (["calibrate", "{missing}"], "gamma^ file"),
        (["frobnicate"], "invalid choice"),
    ],
)
def test_every_mistake_is_one_clear_line(tmp_path: Path, argv: list[str], expect: str) -> None:
    files = {
        "missing": str(tmp_path / "missing"),
        "bad_toml": _bad(tmp_path, "bad.toml", "f1 = [unclosed\n"),
        "swapped": _bad(tmp_path, "swapped.toml", 'quantity = "gamma"\nf1 = 0.9\nf2 = 0.1\n'),
        "bad_dbc": _bad(tmp_path, "bad.dbc", "VERSION \"\"\nBO_ 1 broken\n"),
        "bad_scenario": _bad(tmp_path, "s.toml", "duration = 5\n[[fault]]\nstart = 1\ngamma = 2\n"),
    }
    args = [a.format(**files) for a in argv]
    r = subprocess.run([MONITOR, *args], capture_output=True, text=True, timeout=120,
                       cwd=tmp_path)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith("motor-monitor"), lines
    assert expect in lines[0], lines
    assert "Traceback" not in r.stderr


def test_replay_with_secoc_key_rejects_forged_and_replayed_frames(tmp_path: Path) -> None:
    import json

    import can

    from monitor.bus.codec import load_database
    from sim_ecu.ecu import VirtualECU
    from sim_ecu.scenario import load_scenario

    key = bytes(range(16))
    keyfile = tmp_path / "secoc.key"
    keyfile.write_text(key.hex())
    keyfile.chmod(0o600)
    db = load_database()
    ecu = VirtualECU(None, db, 0, load_scenario("fault-outage-recovery"), seed=2, key=key)
    frames = list(ecu.frames(duration=6.0, start_time=1.7e9))
    # an attacker without the key: a forged current frame with a valid E2E CRC (built by
    # an unkeyed database) and a replay of an authentic frame
    forged = can.Message(arbitration_id=0x110, is_extended_id=False, timestamp=0.0,
                         data=db.encode_current(0, 0.0, 0))
    replayed = next(m for m in frames if m.arbitration_id == 0x110)
    mixed: list[can.Message] = []
    for i, m in enumerate(frames):
        mixed.append(m)
        if i % 200 == 100:
            mixed.append(can.Message(arbitration_id=0x110, is_extended_id=False,
                                     timestamp=m.timestamp, data=forged.data))
            mixed.append(can.Message(arbitration_id=0x110, is_extended_id=False,
                                     timestamp=m.timestamp, data=replayed.data))
    log = tmp_path / "signed.log"
    with can.io.CanutilsLogWriter(str(log), channel="vcan0") as w:
        for m in mixed:
            w.on_message_received(m)
    r = subprocess.run([MONITOR, "replay", str(log), "--key", str(keyfile)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    states = [json.loads(ln)["state"] for ln in r.stdout.splitlines()]
    assert states[:2] == ["fault_free", "fault"], states
    assert "rejected" in r.stderr and "Traceback" not in r.stderr
    n_injected = sum(1 for i in range(len(frames)) if i % 200 == 100)
    rejected = int(r.stderr.rsplit(", ", 1)[1].split()[0])
    assert rejected == 2 * n_injected, r.stderr
    keyfile.chmod(0o644)  # a key others can read is refused, in one line
    r = subprocess.run([MONITOR, "replay", str(log), "--key", str(keyfile)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "chmod 600" in r.stderr


def test_secoc_state_is_saved_on_exit_and_needs_a_key(tmp_path: Path) -> None:
    import json

    keyfile = tmp_path / "k"
    keyfile.write_text(bytes(range(16)).hex())
    keyfile.chmod(0o600)
    state = tmp_path / "fresh.json"
    r = subprocess.run([MONITOR, "run", "--interface", "virtual", "--secoc-state", str(state)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "needs --key" in r.stderr and r.stderr.count("\n") == 1
    proc = subprocess.Popen([MONITOR, "run", "--interface", "virtual", "--channel", "st",
                             "--key", str(keyfile), "--secoc-state", str(state)],
                            stderr=subprocess.PIPE, text=True)
    time.sleep(8)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert state.stat().st_mode & 0o777 == 0o600
    assert isinstance(json.loads(state.read_text()), dict)
