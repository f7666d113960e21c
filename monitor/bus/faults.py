"""CAN bus faults: SocketCAN error frames and the kernel's count of dropped frames.

Error frames (linux/can/error.h) carry the error class in the CAN ID and details in the
data bytes. python-can's socketcan interface subscribes to every class and delivers them
as messages with `is_error_frame` set; the class bits (below 0x200) survive its masking of
the ID. `describe_error_frame` names the conditions a test-bench engineer acts on: bus-off,
error-passive and warning levels, controller receive/transmit overflow, restarts, protocol
and transceiver errors, missing ACK, arbitration lost, TX timeout.

`socket_drops` reads SO_MEMINFO's drop counter of a SocketCAN socket: frames the kernel
discarded because the monitor's receive buffer was full (a flood), which no frame on the
bus can reveal.
"""

from __future__ import annotations

import socket
import struct
from typing import Any

import can

__all__ = ["RECEIVE_BUFFER_BYTES", "describe_error_frame", "grow_receive_buffer", "socket_drops"]

# error classes in the CAN ID
_CLASSES = (
    (0x001, "tx_timeout"),
    (0x002, "lost_arbitration"),
    (0x004, "controller"),
    (0x008, "protocol"),
    (0x010, "transceiver"),
    (0x020, "no_ack"),
    (0x040, "bus_off"),
    (0x080, "bus_error"),
    (0x100, "restarted"),
)
# controller status in data[1] (CAN_ERR_CRTL_*)
_CONTROLLER = (
    (0x01, "rx_overflow"),
    (0x02, "tx_overflow"),
    (0x04, "rx_warning"),
    (0x08, "tx_warning"),
    (0x10, "rx_error_passive"),
    (0x20, "tx_error_passive"),
    (0x40, "error_active"),
)

SO_MEMINFO = 55  # include/uapi/asm-generic/socket.h
SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)  # include/uapi/asm-generic/socket.h

RECEIVE_BUFFER_BYTES = 8 * 2**20
"""A receive buffer of about 10,000 CAN frames (a frame's socket buffer costs the kernel
some 800 bytes): several seconds of a busy bus. The kernel's default (net.core.rmem_default,
208 KiB) holds a few hundred. A larger buffer turns a held-up daemon's losses into latency
(`run --receive-buffer-kib`)."""
SK_MEMINFO_DROPS = 8  # index into the u32 array (include/uapi/linux/sock_diag.h)


def describe_error_frame(msg: can.Message) -> list[str]:
    """Names of the conditions an error frame reports, e.g. ['controller/rx_overflow'].

    Never raises: a frame with no known class bit yields ['unknown'].
    """
    cls = int(msg.arbitration_id) & 0x1FF
    data = bytes(msg.data or b"")
    names: list[str] = []
    for bit, name in _CLASSES:
        if not cls & bit:
            continue
        if name == "controller" and len(data) > 1 and data[1]:
            names.extend(f"controller/{n}" for b, n in _CONTROLLER if data[1] & b)
        else:
            names.append(name)
    return names or ["unknown"]


def socket_drops(bus: Any) -> int | None:
    """Frames the kernel dropped on this bus's socket so far, or None if not a SocketCAN bus."""
    sock = getattr(bus, "socket", None)
    if not isinstance(sock, socket.socket):
        return None
    try:
        raw = sock.getsockopt(socket.SOL_SOCKET, SO_MEMINFO, 4 * (SK_MEMINFO_DROPS + 1))
    except OSError:
        return None
    if len(raw) < 4 * (SK_MEMINFO_DROPS + 1):
        return None
    return int(struct.unpack_from("I", raw, 4 * SK_MEMINFO_DROPS)[0])


def grow_receive_buffer(bus: Any, wanted: int = RECEIVE_BUFFER_BYTES) -> int | None:
    """Ask for a `wanted`-byte receive buffer on a SocketCAN bus's socket: past
    net.core.rmem_max with SO_RCVBUFFORCE where the process may (CAP_NET_ADMIN), else up to
    rmem_max with SO_RCVBUF. Returns the buffer the kernel granted (bytes, as it reports
    them: twice the request, for its bookkeeping), or None if not a SocketCAN bus."""
    sock = getattr(bus, "socket", None)
    if not isinstance(sock, socket.socket):
        return None
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, wanted)
    except OSError:  # EPERM without CAP_NET_ADMIN (the hardened unit): capped at rmem_max
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, wanted)
        except OSError:
            return None
    try:
        return int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
    except OSError:
        return None
