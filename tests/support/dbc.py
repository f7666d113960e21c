"""The repository's motor bus DBC (`REPO_DBC`), and copies of it with one mistake made in
them (`edited_dbc`) for the tests of what the loader refuses, and the decoding of one frame of
it (`decode_frame`)."""

from __future__ import annotations

from pathlib import Path

from monitor.bus.codec import Decoded, MotorDatabase, Rejected
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


def decode_frame(db: MotorDatabase, fid: int, data: bytes, ts: float = 0.0) -> Decoded | Rejected:
    """What `db` makes of a classic CAN data frame with an 11-bit ID (the frames of our bus)
    received at `ts`."""
    return db.decode(fid, data, False, False, False, ts)
