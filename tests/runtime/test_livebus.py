"""The daemon's early receiver on python-can's virtual interface: what it received while the
daemon loaded is handed over whole and in order, a failure with the frames before it, and a
bus that cannot be opened yet is left for later (the SocketCAN path runs in every daemon of
the vcan tests)."""

from __future__ import annotations

import time
import uuid
from collections.abc import Iterator

import can
import pytest

from monitor.runtime import livebus
from monitor.runtime.livebus import EarlyReceiver, LiveBus, open_early


def _frames(n: int) -> list[can.Message]:
    return [can.Message(arbitration_id=0x100 + i % 7, data=i.to_bytes(4, "little"),
                        is_extended_id=False) for i in range(n)]


def _numbers(msgs: list[can.Message]) -> list[int]:
    return [int.from_bytes(m.data, "little") for m in msgs]


@pytest.fixture
def channel() -> Iterator[tuple[str, can.BusABC]]:
    """A virtual channel of its own and a sender on it."""
    name = f"early-{uuid.uuid4().hex}"
    sender = can.Bus(interface="virtual", channel=name)
    yield name, sender
    sender.shutdown()


def _sent_while_loading(channel: tuple[str, can.BusABC], n: int
                        ) -> tuple[LiveBus, EarlyReceiver]:
    """A bus opened early on `channel`, then `n` numbered frames sent on it."""
    live = LiveBus("virtual", channel[0], None)
    early = open_early(live)
    assert live.bus is not None and early is not None
    for msg in _frames(n):
        channel[1].send(msg)
    time.sleep(0.3)  # the thread takes them off the bus meanwhile
    return live, early


def test_frames_received_while_loading_are_handed_over_in_order(
        channel: tuple[str, can.BusABC]) -> None:
    live, early = _sent_while_loading(channel, 3000)
    try:
        frames, failure = early.handover()
        assert failure is None
        assert _numbers(frames) == list(range(3000))
        assert early.handover() == ([], None)  # once
        # the daemon's loop goes on reading the same bus: nothing is taken after handover
        channel[1].send(_frames(1)[0])
        assert live.bus is not None and live.bus.recv(timeout=1.0) is not None
    finally:
        live.drop()


def test_a_failed_receive_ends_it_with_the_frames_before(
        channel: tuple[str, can.BusABC]) -> None:
    live, early = _sent_while_loading(channel, 10)
    assert live.bus is not None
    live.bus.shutdown()  # the interface goes away under the receiver
    time.sleep(0.2)  # its next receive fails
    frames, failure = early.handover()
    assert _numbers(frames) == list(range(10))
    assert isinstance(failure, can.CanError | OSError)


def test_it_keeps_at_most_its_limit(monkeypatch: pytest.MonkeyPatch,
                                    channel: tuple[str, can.BusABC]) -> None:
    monkeypatch.setattr(livebus, "MAX_EARLY_FRAMES", 100)
    live, early = _sent_while_loading(channel, 250)
    try:
        frames, _ = early.handover()
        assert _numbers(frames) == list(range(100))  # the first, not a random hundred
        assert live.bus is not None and live.bus.recv(timeout=1.0) is not None  # left queued
    finally:
        live.drop()


def test_a_bus_that_cannot_open_yet_is_left_for_later() -> None:
    live = LiveBus("no-such-interface", "x", None)
    assert open_early(live) is None
    assert live.bus is None
