"""The one root of every error the monitor reports to its user.

Like python-can's `CanError` and cantools' `cantools.errors.Error`, each stage raises its
own subclass (`CodecError`, `SecOCError`, `ModelError`, `DiagnosisError`, `BusError`, ...)
and the command line catches `MonitorError` once: its message is one line naming the file,
the key or the option and what is wrong, printed as `motor-monitor: error: ...`, exit 2.
The stage errors that describe a bad value also derive from `ValueError`.
"""

from __future__ import annotations

__all__ = ["ERROR_LINE_LIMIT", "MonitorError", "UsageError", "one_line"]

ERROR_LINE_LIMIT = 500
"""The most characters of a message the command lines print: a value echoed from a user's
file (a signal name of a megabyte) must not make the one error line a megabyte."""


class MonitorError(Exception):
    """Root of the monitor's errors; the message is one line for the user."""


class UsageError(MonitorError):
    """A mistake in what the user asked for on the command line."""


def one_line(text: BaseException | str, limit: int = 200) -> str:
    """`text` (or an exception's message, else its type name) collapsed to one line of at
    most `limit` characters. Characters that do not print (a NUL, an escape sequence from a
    binary file quoted in a parser's message) are shown as Python escapes, so that nothing
    read from a user's file reaches the terminal raw."""
    if isinstance(text, BaseException):
        flat = " ".join(str(text).split()) or type(text).__name__
    else:
        flat = " ".join(text.split())
    if not flat.isprintable():
        flat = "".join(c if c.isprintable() else ascii(c)[1:-1] for c in flat)
    return flat if len(flat) <= limit else flat[: limit - 3] + "..."
