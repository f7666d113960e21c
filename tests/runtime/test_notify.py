"""monitor.runtime.notify against real AF_UNIX datagram sockets (no mocks).

Each test binds a SOCK_DGRAM receiver where systemd's notification socket would be, builds
the Notifier from an environment pointing at it and reads back the exact datagrams.
"""

from __future__ import annotations

import logging
import os
import socket
import struct
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from monitor.runtime.notify import NOTIFY_BUFFER_MAX, STATUS_MAX_BYTES, Notifier
from tests.support.paths import ROOT


class Receiver:
    """A bound AF_UNIX datagram socket standing in for the service manager."""

    def __init__(self, address: str | bytes) -> None:
        self.address = address
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        self.sock.bind(address)
        # What systemd does on its notify socket: have the kernel attach the sender's pid.
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_PASSCRED, 1)
        self.sock.settimeout(5.0)

    @property
    def env_value(self) -> str:
        """The $NOTIFY_SOCKET value systemd would export for this socket."""
        if isinstance(self.address, bytes):
            assert self.address.startswith(b"\0")
            return "@" + self.address[1:].decode()
        return self.address

    def recv(self) -> str:
        return self.sock.recv(NOTIFY_BUFFER_MAX + 1).decode("utf-8")

    def recv_with_pid(self) -> tuple[str, int]:
        """A datagram and the sender's pid from SCM_CREDENTIALS (how NotifyAccess=main works)."""
        creds = struct.calcsize("3i")
        data, ancdata, _flags, _addr = self.sock.recvmsg(
            NOTIFY_BUFFER_MAX + 1, socket.CMSG_SPACE(creds)
        )
        pid = -1
        for level, kind, payload in ancdata:
            if level == socket.SOL_SOCKET and kind == socket.SCM_CREDENTIALS:
                pid, _uid, _gid = struct.unpack("3i", payload[:creds])
        return data.decode("utf-8"), pid

    def pending(self) -> list[str]:
        """Everything queued right now, without waiting."""
        out = []
        self.sock.setblocking(False)
        try:
            while True:
                try:
                    out.append(self.sock.recv(NOTIFY_BUFFER_MAX + 1).decode("utf-8"))
                except BlockingIOError:
                    return out
        finally:
            self.sock.settimeout(5.0)

    def close(self) -> None:
        self.sock.close()


def _short_dir(tmp_path: Path) -> Path:
    # sockaddr_un.sun_path holds 107 bytes; pytest's tmp_path can be deeper than that.
    if len(str(tmp_path / "notify.sock")) < 100:
        return tmp_path
    return Path(tempfile.mkdtemp(prefix="notify-", dir="/tmp"))


@pytest.fixture
def receiver(tmp_path: Path) -> Iterator[Receiver]:
    r = Receiver(str(_short_dir(tmp_path) / "notify.sock"))
    yield r
    r.close()


@pytest.fixture
def abstract_receiver() -> Iterator[Receiver]:
    r = Receiver(b"\0motor-monitor-test/" + uuid.uuid4().hex.encode())
    yield r
    r.close()


# -- messages --------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["path", "abstract"])
def test_messages(kind: str, receiver: Receiver, abstract_receiver: Receiver) -> None:
    r = receiver if kind == "path" else abstract_receiver
    n = Notifier.from_environment({"NOTIFY_SOCKET": r.env_value})
    assert n.enabled
    assert not n.watchdog_enabled
    assert n.ready() is True
    assert r.recv() == "READY=1"
    assert n.ready("monitoring vcan0")
    assert r.recv() == "READY=1\nSTATUS=monitoring vcan0"
    assert n.status("frames 1200, rejected 3, lost 0")
    assert r.recv() == "STATUS=frames 1200, rejected 3, lost 0"
    assert n.watchdog()
    assert r.recv() == "WATCHDOG=1"
    assert n.stopping()
    assert r.recv() == "STOPPING=1"
    assert n.stopping("flushing the recording")
    assert r.recv() == "STOPPING=1\nSTATUS=flushing the recording"
    assert n.notify(ERRNO=5, STATUS="bus gone")
    assert r.recv() == "ERRNO=5\nSTATUS=bus gone"
    assert n.extend_timeout(12.5)
    assert r.recv() == "EXTEND_TIMEOUT_USEC=12500000"
    assert n.sent == 8 and n.errors == 0
    assert r.pending() == []


