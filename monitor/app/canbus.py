"""Opening a python-can bus, for the monitor and the virtual ECU alike.

What the command line leaves out (interface, channel) comes from python-can's own
configuration: CAN_INTERFACE / CAN_CHANNEL / CAN_CONFIG, ~/.canrc, can.rc.

SocketCAN is opened CAN FD-capable (python-can's ``fd=True``: the CAN_RAW_FD_FRAMES socket
option), unless the configuration says ``fd`` itself. Without it the kernel never hands
an FD frame to the socket, so FD frames would vanish uncounted. On a classic-only
interface (MTU 16) the option is still accepted: the socket reads and sends classic frames
as before, and no FD frame can arrive (the log says so once).
"""

from __future__ import annotations

import contextlib
import errno
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Final

import can

from monitor.errors import MonitorError, one_line

__all__ = ["CANFD_MTU", "CAN_MTU", "BusError", "interface_mtu", "open_bus"]

log = logging.getLogger(__name__)

CAN_MTU: Final = 16  # sizeof(struct can_frame): a classic CAN interface
CANFD_MTU: Final = 72  # sizeof(struct canfd_frame): a CAN FD interface


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
             quiet: bool = True, fd: bool = True) -> can.BusABC:
    """``can.Bus`` with python-can's configuration filling in what is None.

    `fd`: open a SocketCAN interface CAN FD-capable (unless python-can's configuration
    sets ``fd``); other interfaces are opened as their configuration says.

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
    socketcan = resolved["interface"] == "socketcan"
    if fd and socketcan and "fd" not in resolved:
        extra["fd"] = True
    try:
        with _quiet_can_logger(quiet):
            bus = can.Bus(interface=interface, channel=channel, **extra)
    except Exception as exc:  # backends raise CanError, OSError, ImportError, ValueError...
        hint = ""
        if isinstance(exc, OSError) and exc.errno == errno.EAFNOSUPPORT:
            hint = " (this kernel has no SocketCAN support)"
        raise BusError(f"cannot open CAN {where}: {one_line(exc)}{hint}") from None
    log.info("opened %s (%s)", where, bus.channel_info)
    if socketcan:
        _log_fd_capability(str(resolved["channel"]), bool(extra.get("fd", resolved.get("fd"))))
    return bus


def interface_mtu(channel: str) -> int | None:
    """The MTU of network interface `channel` (16: classic CAN, 72: CAN FD), None if the
    kernel does not say (no such interface in /sys, e.g. another network namespace)."""
    try:
        return int(Path("/sys/class/net", channel, "mtu").read_text().strip())
    except (OSError, ValueError):
        return None


def _log_fd_capability(channel: str, fd: bool) -> None:
    """One log line saying whether CAN FD frames can reach the socket."""
    if not fd:
        log.info("%s: socket opened for classic CAN only: CAN FD frames are not received",
                 channel)
        return
    mtu = interface_mtu(channel)
    if mtu == CAN_MTU:
        log.info("%s: classic CAN interface (MTU %d): no CAN FD frame can arrive; "
                 "'ip link set %s mtu %d' makes it CAN FD (where the driver can)",
                 channel, mtu, channel, CANFD_MTU)
    else:
        log.info("%s: CAN FD frames are received (socket FD-enabled, interface MTU %s)",
                 channel, "unknown" if mtu is None else mtu)


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
