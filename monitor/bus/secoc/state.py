"""The SecOC freshness counters as names and values, and the state file that keeps them.

`SecOC.export_state` / `SecOC.import_state` (`monitor.bus.secoc.engine`) speak the
``{"rx/<kind>/<node>": value, "tx/<kind>/<node>": value}`` form built and checked here;
`SecOC.save_state` writes it with `write_state_file` atomically (temporary file, fsync,
`os.replace`, mode 0600) and `SecOC.load_state` reads it back with `read_state_file` (a
missing file is a fresh start; anything malformed, or a file others may write, is one
`SecOCError` line). The file::

    {"format": "motor-monitor SecOC freshness state", "version": 1,
     "freshness": {"rx/current/0": 250, "tx/voltage/3": 17, ...}}
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Hashable, Mapping
from pathlib import Path
from typing import Any, Final, Literal

from monitor.bus.errors import SecOCError
from monitor.bus.secoc.keys import read_guarded
from monitor.errors import one_line
from monitor.files import atomic_write_text

__all__ = [
    "STATE_FORMAT",
    "STATE_VERSION",
    "export_counters",
    "parse_counters",
    "read_state_file",
    "write_state_file",
]

STATE_FORMAT: Final = "motor-monitor SecOC freshness state"
STATE_VERSION: Final = 1
_MAX_STATE_FILE: Final = 1 << 20
_STATE_KEY: Final = re.compile(r"^(?P<dir>rx|tx)/(?P<kind>[a-z][a-z0-9_]*)/(?P<node>\d{1,5})$")

Direction = Literal["rx", "tx"]


def export_counters(rx: Mapping[Hashable, int], tx: Mapping[Hashable, int]) -> dict[str, int]:
    """``{"rx/<kind>/<node>": value, "tx/<kind>/<node>": value}``, sorted, for the streams
    named ``(kind, node)``; others are left out."""
    out: dict[str, int] = {}
    for direction, table in (("rx", rx), ("tx", tx)):
        for stream, value in table.items():
            name = _stream_name(stream)
            if name is not None:
                out[f"{direction}/{name}"] = value
    return dict(sorted(out.items()))


def parse_counters(state: Mapping[str, int], *,
                   tx_margin: int = 0) -> list[tuple[Direction, tuple[str, int], int]]:
    """`export_counters` output as (direction, (kind, node), value), sending values raised by
    `tx_margin` (capped at 2^64-1); any bad name or value is a `SecOCError`."""
    if isinstance(tx_margin, bool) or not isinstance(tx_margin, int) or tx_margin < 0:
        raise SecOCError(f"tx_margin must be a non-negative int, got {tx_margin!r}")
    if not isinstance(state, Mapping):
        raise SecOCError(f"SecOC state must be a mapping, got {type(state).__name__}")
    parsed: list[tuple[Direction, tuple[str, int], int]] = []
    for key, value in state.items():
        m = _STATE_KEY.match(key) if isinstance(key, str) else None
        if m is None:
            raise SecOCError(f"SecOC state: bad stream name {key!r}; expected "
                             f"rx|tx/<kind>/<node>")
        if isinstance(value, bool) or not isinstance(value, int) or not (
                0 <= value < 1 << 64):
            raise SecOCError(f"SecOC state: {key} must be an int in 0..2^64-1, "
                             f"got {value!r}")
        direction: Direction = "tx" if m["dir"] == "tx" else "rx"
        if direction == "tx":
            value = min(value + tx_margin, (1 << 64) - 1)
        parsed.append((direction, (m["kind"], int(m["node"])), value))
    return parsed


def write_state_file(path: str | os.PathLike[str], counters: Mapping[str, int]) -> None:
    """Write `counters` to `path` atomically, mode 0600; the previous file stays intact on
    any problem, which is one `SecOCError` line."""
    p = Path(path)
    text = json.dumps({"format": STATE_FORMAT, "version": STATE_VERSION,
                       "freshness": dict(counters)}, indent=1) + "\n"
    try:
        atomic_write_text(p, text, mode=0o600, encoding="ascii")
    except OSError as exc:
        raise SecOCError(f"{p}: cannot save SecOC state: {exc.strerror or exc}") from None


def read_state_file(path: str | os.PathLike[str]) -> dict[str, Any] | None:
    """The ``"freshness"`` object of a state file (its values not checked yet: that is
    `parse_counters`' job), or None if `path` does not exist.

    A file that is not a regular file, is writable by group or others, is not JSON or not
    of this format and version is one `SecOCError` line.
    """
    p = Path(path)
    raw = read_guarded(p, "SecOC state", refused_mode=0o022, refused_as="writable",
                       advice="it guards against replays: chmod 600", limit=_MAX_STATE_FILE)
    if raw is None:
        return None
    try:
        doc = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise SecOCError(f"{p}: not a SecOC state file: {one_line(exc, limit=160)}") from None
    if not isinstance(doc, dict) or doc.get("format") != STATE_FORMAT:
        raise SecOCError(f"{p}: not a SecOC state file (no \"format\": "
                         f"\"{STATE_FORMAT}\")")
    if doc.get("version") != STATE_VERSION:
        raise SecOCError(f"{p}: SecOC state version {doc.get('version')!r} is not "
                         f"supported (expected {STATE_VERSION})")
    freshness = doc.get("freshness")
    if not isinstance(freshness, dict):
        raise SecOCError(f"{p}: not a SecOC state file: \"freshness\" must be an object")
    return freshness


def _stream_name(stream: Hashable) -> str | None:
    """``"<kind>/<node>"`` for a stream named ``(kind, node)``, else None."""
    if (isinstance(stream, tuple) and len(stream) == 2 and isinstance(stream[0], str)
            and isinstance(stream[1], int) and not isinstance(stream[1], bool)
            and stream[1] >= 0):
        name = f"{stream[0]}/{stream[1]}"
        if _STATE_KEY.match("rx/" + name):
            return name
    return None
