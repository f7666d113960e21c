"""The vcan harness against real SocketCAN peers (can-utils, python-can, iproute2).

Each ``vcan(...)`` call boots a User-Mode Linux kernel (~2 s) unless the host has SocketCAN, so
the checks are bundled into a few scripts.
"""

from __future__ import annotations

import json
import re
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from tests.support.paths import ROOT
from tests.support.vcan_harness import HARD_KILL_GRACE, VcanResult
from tests.support.vcan_scripts import SCRIPTS, RunOnVcan, run_script

pytestmark = pytest.mark.vcan

def _value(stdout: str, key: str) -> str:
    match = re.search(rf"^{re.escape(key)}=(\S*)$", stdout, re.MULTILINE)
    assert match is not None, f"{key}= missing from:\n{stdout}"
    return match.group(1)


def _lines(stdout: str, prefix: str) -> list[str]:
    return [line[len(prefix) :] for line in stdout.splitlines() if line.startswith(prefix)]


def _flags(link_line: str) -> set[str]:
    match = re.search(r"<([^>]*)>", link_line)
    assert match is not None, link_line
    return set(match.group(1).split(","))


def test_real_peers_on_vcan(vcan: RunOnVcan) -> None:
    started = time.time()
    # (a) cansend -> candump; (b) python-can <-> can-utils; (c) ip link down/up/del/add.
    result = run_script(vcan, "harness_peers.sh", interfaces=("vcan0", "vcan1"), timeout=120)
    out = result.stdout
    assert result.returncode == 0, (out, result.stderr)
    assert result.backend in ("native", "uml")
    # Kernel console noise stays out of the script's output.
    assert "Linux version" not in out and "vcan: Virtual CAN" not in out

    # (a) cansend -> candump -L: "(seconds.micros) vcan0 123#DEADBEEF"
    assert _value(out, "a_rc") == "0"
    captured = _lines(out, "A: ")
    assert len(captured) == 1, out
    match = re.fullmatch(r"\((\d+\.\d{6})\) vcan0 123#DEADBEEF", captured[0])
    assert match is not None, captured
    assert abs(float(match.group(1)) - started) < 300  # the guest clock follows the host's

    # (b) python-can sent 321#01020304, candump saw it; cansend's 456#CAFE reached python-can
    assert _value(out, "b_py_rc") == "0", result.stderr
    assert _value(out, "b_rc") == "0"
    b_lines = _lines(out, "B: ")
    assert len(b_lines) == 1, out
    assert re.fullmatch(r"\(\d+\.\d{6}\) vcan0 321#01020304", b_lines[0]), b_lines
    (b_json,) = _lines(out, "B_JSON: ")
    info = json.loads(b_json)
    assert info["rx_id"] == 0x456, info
    assert info["rx_data"] == "cafe"
    assert info["rx_channel"] == "vcan0"
    # A kernel (SO_TIMESTAMP) receive time: within the send/recv window, not 0 or monotonic.
    assert info["t0"] - 0.05 <= info["rx_ts"] <= info["t1"] + 0.05, info

    # (c) down/up
    assert _value(out, "c_down_rc") == "0"
    (down_line,) = _lines(out, "C_DOWN: ")
    assert "UP" not in _flags(down_line), down_line
    assert _value(out, "c_send_down") == "fail"
    (down_err,) = _lines(out, "C_DOWN_ERR: ")
    assert "Network is down" in down_err
    assert _value(out, "c_up_rc") == "0"
    (up_line,) = _lines(out, "C_UP: ")
    assert "UP" in _flags(up_line), up_line
    assert _value(out, "c_send_up") == "ok"
    assert _value(out, "c_del_rc") == "0"
    assert _value(out, "c_add_rc") == "0"
    (links,) = _lines(out, "C_LINKS: ")
    names = {name.split("@")[0] for name in links.split()}
    assert {"vcan0", "vcan2"} <= names and "vcan1" not in names, links


def test_exit_status_env_memory_and_parallel_runs(vcan: RunOnVcan, tmp_path: Path) -> None:
    def heavy() -> VcanResult:
        # Python with the project's heavy imports (memory), /dev/shm (multiprocessing), env,
        # cwd, stderr and a non-zero exit status.
        return vcan((SCRIPTS / "harness_exit.sh").read_text(),
                    env={"VCAN_TEST_TOKEN": "a b'c$"}, cwd=str(tmp_path), timeout=180)

    def light() -> VcanResult:
        return vcan("echo second; pwd; cansend vcan0 7FF#01", timeout=60)

    # Two kernels at once must not collide (own umid, uml_dir and work directory each).
    with ThreadPoolExecutor(max_workers=2) as pool:
        heavy_future = pool.submit(heavy)
        light_future = pool.submit(light)
        result, second = heavy_future.result(), light_future.result()

    assert second.returncode == 0 and second.stdout == f"second\n{ROOT}\n", second

    out = result.stdout
    assert result.returncode == 3, (out, result.stderr)
    assert "to stderr" in result.stderr
    assert "to stderr" not in out
    assert _value(out, "cwd") == str(tmp_path.resolve())
    assert "token=a b'c$\n" in out
    python = _value(out, "python")
    assert Path(python).parent == Path(sys.executable).parent
    assert _value(out, "sim-ecu") == "found"
    assert _value(out, "motor-monitor") == "found"
    assert _value(out, "python_rc") == "0", result.stderr
    assert _value(out, "numpy_sum") == str(4096 * 8192)


def test_timeout_returns_124_with_partial_output(vcan: RunOnVcan) -> None:
    started = time.monotonic()
    # 20 s: the guest boots in ~1.5 s on a quiet machine but took over 5 s in a CI run
    result = vcan("echo started; echo err-started >&2; sleep 120; echo never", timeout=20)
    elapsed = time.monotonic() - started
    assert result.returncode == 124
    assert result.stdout == "started\n"
    assert "err-started" in result.stderr
    assert elapsed < 20 + HARD_KILL_GRACE + 5, elapsed
