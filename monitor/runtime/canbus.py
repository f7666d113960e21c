"""Opening a python-can bus, and moving frames on it, for the monitor and the virtual ECU
alike.

What the command line leaves out (interface, channel) comes from python-can's own
configuration: CAN_INTERFACE / CAN_CHANNEL / CAN_CONFIG, ~/.canrc, can.rc.

SocketCAN is opened CAN FD-capable (python-can's ``fd=True``: the CAN_RAW_FD_FRAMES socket
option), unless the configuration says ``fd`` itself. Without it the kernel never hands
an FD frame to the socket, so FD frames would vanish uncounted. On a classic-only
interface (MTU 16) the option is still accepted: the socket reads and sends classic frames
as before, and no FD frame can arrive (the log says so once).

`receive_batch` and `send_frame` move frames with python-can's own SocketCAN frame codec
(`capture_message`, `build_can_frame`) but one system call per frame where ``bus.recv`` and
``bus.send`` make three (a clock read, a ``select``, the transfer): on a Raspberry Pi beside a
rig, or a User-Mode Linux guest where a system call costs some 0.3 ms, that is most of the
monitor's and the virtual ECU's CPU. Other interfaces go through python-can as they are.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import select
import socket
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Final

import can
from can.interfaces.socketcan.socketcan import SocketcanBus, build_can_frame, capture_message

from monitor.errors import MonitorError, one_line

__all__ = ["CANFD_MTU", "CAN_MTU", "BusError", "frames_waiting", "interface_mtu", "open_bus",
           "receive_batch", "send_frame"]

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


def _raw_socket(bus: can.BusABC) -> tuple[socket.socket, str] | None:
    """The CAN_RAW socket and interface name of a SocketCAN bus bound to one interface and
    without software filters (whose frames python-can hands on as they come), else None."""
    if not isinstance(bus, SocketcanBus) or not bus.channel or bus.filters:
        return None
    sock = bus.socket
    return (sock, str(bus.channel)) if isinstance(sock, socket.socket) else None


def frames_waiting(bus: can.BusABC) -> bool:
    """Whether a SocketCAN socket holds a frame not yet read (a select without waiting);
    False where that cannot be asked (another interface, a failed select)."""
    raw = _raw_socket(bus)
    if raw is None:
        return False
    try:
        ready, _, _ = select.select([raw[0]], [], [], 0.0)
    except (OSError, ValueError):  # ValueError: a socket closed under us
        return False
    return bool(ready)


def receive_batch(bus: can.BusABC, timeout: float, limit: int, into: list[can.Message]) -> None:
    """Append up to `limit` frames to `into`: waits up to `timeout` for the first, then takes
    what the socket already holds without waiting (none on a timeout). Raises `can.CanError`
    as ``bus.recv`` does, e.g. when the interface goes down, with the frames read before
    the failure already in `into`. Leaves a SocketCAN socket non-blocking."""
    start = len(into)
    raw = _raw_socket(bus)
    if raw is None:
        msg = bus.recv(timeout=timeout)
        while msg is not None:
            into.append(msg)
            if len(into) - start >= limit:
                break
            msg = bus.recv(timeout=0.0)
        return
    sock, channel = raw
    try:
        ready, _, _ = select.select([sock], [], [], timeout)
    except OSError as exc:
        raise can.CanOperationError(f"Failed to receive: {exc.strerror}", exc.errno) from exc
    if not ready:
        return
    if sock.getblocking():  # once: python-can's own recv and send select() first anyway
        sock.setblocking(False)
    while len(into) - start < limit:
        try:
            msg = capture_message(sock)
        except can.CanOperationError as exc:
            if exc.error_code in (errno.EAGAIN, errno.EWOULDBLOCK):
                break  # the socket is empty
            raise
        if msg is None:
            break
        msg.channel = channel
        into.append(msg)


def send_frame(bus: can.BusABC, msg: can.Message, timeout: float) -> None:
    """``bus.send(msg, timeout)``; on SocketCAN first one non-blocking send of python-can's
    encoding of `msg`, and python-can's waiting send only if the kernel's queue is full."""
    raw = _raw_socket(bus)
    if raw is not None:
        sock = raw[0]
        data = build_can_frame(msg)
        try:
            if sock.send(data, socket.MSG_DONTWAIT) == len(data):
                return
        except (BlockingIOError, InterruptedError):
            pass
        except OSError as exc:
            if exc.errno != errno.ENOBUFS:
                raise can.CanOperationError(f"Failed to transmit: {exc.strerror}",
                                            exc.errno) from exc
    bus.send(msg, timeout=timeout)