def test_an_abstract_socket_is_named_with_an_at(abstract_receiver: Receiver) -> None:
    env = {"NOTIFY_SOCKET": abstract_receiver.env_value}
    assert env["NOTIFY_SOCKET"].startswith("@")
    n = Notifier.from_environment(env)
    assert n.enabled
    assert "@motor-monitor-test/" in repr(n)


def test_reloading_carries_the_monotonic_clock(receiver: Receiver) -> None:
    n = Notifier.from_environment({"NOTIFY_SOCKET": receiver.env_value})
    before = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
    assert n.reloading("reloading thresholds")
    after = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
    lines = receiver.recv().split("\n")
    assert lines[0] == "RELOADING=1"
    assert lines[1].startswith("MONOTONIC_USEC=")
    assert before <= int(lines[1].split("=", 1)[1]) <= after
    assert lines[2] == "STATUS=reloading thresholds"


def test_status_is_one_bounded_line(receiver: Receiver) -> None:
    n = Notifier.from_environment({"NOTIFY_SOCKET": receiver.env_value})
    assert n.status("frames 10\nrejected 2\r\nlost\x001\ttab")
    assert receiver.recv() == "STATUS=frames 10 rejected 2  lost 1 tab"
    # A multi-line value cannot inject another field.
    assert n.status("ok\nREADY=1")
    assert receiver.recv() == "STATUS=ok READY=1"
    # Long text is cut on a character boundary, within the bound, with an ellipsis.
    assert n.status("é" * 5000)
    got = receiver.recv()
    text = got.removeprefix("STATUS=")
    assert len(text.encode()) <= STATUS_MAX_BYTES
    assert text.endswith("…") and set(text[:-1]) == {"é"}
    assert len(text.encode()) > STATUS_MAX_BYTES - 8
    assert n.notify(READY=True)
    assert receiver.recv() == "READY=1"


def test_invalid_field_names_are_programming_errors(receiver: Receiver) -> None:
    n = Notifier.from_environment({"NOTIFY_SOCKET": receiver.env_value})
    for bad in ({"ready": 1}, {"READY=1\nSTATUS": "x"}, {"": 1}, {"ÉTAT": 1}):
        with pytest.raises(ValueError):
            n.notify(**bad)
    assert not n.notify()  # nothing to send
    assert receiver.pending() == []


def test_socket_is_close_on_exec_and_non_blocking(receiver: Receiver) -> None:
    n = Notifier.from_environment({"NOTIFY_SOCKET": receiver.env_value})
    sock = n._sock
    assert sock is not None
    assert not os.get_inheritable(sock.fileno())
    assert sock.getblocking() is False
    assert sock.type == socket.SOCK_DGRAM and sock.family == socket.AF_UNIX
    n.close()
    assert not n.enabled and not n.ready()


# -- disabled ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "env",
    [
        {},
        {"NOTIFY_SOCKET": ""},
        {"WATCHDOG_USEC": "10000000"},
        {"NOTIFY_SOCKET": "relative/path.sock"},
        {"NOTIFY_SOCKET": "@"},
    ],
)
def test_without_a_usable_notify_socket_everything_is_a_no_op(env: dict[str, str]) -> None:
    n = Notifier.from_environment(env)
    assert not n.enabled
    assert not n.watchdog_enabled
    assert n.watchdog_interval() is None
    assert n.ready("x") is False
    assert n.status("x") is False
    assert n.watchdog() is False
    assert n.stopping() is False
    assert n.reloading() is False
    assert n.maybe_ping(0.0) is False
    assert n.maybe_ping(1e9) is False
    assert n.errors == 0 and n.sent == 0
    assert repr(n) == "Notifier(disabled)"
    n.close()


