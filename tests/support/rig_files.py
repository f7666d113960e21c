"""The rule every refused rig file keeps: `load_rig` raises one `RigError` line that starts
with ``rig file <path>: `` (`rig_refusal`); a rig file written from a text, beside copies of
the DBCs it names (`written_rig`)."""

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


def written_rig(directory: Path, text: str, *dbcs: Path, name: str = "rig.toml") -> Path:
    """The rig file `name` in `directory` holding `text`, with a copy of each of `dbcs` beside
    it (a rig names its DBC relative to itself)."""
    for dbc in dbcs:
        (directory / dbc.name).write_text(dbc.read_text())
    path = directory / name
    path.write_text(text)
    return path
