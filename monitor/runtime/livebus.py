"""The daemon's bus: opened first, reopened after a failure, received on from the start.

`LiveBus` holds the current python-can bus, or None while the interface is down, and
reopens it with the same settings. `EarlyReceiver` receives on a freshly opened bus in a
thread while the daemon is still loading its estimator (the numerical libraries and the
compiled kernels take a second on a PC and several on a small ARM computer or in a
User-Mode Linux guest): a socket's receive buffer holds a few hundred frames, so without it
the frames of those seconds would be dropped by the kernel before the daemon first reads.
The daemon's loop then takes the frames received so far as its first batch and goes on
reading the same socket itself, so the order of frames and their kernel time stamps are
those of the bus.
"""

from __future__ import annotations

import logging
import threading
from contextlib import suppress

import can

from monitor.bus.faults import grow_receive_buffer
from monitor.runtime.canbus import BusError, open_bus, receive_batch, send_frame

__all__ = ["MAX_EARLY_FRAMES", "EarlyReceiver", "LiveBus", "open_early"]

log = logging.getLogger(__name__)

#: Frames an `EarlyReceiver` keeps at most (some 40 s of a saturated 1 Mbit/s bus; about
#: 100 MiB): past it, it stops reading and the kernel drops what follows, counted as the
#: socket's drops like any other.
MAX_EARLY_FRAMES = 1 << 18
_BATCH = 512  # frames per receive
_WAIT_S = 0.05  # how long a receive waits, i.e. how soon `handover` returns


class LiveBus:
    """The current bus (`bus`), or None while the interface is down; `reopen` opens it.

    `receive_buffer_kib`: the socket's receive buffer asked for at every (re)open (None:
    the kernel's default); where the kernel grants less, the log says why once per open.
    """

    def __init__(self, interface: str | None, channel: str | None, bitrate: int | None,
                 receive_buffer_kib: int | None = None) -> None:
        self.interface = interface
        self.channel = channel
        self.bitrate = bitrate
        self.receive_buffer_kib = receive_buffer_kib
        self.bus: can.BusABC | None = None

    def reopen(self) -> None:
        """Open the bus (raises `BusError` with one line when it cannot be). python-can's own
        error record would be a second line: it is left out unless the log shows debug."""
        self.bus = open_bus(self.interface, self.channel, self.bitrate,
                            quiet=not log.isEnabledFor(logging.DEBUG))
        wanted = self.receive_buffer_kib
        if wanted is None:
            return
        granted = grow_receive_buffer(self.bus, wanted * 1024)
        if granted is not None and granted < 2 * wanted * 1024:
            log.warning("socket receive buffer %d KiB, not the %d KiB asked for: the kernel "
                        "caps it at net.core.rmem_max (raise that sysctl)", granted // 2048,
                        wanted)

    def send(self, msg: can.Message) -> None:
        if self.bus is None:
            raise can.CanOperationError("interface is down")
        send_frame(self.bus, msg, 0.01)

    def drop(self) -> None:
        """Close the bus (if open); a close that fails is of no consequence."""
        if self.bus is not None:
            with suppress(Exception):
                self.bus.shutdown()
        self.bus = None


class EarlyReceiver:
    """Receives on `live`'s open bus in a thread until `handover`.

    A receive that fails (the interface went down) ends the thread; `handover` returns
    the failure with the frames read before it, for the daemon's loop to treat as a failure
    of its own receive. At most `MAX_EARLY_FRAMES` are kept.
    """

    def __init__(self, live: LiveBus) -> None:
        if live.bus is None:
            raise ValueError("EarlyReceiver needs an open bus")
        self._bus = live.bus
        self.frames: list[can.Message] = []
        self.failure: Exception | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._receive, name="early-receive",
                                        daemon=True)
        self._thread.start()

    def _receive(self) -> None:
        while not self._stop.is_set() and len(self.frames) < MAX_EARLY_FRAMES:
            try:
                room = MAX_EARLY_FRAMES - len(self.frames)
                receive_batch(self._bus, _WAIT_S, min(_BATCH, room), self.frames)
            except (can.CanError, OSError) as exc:
                self.failure = exc
                return

    def handover(self) -> tuple[list[can.Message], Exception | None]:
        """Stop receiving (within one wait) and return the frames received, in order, and
        the failure that ended the receiving, if one did; later calls return no frames."""
        self._stop.set()
        self._thread.join()
        frames, self.frames = self.frames, []
        return frames, self.failure


def open_early(live: LiveBus) -> EarlyReceiver | None:
    """`live` opened and received on at once, or None where it cannot be opened yet (left
    closed): the caller opens it again later, where its failure is reported (after the
    configuration's own mistakes, which come first)."""
    try:
        live.reopen()
    except BusError as exc:
        log.debug("bus not opened early: %s", exc)
        return None
    return EarlyReceiver(live)
