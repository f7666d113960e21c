"""Where the tests and benchmarks find the repository and their data files, derived once here
so that a test module reads the same path wherever its package lies below tests/."""

from __future__ import annotations

from pathlib import Path

#: The repository: monitor/, sim_ecu/, dbc/, rigs/ (the example rigs), systemd/, tests/.
ROOT = Path(__file__).resolve().parents[2]
#: The rigs the tests load: DBC, rig and scenario files of drives other than our bus's motor.
TEST_RIGS = ROOT / "tests" / "rigs"
#: Files of others the tests read: public EDS and DCF files (data/eds, its README says whose).
TEST_DATA = ROOT / "tests" / "data"
#: The shell scripts the vcan harness runs (the guest's init among them).
SCRIPTS = ROOT / "tests" / "support" / "scripts"
