"""Helpers of the tests and benchmarks (not part of the monitor package).

* `candump`: CAN frames in cansend / ``candump -L`` syntax, and candump logs.
* `bad_frames`: the catalogue of bad frames sent to the daemon, checked offline.
* `rrd`: the daemon's ``.rrd`` recordings: series and counter snapshots.
* `cli_cases`: malformed files and wrong command lines, each one clear error line.
* `boots`: the two User-Mode Linux (or native vcan) boots of the robustness tests, their
  shell scripts (``scripts/*.sh``) and what the host reads back from them.
* `ukf_filter`: a stateful wrapper of the compiled UKF kernels.
* `pipeline`: a `MonitorPipeline` driven in tests, and `Recorder`, a sink that keeps all.
* `engines`: both engines on one log, which must agree (`compare_engines`), and the
  virtual ECU's logs they are tried on.
* `dbc`: the repository's DBC, and copies of it with one edit (`edited_dbc`).
* `rig_files`: the one-line refusal every bad rig file gets (`rig_refusal`).
* `paths`: the repository (`ROOT`) and the tests' data (`TEST_RIGS`, `TEST_DATA`, `SCRIPTS`).
* `vcan_harness`: shell scripts run on real vcan, natively or in User-Mode Linux.
* `vcan_scripts`: the scripts of ``scripts/`` run on vcan, and what they print.
* `log_readers`: a log's frames as each reader gives them, random frames, MF4 files.
* `daemon`: ``motor-monitor`` started under a service manager's notify socket.

`motor_monitor` runs the installed command once, its output captured.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

#: The virtual environment's bin directory: motor-monitor, sim-ecu, rerun.
BIN = Path(sys.executable).parent


def motor_monitor(*args: str, cwd: Path | None = None, timeout: float = 300.0
                  ) -> subprocess.CompletedProcess[str]:
    """`motor-monitor ARGS` in `cwd` (None: here), its output captured, as a user runs it."""
    return subprocess.run([str(BIN / "motor-monitor"), *args], cwd=cwd,
                          capture_output=True, text=True, timeout=timeout)