def test_default_environment_is_os_environ(
    receiver: Receiver, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert not Notifier.from_environment().enabled
    monkeypatch.setenv("NOTIFY_SOCKET", receiver.env_value)
    monkeypatch.setenv("WATCHDOG_USEC", "3000000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    n = Notifier.from_environment()
    assert n.enabled and n.watchdog_interval() == 1.5
    assert n.ready()
    assert receiver.recv() == "READY=1"


# -- watchdog ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("extra", "interval"),
    [
        ({"WATCHDOG_USEC": "10000000"}, 5.0),
        ({"WATCHDOG_USEC": "10000000", "WATCHDOG_PID": str(os.getpid())}, 5.0),
        ({"WATCHDOG_USEC": "10000000", "WATCHDOG_PID": ""}, 5.0),
        ({"WATCHDOG_USEC": "250000"}, 0.125),
        ({"WATCHDOG_USEC": "10000000", "WATCHDOG_PID": str(os.getpid() + 1)}, None),
        ({"WATCHDOG_USEC": "10000000", "WATCHDOG_PID": "1"}, None),
        ({"WATCHDOG_USEC": "10000000", "WATCHDOG_PID": "init"}, None),
        ({"WATCHDOG_USEC": "10s"}, None),
        ({"WATCHDOG_USEC": "0"}, None),
        ({"WATCHDOG_USEC": "-5"}, None),
        ({"WATCHDOG_USEC": ""}, None),
        ({}, None),
    ],
)
def test_watchdog_environment(
    receiver: Receiver, extra: dict[str, str], interval: float | None
) -> None:
    n = Notifier.from_environment({"NOTIFY_SOCKET": receiver.env_value, **extra})
    assert n.enabled
    assert n.watchdog_interval() == interval
    assert n.watchdog_enabled is (interval is not None)
    if interval is None:
        assert n.maybe_ping(0.0) is False
        assert n.maybe_ping(1e6) is False
        assert receiver.pending() == []


def test_watchdog_pid_can_be_given(receiver: Receiver) -> None:
    env = {"NOTIFY_SOCKET": receiver.env_value, "WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "42"}
    assert Notifier.from_environment(env, pid=42).watchdog_interval() == 1.0
    assert Notifier.from_environment(env, pid=43).watchdog_interval() is None


def test_maybe_ping_rate(receiver: Receiver) -> None:
    n = Notifier.from_environment(
        {"NOTIFY_SOCKET": receiver.env_value, "WATCHDOG_USEC": "10000000"}
    )
    assert n.watchdog_interval() == 5.0
    turns = [100.0 + 0.01 * k for k in range(2001)]  # 20 s of a 100 Hz loop
    sent = [t for t in turns if n.maybe_ping(t)]
    # First turn, then every 5 s (half of WatchdogSec=10s).
    assert sent == pytest.approx([100.0, 105.0, 110.0, 115.0, 120.0])
    assert receiver.pending() == ["WATCHDOG=1"] * 5
    # Not before the interval, right at it.
    assert n.maybe_ping(124.99) is False
    assert n.maybe_ping(125.0) is True
    assert receiver.recv() == "WATCHDOG=1"


def test_explicit_watchdog_resets_the_ping_clock(receiver: Receiver) -> None:
    n = Notifier.from_environment(
        {"NOTIFY_SOCKET": receiver.env_value, "WATCHDOG_USEC": "2000000"}
    )
    assert n.watchdog()
    now = time.monotonic()
    assert n.maybe_ping(now + 0.5) is False
    assert n.maybe_ping(now + 1.01) is True
    assert receiver.pending() == ["WATCHDOG=1", "WATCHDOG=1"]


# -- failures ---------------------------------------------------------------------------------


def test_socket_vanishing_mid_run_does_not_raise(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = str(_short_dir(tmp_path) / "gone.sock")
    r = Receiver(path)
    n = Notifier.from_environment({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "1000000"})
    assert n.ready("up")
    assert r.recv() == "READY=1\nSTATUS=up"
    # The manager goes away: socket unlinked and closed.
    os.unlink(path)
    r.close()
    t = time.monotonic() + 10.0
    with caplog.at_level(logging.WARNING, logger="monitor.runtime.notify"):
        assert n.status("still running") is False
        assert n.watchdog() is False
        assert n.maybe_ping(t) is False
        assert n.stopping() is False
    assert n.errors == 4
    warnings = [rec for rec in caplog.records if rec.levelno >= logging.WARNING]
    assert len(warnings) == 1, "logged once, not once per message"
    assert "gone.sock" in warnings[0].getMessage()
    # The manager comes back at the same address (daemon-reexec): notifications resume.
    r2 = Receiver(path)
    try:
        assert n.status("back") is True
        assert r2.recv() == "STATUS=back"
        assert n.maybe_ping(t + 0.25) is False  # the failed ping still counted for the rate
        assert n.maybe_ping(t + 0.5) is True
        assert r2.recv() == "WATCHDOG=1"
    finally:
        r2.close()


def test_socket_that_never_existed(tmp_path: Path) -> None:
    n = Notifier.from_environment({"NOTIFY_SOCKET": str(tmp_path / "nothing.sock")})
    assert n.enabled
    assert n.ready() is False
    assert n.errors == 1


def test_full_queue_drops_pings_and_waits_bounded_for_state_changes(receiver: Receiver) -> None:
    n = Notifier.from_environment({"NOTIFY_SOCKET": receiver.env_value}, timeout=0.2)
    # Fill the receiver's queue (net.unix.max_dgram_qlen / the send buffer) without reading.
    for _ in range(100_000):
        if not n.watchdog():
            break
    else:
        pytest.fail("the datagram queue never filled up")
    queued = n.sent
    assert queued > 0 and n.errors == 1
    t0 = time.monotonic()
    assert n.status("dropped") is False  # tried once
    assert time.monotonic() - t0 < 0.1
    t0 = time.monotonic()
    assert n.ready() is False  # retried for `timeout`, then given up
    assert 0.2 <= time.monotonic() - t0 < 2.0
    # A manager that catches up in time gets the state change.
    n.timeout = 5.0
    drained: list[str] = []
    drain = threading.Timer(0.1, lambda: drained.extend(receiver.pending()))
    drain.start()
    try:
        assert n.stopping("flushing") is True
    finally:
        drain.join()
    got = drained + receiver.pending()
    assert got == ["WATCHDOG=1"] * queued + ["STOPPING=1\nSTATUS=flushing"]


# -- end to end -------------------------------------------------------------------------------

CHILD = textwrap.dedent(
    """
    import os
    from monitor.runtime.notify import Notifier

    n = Notifier.from_environment()
    assert n.enabled, os.environ.get("NOTIFY_SOCKET")
    print(n.watchdog_interval(), flush=True)
    n.ready("monitoring vcan0")
    n.status("frames 100\\nrejected 0")
    sent = [n.maybe_ping(t) for t in (8.0, 8.0625, 8.125, 8.1875)]
    n.stopping("flushing the recording")
    print(sent, n.sent, n.errors, flush=True)
    """
)


@pytest.mark.parametrize("kind", ["path", "abstract"])
def test_end_to_end_subprocess(
    kind: str, receiver: Receiver, abstract_receiver: Receiver
) -> None:
    r = receiver if kind == "path" else abstract_receiver
    env = {k: v for k, v in os.environ.items() if k not in ("WATCHDOG_PID", "NOTIFY_SOCKET")}
    env.update(NOTIFY_SOCKET=r.env_value, WATCHDOG_USEC="250000")
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD],
        env=env,
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    got = [r.recv_with_pid() for _ in range(5)]
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert out.split("\n")[:2] == ["0.125", "[True, False, True, False] 5 0"]
    assert [text for text, _ in got] == [
        "READY=1\nSTATUS=monitoring vcan0",
        "STATUS=frames 100 rejected 0",
        "WATCHDOG=1",
        "WATCHDOG=1",
        "STOPPING=1\nSTATUS=flushing the recording",
    ]
    # The kernel-attached sender pid is the child's: NotifyAccess=main would accept them.
    assert {pid for _, pid in got} == {proc.pid}
    assert r.pending() == []


def test_child_with_another_watchdog_pid_does_not_ping(receiver: Receiver) -> None:
    env = dict(os.environ, NOTIFY_SOCKET=receiver.env_value, WATCHDOG_USEC="200000",
               WATCHDOG_PID=str(os.getpid()))  # the watchdog is ours, not the child's
    code = (
        "from monitor.runtime.notify import Notifier\n"
        "n = Notifier.from_environment()\n"
        "print(n.watchdog_interval(), n.maybe_ping(0.0), n.status('child'))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, cwd=ROOT, capture_output=True, text=True,
        timeout=60, check=True,
    ).stdout
    assert out.split() == ["None", "False", "True"]
    assert receiver.pending() == ["STATUS=child"]
