"""The errors of the bus stage, both under `monitor.errors.MonitorError`.

They live here, below `codec`, `scheme` and `secoc`, so that every module of the package
can raise them without importing another; `monitor.bus.codec` and `monitor.bus.secoc`
re-export the one that is theirs.
"""

from __future__ import annotations

from monitor.errors import MonitorError

__all__ = ["CodecError", "SecOCError"]


class CodecError(MonitorError, ValueError):
    """A DBC that cannot serve the codec, or a value that cannot be encoded (one line)."""


class SecOCError(MonitorError, ValueError):
    """A key, key file, SecOC layout or freshness state that cannot be used (one line)."""
