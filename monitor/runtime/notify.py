"""The sd_notify protocol in plain Python (no python-systemd, no libsystemd).

A service started by systemd with ``Type=notify`` finds ``$NOTIFY_SOCKET`` in its
environment and reports its state by sending datagrams to that AF_UNIX socket. The
semantics are those of sd_notify(3):

* The message is a single datagram of newline-separated ``KEY=value`` assignments, e.g.
  ``READY=1\\nSTATUS=listening on vcan0``. The service manager reads at most PIPE_BUF
  (4096) bytes and ignores longer datagrams and datagrams containing NUL bytes.
* ``READY=1`` ends the start-up of a ``Type=notify`` unit (``systemctl start`` returns,
  dependent units start). ``STOPPING=1`` tells that the service is shutting down,
  ``RELOADING=1`` that it reloads its configuration (it sends ``READY=1`` when done).
  ``STATUS=...`` is a free-form single-line status shown by ``systemctl status``.
  ``WATCHDOG=1`` keeps the watchdog of a unit with ``WatchdogSec=`` alive;
  ``EXTEND_TIMEOUT_USEC=...`` pushes the start/stop timeout further away.
* ``$NOTIFY_SOCKET`` is an absolute file-system path or, when it starts with ``@``, a
  socket in the abstract namespace (the ``@`` stands for a leading NUL byte).
* ``$WATCHDOG_USEC`` is the watchdog timeout in microseconds. ``$WATCHDOG_PID``, if set,
  names the process the watchdog applies to: any other process (a child that inherited
  the environment) must not ping. sd_watchdog_enabled(3) recommends pinging at half the
  timeout; :meth:`Notifier.watchdog_interval` is that half.
* Without ``$NOTIFY_SOCKET`` (not started by systemd, or ``Type=simple``) every call is a
  no-op: the same daemon runs unchanged from a shell.

With ``NotifyAccess=main`` systemd accepts messages only from the unit's main process; it
identifies the sender by the SCM_CREDENTIALS the kernel attaches to the datagram, so the
daemon itself (not a helper process) must send them.

Nothing here raises into the caller's loop for an I/O problem: a vanished socket (the
manager re-executing, a test closing its receiver) or a full socket queue is logged once
(again only after the next success), counted in :attr:`Notifier.errors`, and the next
call tries again. The socket is created once, close-on-exec and non-blocking. Messages
that change the unit's state (``READY``, ``STOPPING``, ``RELOADING``) are retried for up to
``timeout`` seconds while the manager's queue is full; ``WATCHDOG`` and ``STATUS`` are
sent once and dropped otherwise (the next ones follow shortly).

Usage in a daemon::

    notifier = Notifier.from_environment()
    ...                                   # open the bus, load the model
    notifier.ready("monitoring vcan0")
    while running:
        ...                               # one loop turn
        notifier.maybe_ping(time.monotonic())
    notifier.stopping("flushing the recording")
"""

from __future__ import annotations

import errno
import logging
import os
import re
import socket
import time
from collections.abc import Mapping

from monitor.errors import FailureBurst

__all__ = ["NOTIFY_BUFFER_MAX", "STATUS_MAX_BYTES", "Notifier"]

log = logging.getLogger(__name__)

#: The service manager reads notification datagrams into a PIPE_BUF-sized buffer and
#: ignores longer ones (systemd src/core/manager.c, NOTIFY_BUFFER_MAX).
NOTIFY_BUFFER_MAX = 4096
#: STATUS= text is cut to this many UTF-8 bytes (on a character boundary, with an ellipsis).
STATUS_MAX_BYTES = 1024
#: Any other value is cut to this many bytes.
VALUE_MAX_BYTES = 1024

# Fields whose loss would leave the unit in the wrong state: retried while the queue is full.
_STATE_FIELDS = frozenset({"READY", "STOPPING", "RELOADING"})
# Control characters (NUL included: systemd drops a datagram containing NUL) become spaces.
_CONTROL = {c: " " for c in (*range(0x20), 0x7F)}
_KEY = re.compile(r"[A-Z][A-Z0-9_]*")


def _sanitise(value: object, max_bytes: int) -> str:
    """One line of at most ``max_bytes`` UTF-8 bytes: control characters become spaces."""
    if isinstance(value, bool):
        value = int(value)
    text = str(value).translate(_CONTROL)
    raw = text.encode("utf-8", "replace")
    if len(raw) <= max_bytes:
        return raw.decode("utf-8")
    ellipsis = "…".encode()
    cut = raw[: max_bytes - len(ellipsis)].decode("utf-8", "ignore")
    return cut + "…"


