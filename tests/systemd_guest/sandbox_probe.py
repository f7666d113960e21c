"""Probe a systemd sandbox from the inside: one line ``PROBE name=outcome`` per attempt.

Run in the guest (tests/systemd_guest) by dropins/sandbox-probe.conf as an ExecStartPre=
of motor-monitor@vcan0.service (so with all of the unit's settings), and once as plain
root outside any sandbox for comparison. ``outcome`` is ``ok`` (allowed, sometimes with a
detail: ``ok:...``) or ``refused:ERRNO`` (the call failed with that errno). Standard
library only; exits 0 whatever it finds (the host judges the outcomes).

    sandbox_probe.py [--udp]

``--udp``: only send one UDP datagram to 127.0.0.1 (for IPAddressDeny=; the guest runs
this with its own /usr/bin/python3, under ``systemd-run``).
"""

from __future__ import annotations

import ctypes
import errno
import mmap
import os
import socket
import sys
from collections.abc import Callable

LIBC = ctypes.CDLL(None, use_errno=True)
LIBC.mmap.restype = ctypes.c_void_p
LIBC.mmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int,
                      ctypes.c_int, ctypes.c_long]
LIBC.mprotect.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
CLONE_NEWUSER = 0x10000000
READ_IMPLIES_EXEC = 0x0400000
PAGE = mmap.PAGESIZE


def report(name: str, fn: Callable[[], object]) -> None:
    try:
        detail = fn()
    except OSError as exc:
        code = exc.errno if exc.errno is not None else 0
        outcome = f"refused:{errno.errorcode.get(code, code)}"
    except Exception as exc:  # anything else is a probe bug: say so
        outcome = f"error:{type(exc).__name__}:{exc}"
    else:
        outcome = "ok" if detail is None else f"ok:{detail}"
    print(f"PROBE {name}={outcome}", flush=True)


def _check(ret: int) -> int:
    if ret == -1:
        code = ctypes.get_errno()
        raise OSError(code, os.strerror(code))
    return ret


def write_file(path: str) -> None:
    with open(path, "w") as fh:
        fh.write("probe\n")
    os.unlink(path)


def scratch() -> str:
    """A directory the probe may write: the unit's state directory, else /tmp."""
    return os.environ.get("STATE_DIRECTORY", "/tmp").split(":")[0]


def write_scratch() -> str:
    """Create a file where the unit may write; its mode shows UMask=."""
    path = os.path.join(scratch(), f".probe-{os.getpid()}")
    with open(path, "w") as fh:
        fh.write("probe\n")
    mode = os.stat(path).st_mode & 0o7777
    os.unlink(path)
    return f"{mode:04o}"


def setuid_bit() -> None:
    path = os.path.join(scratch(), f".probe-suid-{os.getpid()}")
    with open(path, "w"):
        pass
    try:
        os.chmod(path, 0o4755)
    finally:
        os.unlink(path)


def namespaces() -> str:
    return ",".join(f"{ns}={os.readlink(f'/proc/self/ns/{ns}').split(':')[1].strip('[]')}"
                    for ns in ("mnt", "user", "uts", "net"))


def mount_options(target: str) -> str:
    """"ro" or "rw" for the mount at target (the last one), "none" if not a mount point."""
    found = "none"
    with open("/proc/self/mountinfo") as fh:
        for line in fh:
            fields = line.split()
            if fields[4] == target:
                found = fields[5].split(",")[0]
    return found


def wx_mmap() -> None:
    m = mmap.mmap(-1, PAGE, prot=mmap.PROT_READ | mmap.PROT_WRITE | mmap.PROT_EXEC)
    m.close()


def wx_mprotect() -> None:
    prot_rw = mmap.PROT_READ | mmap.PROT_WRITE
    addr = LIBC.mmap(None, PAGE, prot_rw, mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS, -1, 0)
    if addr in (None, ctypes.c_void_p(-1).value):
        raise OSError(ctypes.get_errno(), "mmap")
    _check(LIBC.mprotect(addr, PAGE, prot_rw | mmap.PROT_EXEC))


def open_socket(family: int, kind: int, proto: int = 0) -> None:
    socket.socket(family, kind, proto).close()


def udp_send() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.sendto(b"probe", ("127.0.0.1", 9))


def in_child(call: Callable[[], int]) -> Callable[[], None]:
    """Run a call that changes the process (namespaces, personality) in a child."""
    def run() -> None:
        pid = os.fork()
        if pid == 0:
            try:
                _check(call())
            except OSError as exc:
                os._exit(exc.errno or 1)
            os._exit(0)
        _, status = os.waitpid(pid, 0)
        code = os.waitstatus_to_exitcode(status)
        if code:
            raise OSError(code, os.strerror(code))
    return run


def proc_status() -> str:
    wanted = ("Uid", "NoNewPrivs", "Seccomp", "CapEff", "CapBnd")
    fields = {}
    with open("/proc/self/status") as fh:
        for line in fh:
            key, _, value = line.partition(":")
            if key in wanted:
                fields[key] = value.split()[0]
    return ",".join(f"{k}={fields.get(k, '?')}" for k in wanted)


def main(argv: list[str]) -> int:
    if "--udp" in argv:
        report("udp_send", udp_send)
        return 0
    report("status", proc_status)
    report("namespaces", namespaces)
    report("write_state_directory", write_scratch)
    report("write_etc", lambda: write_file(f"/etc/.probe-{os.getpid()}"))
    report("write_var_lib", lambda: write_file(f"/var/lib/.probe-{os.getpid()}"))
    report("list_root_home", lambda: len(os.listdir("/root")))
    report("wx_mmap", wx_mmap)
    report("wx_mprotect", wx_mprotect)
    report("af_inet", lambda: open_socket(socket.AF_INET, socket.SOCK_DGRAM))
    report("af_inet6", lambda: open_socket(socket.AF_INET6, socket.SOCK_DGRAM))
    report("af_packet", lambda: open_socket(socket.AF_PACKET, socket.SOCK_DGRAM))
    report("af_can", lambda: open_socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW))
    report("af_netlink", lambda: open_socket(socket.AF_NETLINK, socket.SOCK_RAW, 0))
    report("setpriority", lambda: os.setpriority(os.PRIO_PROCESS, 0, 1))
    report("unshare_user", in_child(lambda: LIBC.unshare(CLONE_NEWUSER)))
    report("personality", in_child(lambda: LIBC.personality(READ_IMPLIES_EXEC)))
    report("setuid_bit", setuid_bit)
    report("tmp", lambda: f"{os.stat('/tmp').st_dev}:{os.stat('/tmp').st_ino}")
    report("list_kernel_modules", lambda: len(os.listdir("/usr/lib/modules")))
    report("proc_meminfo", lambda: os.stat("/proc/meminfo").st_size)
    report("proc_pid1", lambda: os.stat("/proc/1").st_uid)
    report("dev_entries", lambda: len(os.listdir("/dev")))
    report("cgroup_mount", lambda: mount_options("/sys/fs/cgroup"))
    report("sys_mount", lambda: mount_options("/sys"))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
