"""The one root of every error the monitor reports to its user.

Like python-can's `CanError` and cantools' `cantools.errors.Error`, each stage raises its
own subclass (`CodecError`, `SecOCError`, `ModelError`, `DiagnosisError`, `BusError`, ...)
and the command line catches `MonitorError` once: its message is one line naming the file,
the key or the option and what is wrong, printed as `motor-monitor: error: ...`, exit 2.
The stage errors that describe a bad value also derive from `ValueError`.
"""

from __future__ import annotations

import logging

__all__ = ["ERROR_LINE_LIMIT", "FailureBurst", "MonitorError", "UsageError", "one_line"]

ERROR_LINE_LIMIT = 500
"""The most characters of a message the command lines print: a value echoed from a user's
file (a signal name of a megabyte) must not make the one error line a megabyte."""


class MonitorError(Exception):
    """Root of the monitor's errors; the message is one line for the user."""


class UsageError(MonitorError):
    """A mistake in what the user asked for on the command line."""


class FailureBurst:
    """The log of an operation the program retries and runs on without (a periodic file
    write, a notification): the first failure of a burst is logged, the ones after it are
    not (a failing disk would otherwise bury the journal in one line a period), and the first
    success after a burst says that it works again."""

    def __init__(self, log: logging.Logger, recovered: str, *,
                 level: int = logging.ERROR) -> None:
        self.failing = False
        self._log = log
        self._recovered = recovered
        self._level = level

    def failed(self, message: str) -> None:
        """One failure: logged at the burst's `level` when it starts one."""
        if not self.failing:
            self._log.log(self._level, "%s", message)
        self.failing = True

    def worked(self) -> None:
        """One success: ends a burst, with the `recovered` line."""
        if self.failing:
            self._log.warning("%s", self._recovered)
        self.failing = False


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