def _parse_address(value: str) -> bytes | None:
    """``$NOTIFY_SOCKET`` -> a socket address, None if unusable (sd_notify(3) rules)."""
    if len(value) < 2:
        return None
    if value.startswith("@"):
        return b"\0" + os.fsencode(value[1:])
    if value.startswith("/"):
        return os.fsencode(value)
    return None  # relative paths and other schemes (vsock: is systemd >= 253) are not used


def _parse_watchdog(env: Mapping[str, str], pid: int) -> int | None:
    """``$WATCHDOG_USEC`` if it applies to ``pid`` (sd_watchdog_enabled(3)), else None."""
    usec_text = env.get("WATCHDOG_USEC")
    if not usec_text:
        return None
    pid_text = env.get("WATCHDOG_PID")
    if pid_text:
        try:
            watchdog_pid = int(pid_text)
        except ValueError:
            log.warning("ignoring the watchdog: WATCHDOG_PID=%r is not a number", pid_text)
            return None
        if watchdog_pid != pid:
            return None  # the watchdog belongs to another process (our parent)
    try:
        usec = int(usec_text)
    except ValueError:
        log.warning("ignoring the watchdog: WATCHDOG_USEC=%r is not a number", usec_text)
        return None
    if usec <= 0:
        log.warning("ignoring the watchdog: WATCHDOG_USEC=%r is not positive", usec_text)
        return None
    return usec


