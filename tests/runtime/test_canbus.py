"""`receive_batch` and `send_frame` on python-can's virtual interface (the SocketCAN path is
exercised by every daemon and virtual ECU on real vcan:
tests/integration/test_integration_vcan.py)."""

from __future__ import annotations

import uuid

import can

from monitor.runtime.canbus import receive_batch, send_frame


def _pair() -> tuple[can.BusABC, can.BusABC]:
    channel = f"batch-{uuid.uuid4().hex}"
    return (can.Bus(interface="virtual", channel=channel),
            can.Bus(interface="virtual", channel=channel))


def test_batches_keep_order_and_stop_at_the_limit_or_when_empty() -> None:
    tx, rx = _pair()
    try:
        for i in range(100):
            send_frame(tx, can.Message(arbitration_id=0x100 + i % 7, data=bytes([i]),
                                       is_extended_id=False, is_fd=i % 3 == 0), 0.01)
        got: list[can.Message] = []
        receive_batch(rx, 1.0, 64, got)
        assert len(got) == 64
        receive_batch(rx, 1.0, 64, got)  # appended
        assert len(got) == 100
        assert [m.data[0] for m in got] == list(range(100))
        assert [m.is_fd for m in got] == [i % 3 == 0 for i in range(100)]
        receive_batch(rx, 0.05, 64, got)
        assert len(got) == 100
    finally:
        tx.shutdown()
        rx.shutdown()


def test_a_batch_waits_for_its_first_frame_only() -> None:
    tx, rx = _pair()
    try:
        got: list[can.Message] = []
        receive_batch(rx, 0.0, 8, got)
        assert got == []
        send_frame(tx, can.Message(arbitration_id=0x7E0, data=b"\x01", is_extended_id=False),
                   0.01)
        receive_batch(rx, 2.0, 8, got)
        assert [(m.arbitration_id, bytes(m.data)) for m in got] == [(0x7E0, b"\x01")]
    finally:
        tx.shutdown()
        rx.shutdown()
