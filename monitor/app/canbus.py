"""Opening a python-can bus, for the monitor and the virtual ECU alike.

What the command line leaves out (interface, channel) comes from python-can's own
configuration: CAN_INTERFACE / CAN_CHANNEL / CAN_CONFIG, ~/.canrc, can.rc.
"""

from __future__ import annotations

import contextlib
import errno
import logging
from collections.abc import Iterator
from typing import Any

import can

from monitor.errors import MonitorError, one_line

__all__ = ["BusError", "open_bus"]

log = logging.getLogger(__name__)


class BusError(MonitorError):
    """The CAN interface cannot be opened; the message is one line."""


@contextlib.contextmanager
def _quiet_can_logger(quiet: bool) -> Iterator[None]:
    """Silence python-can's own log records while opening (its error becomes our one line).

    e.g. socketcan logs "Could not access SocketCAN device ..." at ERROR before it raises.
    """
    can_log = logging.getLogger("can")
    old = can_log.level
    if quiet:
        can_log.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        can_log.setLevel(old)


def open_bus(interface: str | None, channel: str | None, bitrate: int | None = None, *,
             quiet: bool = True) -> can.BusABC:
    """``can.Bus`` with python-can's configuration filling in what is None.

    Raises `BusError` with one line when nothing names an interface (or a channel for
    socketcan, whose default "" means every interface and cannot send), or the bus cannot
    be opened. Other missing settings are left to the backend's defaults. `quiet` keeps
    python-can's own error record (a second line) out of the log.
    """
    given: dict[str, Any] = {}
    if interface is not None:
        given["interface"] = interface
    if channel is not None:
        given["channel"] = channel
    if bitrate is not None:
        given["bitrate"] = bitrate
    # Resolve once ourselves for clear messages; can.Bus repeats exactly this lookup.
    try:
        resolved = can.util.load_config(config=dict(given))
    except can.CanInterfaceNotImplementedError:
        name = _configured_interface(given)
        if name is None:
            raise BusError(
                "no CAN interface given: use --interface or set CAN_INTERFACE or a "
                "python-can config file"
            ) from None
        known = ", ".join(sorted(can.VALID_INTERFACES))
        raise BusError(f"cannot open CAN interface {name!r}: unknown CAN interface; python-can "
                       f"knows {known}") from None
    except Exception as exc:  # malformed CAN_CONFIG JSON, bad config-file values, ...
        raise BusError(f"python-can configuration: {one_line(exc)}") from None
    shown = "(default)" if resolved["channel"] is None else repr(resolved["channel"])
    where = f"interface {resolved['interface']!r} channel {shown}"
    if resolved["channel"] is None and resolved["interface"] == "socketcan":
        # socketcan's default channel "" binds to every interface and cannot send.
        raise BusError(
            "no CAN channel given for interface 'socketcan': use --channel or set "
            "CAN_CHANNEL or a python-can config file"
        )
    extra: dict[str, Any] = {"bitrate": bitrate} if bitrate is not None else {}
    try:
        with _quiet_can_logger(quiet):
            bus = can.Bus(interface=interface, channel=channel, **extra)
    except Exception as exc:  # backends raise CanError, OSError, ImportError, ValueError...
        hint = ""
        if isinstance(exc, OSError) and exc.errno == errno.EAFNOSUPPORT:
            hint = " (this kernel has no SocketCAN support)"
        raise BusError(f"cannot open CAN {where}: {one_line(exc)}{hint}") from None
    log.info("opened %s (%s)", where, bus.channel_info)
    return bus


def _configured_interface(given: dict[str, Any]) -> str | None:
    """The interface python-can's configuration yields for `given` (None: nowhere set)."""
    if given.get("interface"):
        return str(given["interface"])
    sources: list[dict[str, Any]] = [
        dict(can.rc),
        can.util.load_environment_config(),
        can.util.load_file_config(),
    ]
    for cfg in sources:
        value = cfg.get("interface") or cfg.get("bustype")
        if value:
            return str(value)
    return None
