"""Run the shell scripts of ``tests/support/scripts/`` on vcan and read back what they print.

Each script sources ``scripts/common.sh`` (found through ``SCRIPTS``) and prints ``key=value``
lines (``ready=1`` once the programs under test are up, ``<name>_rc=<status>`` as each one
ends); the programs' stderr goes to ``*.err`` files in the directory ``OUT``. The vcan
harness (tests/support/vcan_harness.py) runs the script's text with /bin/sh.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

from tests.support.paths import SCRIPTS
from tests.support.vcan_harness import VcanResult

__all__ = [
    "SCRIPTS",
    "RunOnVcan",
    "logs_tail",
    "monitor_summary",
    "run_ready",
    "run_script",
    "script_values",
]

#: `run_on_vcan` (the ``vcan`` fixture of tests/conftest.py).
RunOnVcan = Callable[..., VcanResult]


def script_values(stdout: str) -> dict[str, str]:
    """The ``key=value`` lines of a script's output."""
    return {m[1]: m[2] for m in re.finditer(r"^(\w+)=(\S*)$", stdout, re.MULTILINE)}


_SUMMARY_RE = re.compile(
    r"motor-monitor: stopped \(signal 15\): (\d+) frames, (\d+) estimated, (\d+) rejected, "
    r"(\d+) diagnosis frames sent")


def monitor_summary(stderr: str) -> dict[str, int] | None:
    """The counts of the daemon's last line after SIGTERM (frames, estimated, rejected,
    sent), or None if its stderr has no such line."""
    m = _SUMMARY_RE.search(stderr)
    if m is None:
        return None
    return dict(zip(("frames", "estimated", "rejected", "sent"), map(int, m.groups()),
                    strict=True))


def logs_tail(out: Path, chars: int = 3000) -> str:
    """The last ``chars`` characters of each ``*.err`` file in ``out``, for failure messages."""
    return "\n".join(f"--- {p.name} ---\n{p.read_text(errors='replace')[-chars:]}"
                     for p in sorted(out.glob("*.err")))


def run_script(vcan: RunOnVcan, name: str, *, env: Mapping[str, str] | None = None,
               timeout: float, interfaces: Sequence[str] = ("vcan0",)) -> VcanResult:
    """Run ``scripts/<name>`` on vcan with ``SCRIPTS`` and ``env`` in its environment."""
    res = vcan((SCRIPTS / name).read_text(), env={"SCRIPTS": str(SCRIPTS), **(env or {})},
               timeout=timeout, interfaces=interfaces)
    print(f"[vcan] {name}: {res.backend} run took {res.duration:.1f} s")
    return res


def run_ready(vcan: RunOnVcan, name: str, out: Path, *, env: Mapping[str, str] | None = None,
              timeout: float, interfaces: Sequence[str] = ("vcan0",)) -> dict[str, str]:
    """`run_script` with ``OUT=out``: the run must have exited 0 and printed ``ready=1`` (else
    the assertion shows its output and the tails of ``out/*.err``). Returns its ``key=value``
    lines."""
    res = run_script(vcan, name, env={"OUT": str(out), **(env or {})}, timeout=timeout,
                     interfaces=interfaces)
    values = script_values(res.stdout)
    detail = f"{res.stdout}\n{res.stderr}\n{logs_tail(out)}"
    assert res.returncode == 0, f"{name}: rc {res.returncode}\n{detail}"
    assert values.get("ready") == "1", f"{name}: not ready\n{detail}"
    return values
