"""On a classic CAN interface (MTU 16), the monitor's FD-capable socket opens, reads a classic
frame and cannot send an FD frame: prints ``classic_rx=True|False`` and
``fd_sent_on_classic=1|0`` (run by canfd.sh inside the vcan guest; argument: the interface)."""

from __future__ import annotations

import logging
import sys

import can

from monitor.runtime.canbus import open_bus


def main(channel: str) -> None:
    logging.basicConfig(level=logging.INFO)
    rx = open_bus("socketcan", channel)
    tx = open_bus("socketcan", channel)
    tx.send(can.Message(arbitration_id=0x123, data=b"\x01\x02", is_extended_id=False))
    m = rx.recv(timeout=5)
    ok = m is not None and bytes(m.data) == b"\x01\x02" and not m.is_fd
    print(f"classic_rx={ok}")
    try:
        tx.send(can.Message(arbitration_id=0x123, data=bytes(12), is_fd=True,
                            is_extended_id=False))
        print("fd_sent_on_classic=1")
    except can.CanError:
        print("fd_sent_on_classic=0")
    rx.shutdown()
    tx.shutdown()


if __name__ == "__main__":
    main(sys.argv[1])
