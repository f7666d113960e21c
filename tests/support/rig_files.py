"""The rule every refused rig file keeps: `load_rig` raises one `RigError` line that starts
with ``rig file <path>: `` (`rig_refusal`)."""

from __future__ import annotations

from pathlib import Path

import pytest

from monitor.rig import RigError, load_rig


def rig_refusal(path: Path) -> str:
    """The line `load_rig` refuses the rig file at `path` with, after asserting that it is
    one line naming the file."""
    with pytest.raises(RigError) as info:
        load_rig(path)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(f"rig file {path}: "), msg
    return msg