class Notifier:
    """Sends sd_notify(3) messages to the service manager; a no-op without NOTIFY_SOCKET.

    Build it with :meth:`from_environment`. Every sending method returns True when the
    datagram went out, False when disabled or when sending failed (never raises for I/O).
    """

    def __init__(
        self,
        address: bytes | None,
        watchdog_usec: int | None = None,
        *,
        timeout: float = 1.0,
    ) -> None:
        """``address``: a socket address (abstract: leading NUL), None = disabled.

        ``watchdog_usec``: the watchdog timeout (``$WATCHDOG_USEC``), None = no watchdog.
        ``timeout``: how long READY/STOPPING/RELOADING wait for room in a full queue.
        """
        self.address = address
        self.watchdog_usec = watchdog_usec if address is not None else None
        self.timeout = timeout
        #: Datagrams that could not be sent.
        self.errors = 0
        #: Datagrams sent.
        self.sent = 0
        self._last_ping: float | None = None
        self._burst = FailureBurst(log, "sd_notify: the notification socket works again",
                                   level=logging.WARNING)
        self._sock: socket.socket | None = None
        if address is not None:
            try:
                self._sock = socket.socket(
                    socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC | socket.SOCK_NONBLOCK
                )
            except OSError as exc:  # out of descriptors: run without notifications
                log.warning("sd_notify disabled: cannot create a socket: %s", exc)
                self.address = None
                self.watchdog_usec = None

    @classmethod
    def from_environment(
        cls,
        env: Mapping[str, str] | None = None,
        *,
        pid: int | None = None,
        timeout: float = 1.0,
    ) -> Notifier:
        """Read ``$NOTIFY_SOCKET``, ``$WATCHDOG_USEC`` and ``$WATCHDOG_PID``.

        ``env`` defaults to :data:`os.environ`, ``pid`` (the process the watchdog must
        belong to) to :func:`os.getpid`.
        """
        if env is None:
            env = os.environ
        raw = env.get("NOTIFY_SOCKET", "")
        address = _parse_address(raw) if raw else None
        if raw and address is None:
            log.warning("sd_notify disabled: unusable NOTIFY_SOCKET=%r", raw)
        if address is None:
            return cls(None, timeout=timeout)
        watchdog = _parse_watchdog(env, os.getpid() if pid is None else pid)
        return cls(address, watchdog, timeout=timeout)

    @classmethod
    def disabled(cls) -> Notifier:
        """A notifier that does nothing (what ``from_environment`` gives outside systemd)."""
        return cls(None)

    # -- state ----------------------------------------------------------------------------

    @property
    def enabled(self) -> bool:
        """True when there is a notification socket to talk to."""
        return self._sock is not None

    @property
    def watchdog_enabled(self) -> bool:
        """True when the service manager expects WATCHDOG=1 pings from this process."""
        return self._sock is not None and self.watchdog_usec is not None

    def watchdog_interval(self) -> float | None:
        """Seconds between watchdog pings: half of ``$WATCHDOG_USEC``; None = no watchdog."""
        if not self.watchdog_enabled or self.watchdog_usec is None:
            return None
        return self.watchdog_usec / 2e6

    # -- messages -------------------------------------------------------------------------

    def ready(self, status: str | None = None) -> bool:
        """``READY=1`` (start-up finished), with an optional ``STATUS=``."""
        if status is None:
            return self.notify(READY=1)
        return self.notify(READY=1, STATUS=status)

    def status(self, text: str) -> bool:
        """``STATUS=text``: one line (newlines become spaces), at most 1024 bytes."""
        return self.notify(STATUS=text)

    def watchdog(self) -> bool:
        """``WATCHDOG=1`` now (sent even when ``$WATCHDOG_USEC`` is not set)."""
        if self._sock is not None:
            self._last_ping = time.monotonic()
        return self.notify(WATCHDOG=1)

    def maybe_ping(self, now_monotonic: float) -> bool:
        """Send ``WATCHDOG=1`` if :meth:`watchdog_interval` has passed since the last ping.

        Cheap enough for every loop turn (a comparison when no ping is due). The first call
        pings at once. ``now_monotonic`` is :func:`time.monotonic` (the clock systemd's
        watchdog runs on too). Returns True when a ping was sent.
        """
        if self.watchdog_usec is None or self._sock is None:
            return False
        last = self._last_ping
        if last is not None and now_monotonic - last < self.watchdog_usec / 2e6:
            return False
        self._last_ping = now_monotonic  # also on failure: no retry storm in the hot loop
        return self.notify(WATCHDOG=1)

    def stopping(self, status: str | None = None) -> bool:
        """``STOPPING=1`` (shutting down, e.g. flushing the recording after SIGTERM)."""
        if status is None:
            return self.notify(STOPPING=1)
        return self.notify(STOPPING=1, STATUS=status)

    def reloading(self, status: str | None = None) -> bool:
        """``RELOADING=1`` with ``MONOTONIC_USEC`` (send :meth:`ready` when done)."""
        fields: dict[str, object] = {
            "RELOADING": 1,
            "MONOTONIC_USEC": time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000,
        }
        if status is not None:
            fields["STATUS"] = status
        return self.notify(**fields)

    def extend_timeout(self, seconds: float) -> bool:
        """``EXTEND_TIMEOUT_USEC``: the start/stop must finish within ``seconds`` from now."""
        return self.notify(EXTEND_TIMEOUT_USEC=max(0, round(seconds * 1e6)))

    def notify(self, **fields: object) -> bool:
        """Send one datagram of ``KEY=value`` lines in the given order.

        Values are made single-line (control characters become spaces); ``STATUS`` is cut
        to :data:`STATUS_MAX_BYTES`, other values to :data:`VALUE_MAX_BYTES`; booleans are
        sent as 1/0. A malformed key (empty, lower case, with ``=``) is a programming error
        and raises ValueError, even when disabled. Returns True if the datagram was sent.
        """
        lines = []
        for key, value in fields.items():
            if not _KEY.fullmatch(key):
                raise ValueError(f"sd_notify: invalid field name {key!r}")
            limit = STATUS_MAX_BYTES if key == "STATUS" else VALUE_MAX_BYTES
            lines.append(f"{key}={_sanitise(value, limit)}")
        if self._sock is None or not lines:
            return False
        payload = "\n".join(lines).encode("utf-8")
        if len(payload) > NOTIFY_BUFFER_MAX:
            self._failed(f"message of {len(payload)} bytes exceeds {NOTIFY_BUFFER_MAX}")
            return False
        wait = self.timeout if _STATE_FIELDS.intersection(fields) else 0.0
        return self._send(payload, wait)

    def _send(self, payload: bytes, wait: float) -> bool:
        sock, address = self._sock, self.address
        assert sock is not None and address is not None
        deadline: float | None = None
        while True:
            try:
                sock.sendto(payload, socket.MSG_NOSIGNAL, address)
            except BlockingIOError:
                # The manager's queue is full (net.unix.max_dgram_qlen): wait a little.
                now = time.monotonic()
                if deadline is None:
                    deadline = now + wait
                if now >= deadline:
                    self._failed("the notification socket's queue is full")
                    return False
                time.sleep(min(0.005, deadline - now))
                continue
            except OSError as exc:
                reason = errno.errorcode.get(exc.errno or 0, str(exc.errno))
                self._failed(f"{reason}: {exc.strerror or exc}")
                return False
            break
        self.sent += 1
        self._burst.worked()
        return True

    def _failed(self, reason: str) -> None:
        self.errors += 1
        self._burst.failed(f"sd_notify: cannot send to {self._printable_address()!r} ({reason}); "
                           "carrying on without notifications")

    def _printable_address(self) -> str:
        if self.address is None:
            return ""
        if self.address.startswith(b"\0"):
            return "@" + os.fsdecode(self.address[1:])
        return os.fsdecode(self.address)

    # -- lifetime -------------------------------------------------------------------------

    def close(self) -> None:
        """Close the socket; the notifier is disabled afterwards."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> Notifier:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        if self._sock is None:
            return "Notifier(disabled)"
        return (
            f"Notifier({self._printable_address()!r}, watchdog_usec={self.watchdog_usec})"
        )
