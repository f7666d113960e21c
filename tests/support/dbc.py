"""The repository's motor bus DBC (`REPO_DBC`), and copies of it with one mistake made in
them (`edited_dbc`) for the tests of what the loader refuses."""

from __future__ import annotations

from pathlib import Path

from tests.support.paths import ROOT

REPO_DBC = ROOT / "dbc" / "motor.dbc"


def edited_dbc(directory: Path, old: str, new: str) -> Path:
    """A copy of `REPO_DBC` in `directory` (``motor.dbc``) with the first `old` replaced by
    `new`; `old` must be in it, so that the edit cannot silently miss."""
    text = REPO_DBC.read_text()
    assert old in text, old
    path = directory / "motor.dbc"
    path.write_text(text.replace(old, new, 1))
    return path
