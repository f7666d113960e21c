"""The daemon's socket receive buffer: grown past the kernel's default so that a daemon held
up for a moment catches up instead of losing frames (on a real socket of this kernel)."""

from __future__ import annotations

import socket
from types import SimpleNamespace

from monitor.bus.faults import RECEIVE_BUFFER_BYTES, grow_receive_buffer


def test_the_receive_buffer_grows_past_the_default() -> None:
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        default = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        granted = grow_receive_buffer(SimpleNamespace(socket=sock))
        assert granted == sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        assert granted is not None and granted >= default
        with open("/proc/sys/net/core/rmem_max") as f:
            rmem_max = int(f.read())
        # the whole request where the process may exceed rmem_max (CAP_NET_ADMIN), else the cap
        assert granted >= 2 * min(RECEIVE_BUFFER_BYTES, rmem_max)


def test_a_bus_without_a_socket_is_left_alone() -> None:
    assert grow_receive_buffer(SimpleNamespace()) is None
    assert grow_receive_buffer(SimpleNamespace(socket="not a socket")) is None
