"""`motor-monitor` started as a service manager starts it: under a notify socket."""

from __future__ import annotations

import socket
import subprocess
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import IO

from tests.support import BIN

__all__ = ["notified_daemon"]


@contextmanager
def notified_daemon(args: Sequence[str], notify: Path, env: Mapping[str, str], *,
                    stdout: IO[str] | int = subprocess.PIPE
                    ) -> Iterator[tuple[subprocess.Popen[str], socket.socket]]:
    """`motor-monitor ARGS` with `env` and ``NOTIFY_SOCKET`` naming an AF_UNIX datagram
    socket bound at `notify` (the service manager's end): the process (stderr piped, text) and
    that socket. On leaving, a process still running is killed (a failed test leaves no
    daemon behind) and the socket closed."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        sock.bind(str(notify))
        proc = subprocess.Popen([str(BIN / "motor-monitor"), *args],
                                env=dict(env, NOTIFY_SOCKET=str(notify)), stdout=stdout,
                                stderr=subprocess.PIPE, text=True)
        try:
            yield proc, sock
        finally:
            if proc.poll() is None:
                proc.kill()
    finally:
        sock.close()
