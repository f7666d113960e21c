"""Run shell scripts against real SocketCAN ``vcan`` interfaces.

The host kernel of most development and CI machines here is built without CAN, so
``ip link add dev vcan0 type vcan`` fails.  :func:`run_on_vcan` then boots User-Mode Linux
(``/usr/bin/linux.uml``, Debian package ``user-mode-linux``): a real Linux kernel running as an
ordinary process, with the host file system mounted as its root (hostfs), so the project, the
virtual environment and ``/tmp`` are visible inside.  On a host whose kernel does have SocketCAN
the script runs natively instead.  See ``/work/shared/VCAN.md``.

Inside User-Mode Linux the script runs as root (so it can call ``ip link ...``), as a child of
the init (PID 1) ``tests/support/scripts/uml_init.sh``, which mounts proc, sysfs, devtmpfs and a
tmpfs on ``/dev/shm``, loads the CAN modules and brings the requested vcan interfaces up.  Its
stdout, stderr and exit status are written to files in a private temporary directory on the
host and read back after the kernel has powered off; the kernel console goes to a separate log
file in that directory.

Environment knobs (all optional): ``VCAN_HARNESS_BACKEND`` (``native`` or ``uml``: force a
backend), ``VCAN_UML_MEM`` (UML memory, default ``1024M``), ``VCAN_HARNESS_KEEP=1`` (keep the
temporary directory for debugging; its path is printed on stderr).
"""

from __future__ import annotations

import contextlib
import functools
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from tests.support.paths import ROOT, SCRIPTS

__all__ = [
    "VcanResult",
    "VcanSetupError",
    "native_vcan_available",
    "run_on_vcan",
    "uml_available",
    "vcan_unavailable_reason",
]

#: Where `.ci/install-uml.sh` unpacks a newer User-Mode Linux on a host whose CPU Debian 12's
#: kernel cannot run a process on (Intel AMX); absent elsewhere.
UML_PREFIX = Path(os.environ.get("UML_PREFIX", "/opt/motor-monitor-uml"))
_UML_ROOT = UML_PREFIX if os.access(UML_PREFIX / "usr/bin/linux.uml", os.X_OK) else Path("/")
UML_KERNEL = str(_UML_ROOT / "usr/bin/linux.uml")
UML_MODULES_ROOT = _UML_ROOT / "usr/lib/uml/modules"
#: Load order matters: can-raw, can-bcm and can-dev need can.ko; vcan needs can-dev.
UML_MODULES = (
    "net/can/can.ko",
    "net/can/can-raw.ko",
    "net/can/can-bcm.ko",
    "drivers/net/can/dev/can-dev.ko",
    "drivers/net/can/vcan.ko",
)
DEFAULT_UML_MEM = "1024M"
SYSTEM_PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
#: Exit status reported when the script ran out of time (as coreutils ``timeout``).
TIMEOUT_RETURNCODE = 124
#: Extra seconds, past ``timeout``, before the whole UML process group is killed.  Normally the
#: in-guest ``timeout`` fires at the deadline and the guest powers off cleanly well before this.
HARD_KILL_GRACE = 10.0

_IFNAME_RE = re.compile(r"^[A-Za-z0-9_.-]{1,15}$")
_ENV_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
#: Passed into the script's environment when set. The numba cache's: the guest runs the host's
#: virtual environment and source through hostfs, and numba keys its cache by the source's
#: content, directory and the CPU, all the same inside, so the monitor in the guest loads the
#: kernels the install cached (monitor.estimation.kernels_aot) -- from the directory the host
#: uses only if it is told the same one.
_PASSTHROUGH_ENV = ("PYTHONPATH", "VIRTUAL_ENV", "NUMBA_CACHE_DIR", "XDG_CACHE_HOME")


class VcanSetupError(RuntimeError):
    """The vcan environment itself could not be set up (not a failure of the user script)."""


@dataclass(frozen=True)
class VcanResult:
    """Outcome of :func:`run_on_vcan`."""

    returncode: int
    stdout: str
    stderr: str
    backend: str  # "native" or "uml"
    duration: float = 0.0  # wall-clock seconds, including the UML boot


# --------------------------------------------------------------------------- availability


def _find_tool(name: str) -> str | None:
    return shutil.which(name, path=f"{os.environ.get('PATH', '')}:{SYSTEM_PATH}")


def _iface_exists(name: str) -> bool:
    return Path("/sys/class/net", name).exists()


def _host_can_socket_ok() -> bool:
    af_can = getattr(socket, "AF_CAN", None)
    can_raw = getattr(socket, "CAN_RAW", None)
    if af_can is None or can_raw is None:
        return False
    try:
        sock = socket.socket(af_can, socket.SOCK_RAW, can_raw)
    except OSError:
        return False
    sock.close()
    return True


def _ensure_native_iface(name: str) -> str | None:
    """Create (if needed) and bring up a native vcan interface; return an error or None."""
    ip = _find_tool("ip")
    if ip is None:
        return "the `ip` tool (iproute2) is not installed"
    if not _iface_exists(name):
        add = subprocess.run(
            [ip, "link", "add", "dev", name, "type", "vcan"],
            capture_output=True,
            text=True,
            check=False,
        )
        if add.returncode != 0 and not _iface_exists(name):
            return f"`ip link add dev {name} type vcan` failed: {add.stderr.strip()}"
        # CAN FD's MTU, as in the UML guest (`vcan_up` in tests/support/scripts/common.sh)
        subprocess.run([ip, "link", "set", name, "mtu", "72"], capture_output=True,
                       check=False)
    up = subprocess.run(
        [ip, "link", "set", "up", name], capture_output=True, text=True, check=False
    )
    if up.returncode != 0:
        return f"`ip link set up {name}` failed: {up.stderr.strip()}"
    return None


@functools.cache
def native_vcan_available() -> bool:
    """True if the host kernel opens AF_CAN raw sockets and vcan0 exists or can be created."""
    if not _host_can_socket_ok():
        return False
    if _iface_exists("vcan0"):
        return True
    ip = _find_tool("ip")
    if ip is None:
        return False
    add = subprocess.run(
        [ip, "link", "add", "dev", "vcan0", "type", "vcan"],
        capture_output=True,
        check=False,
    )
    return add.returncode == 0 or _iface_exists("vcan0")


@functools.cache
def _uml_modules_dir() -> Path | None:
    """``/usr/lib/uml/modules/<version>/kernel`` for the installed linux.uml, if complete."""
    if not os.access(UML_KERNEL, os.X_OK) or not UML_MODULES_ROOT.is_dir():
        return None
    candidates: list[Path] = []
    try:
        version = subprocess.run(
            [UML_KERNEL, "--version"], capture_output=True, text=True, timeout=10, check=False
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        version = ""
    if version:
        candidates.append(UML_MODULES_ROOT / version / "kernel")
    candidates.extend(sorted(p / "kernel" for p in UML_MODULES_ROOT.iterdir() if p.is_dir()))
    for kernel_dir in candidates:
        if all((kernel_dir / mod).is_file() for mod in UML_MODULES):
            return kernel_dir
    return None


@functools.cache
def uml_available() -> bool:
    """True if linux.uml, its vcan modules and the tools the guest init needs are installed."""
    if _uml_modules_dir() is None:
        return False
    return all(_find_tool(tool) is not None for tool in ("insmod", "ip", "timeout", "awk"))


def _forced_backend() -> str | None:
    forced = os.environ.get("VCAN_HARNESS_BACKEND", "").strip().lower()
    return forced if forced in ("native", "uml") else None


def vcan_unavailable_reason() -> str | None:
    """None if :func:`run_on_vcan` can work here, else a human-readable reason."""
    forced = _forced_backend()
    if forced == "native":
        return None if native_vcan_available() else "VCAN_HARNESS_BACKEND=native but no SocketCAN"
    if forced == "uml":
        return None if uml_available() else "VCAN_HARNESS_BACKEND=uml but UML is not installed"
    if native_vcan_available() or uml_available():
        return None
    return (
        "no vcan: the host kernel has no usable SocketCAN/vcan and User-Mode Linux is not "
        f"installed ({UML_KERNEL} plus vcan modules under {UML_MODULES_ROOT}; see "
        ".ci/install-system.sh)"
    )


def _backend() -> str:
    forced = _forced_backend()
    if forced is not None:
        return forced
    return "native" if native_vcan_available() else "uml"


# --------------------------------------------------------------------------- helpers


def _script_env(env: Mapping[str, str] | None, home: str) -> dict[str, str]:
    exe_dir = os.path.dirname(sys.executable)  # not resolved: keep the venv's bin directory
    result = {
        "PATH": f"{exe_dir}:{SYSTEM_PATH}",
        "HOME": home,
        "TMPDIR": "/tmp",
        "LANG": "C.UTF-8",
        "LC_ALL": "C.UTF-8",
        "PYTHONUNBUFFERED": "1",
    }
    for name in _PASSTHROUGH_ENV:
        value = os.environ.get(name)
        if value:
            result[name] = value
    if env:
        result.update(env)
    for name in result:
        if not _ENV_NAME_RE.match(name):
            raise ValueError(f"invalid environment variable name: {name!r}")
    return result


def _check_ifaces(interfaces: Sequence[str]) -> list[str]:
    if isinstance(interfaces, str):
        interfaces = [interfaces]
    names = list(interfaces)
    for name in names:
        if not _IFNAME_RE.match(name):
            raise ValueError(f"invalid interface name: {name!r}")
    return names


def _read(path: Path) -> str:
    try:
        return path.read_bytes().decode("utf-8", errors="replace")
    except FileNotFoundError:
        return ""


def _kill_group(proc: subprocess.Popen[bytes]) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)
    with contextlib.suppress(subprocess.TimeoutExpired):
        proc.wait(timeout=10)


def _tail(text: str, lines: int = 40) -> str:
    return "\n".join(text.splitlines()[-lines:])


def _exports(env: Mapping[str, str]) -> str:
    """``env`` as lines of ``export NAME=value`` for /bin/sh to source."""
    return "".join(f"export {k}={shlex.quote(v)}\n" for k, v in env.items())


def _run_group(
    cmd: Sequence[str],
    *,
    stdout: Path,
    stderr: Path | None,
    cwd: str,
    env: Mapping[str, str],
    timeout: float,
) -> int | None:
    """Run ``cmd`` in a process group of its own (stdin empty; stdout to the file ``stdout``,
    stderr to ``stderr`` or with stdout) for at most ``timeout`` seconds, then kill whatever
    is left of the group (background children of a script, UML's helper processes). Returns
    its exit status, or None if it ran out of time."""
    with contextlib.ExitStack() as files:
        out = files.enter_context(stdout.open("wb"))
        err = files.enter_context(stderr.open("wb")) if stderr is not None else subprocess.STDOUT
        proc = subprocess.Popen(
            list(cmd),
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=err,
            cwd=cwd,
            env=dict(env),
            start_new_session=True,
        )
        try:
            returncode: int | None = proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            returncode = None
        _kill_group(proc)
    return returncode


@dataclass(frozen=True)
class _Job:
    """One run for a backend: the script is ``workdir/script.sh`` already."""

    timeout: float
    interfaces: list[str]
    env: dict[str, str]
    cwd: str
    workdir: Path


# --------------------------------------------------------------------------- native backend


def _run_native(job: _Job) -> VcanResult:
    for name in job.interfaces:
        error = _ensure_native_iface(name)
        if error is not None:
            raise VcanSetupError(error)
    out_path, err_path = job.workdir / "stdout", job.workdir / "stderr"
    start = time.monotonic()
    returncode = _run_group(
        ["/bin/sh", str(job.workdir / "script.sh")],
        stdout=out_path,
        stderr=err_path,
        cwd=job.cwd,
        env=job.env,
        timeout=job.timeout,
    )
    return VcanResult(
        returncode=TIMEOUT_RETURNCODE if returncode is None else returncode,
        stdout=_read(out_path),
        stderr=_read(err_path),
        backend="native",
        duration=time.monotonic() - start,
    )


# --------------------------------------------------------------------------- UML backend

#: PID 1 of the guest: ``init=/bin/sh -- UML_INIT WORKDIR``, its parameters in
#: ``WORKDIR/init.env`` (see the script).
UML_INIT = SCRIPTS / "uml_init.sh"


def _uml_mem() -> str:
    mem = os.environ.get("VCAN_UML_MEM", DEFAULT_UML_MEM).strip()
    if not re.fullmatch(r"[0-9]+[kKmMgG]?", mem):
        raise ValueError(f"invalid VCAN_UML_MEM: {mem!r}")
    return mem


def _mem_bytes(mem: str) -> int:
    units = {"k": 1 << 10, "m": 1 << 20, "g": 1 << 30}
    suffix = mem[-1].lower()
    if suffix in units:
        return int(mem[:-1]) * units[suffix]
    return int(mem)


def _uml_process_env(workdir: Path, mem: str) -> dict[str, str]:
    """Environment of the linux.uml process itself (not of the guest).

    UML backs its "physical" memory with a file in $TMPDIR, else in /dev/shm.  A small
    /dev/shm (64 MiB in Docker) would make the guest die of SIGBUS once it touches more memory,
    so use the work directory on /tmp unless /dev/shm has room for all of it.
    """
    uml_env = {k: v for k, v in os.environ.items() if k not in ("TMPDIR", "TMP", "TEMP")}
    try:
        shm = os.statvfs("/dev/shm")
        shm_free = shm.f_bavail * shm.f_frsize
    except OSError:
        shm_free = 0
    if shm_free < _mem_bytes(mem) + (256 << 20):
        uml_env["TMPDIR"] = str(workdir)
    return uml_env


def _run_uml(job: _Job) -> VcanResult:
    workdir = job.workdir
    modules_dir = _uml_modules_dir()
    if modules_dir is None:
        raise VcanSetupError(vcan_unavailable_reason() or "User-Mode Linux is not installed")
    for path in (workdir, UML_INIT):  # both are words of the kernel's command line
        if any(c.isspace() for c in str(path)):
            raise VcanSetupError(f"path must not contain white space: {path}")
    mem = _uml_mem()
    start_wall = time.time()
    start = time.monotonic()
    (workdir / "env.sh").write_text(_exports(job.env))
    (workdir / "init.env").write_text(
        _exports(
            {
                "SYSTEM_PATH": SYSTEM_PATH,
                "MODULES_DIR": str(modules_dir),
                "MODULES": " ".join(UML_MODULES),
                "IFACES": " ".join(job.interfaces),
                "CWD": job.cwd,
                "DEADLINE": f"{start_wall + job.timeout:.3f}",
            }
        )
    )
    umid = f"vcan-{os.getpid()}-{uuid.uuid4().hex[:10]}"
    cmd = [
        UML_KERNEL,
        f"mem={mem}",
        f"umid={umid}",
        f"uml_dir={workdir}",
        "root=/dev/root",
        "rootfstype=hostfs",
        "rootflags=/",
        "rw",
        "init=/bin/sh",
        "con=null",
        "ssl=null",
        "con0=fd:0,fd:1",
        "--",  # the rest goes to init as its arguments
        str(UML_INIT),
        str(workdir),
    ]
    kernel_log = workdir / "kernel.log"
    # its own process group: UML forks a host process per guest mm
    kernel_rc = _run_group(
        cmd,
        stdout=kernel_log,
        stderr=None,
        cwd=str(workdir),
        env=_uml_process_env(workdir, mem),
        timeout=job.timeout + HARD_KILL_GRACE,
    )
    timed_out = kernel_rc is None
    duration = time.monotonic() - start
    stdout = _read(workdir / "stdout")
    stderr = _read(workdir / "stderr")
    rc_text = _read(workdir / "rc").strip()
    if rc_text.lstrip("-").isdigit():  # the script finished (even if poweroff then hung)
        return VcanResult(int(rc_text), stdout, stderr, "uml", duration)
    if timed_out:
        return VcanResult(TIMEOUT_RETURNCODE, stdout, stderr, "uml", duration)
    what = (
        "vcan setup failed inside User-Mode Linux"
        if (workdir / "setup_failed").exists()
        else "User-Mode Linux guest produced no exit status"
    )
    raise VcanSetupError(
        f"{what} (linux.uml exited with {kernel_rc}).\n"
        f"--- init log ---\n{_tail(_read(workdir / 'init.log'))}\n"
        f"--- kernel log (tail) ---\n{_tail(_read(kernel_log))}"
    )


# --------------------------------------------------------------------------- public API


def run_on_vcan(
    script: str,
    *,
    timeout: float = 120.0,
    interfaces: Sequence[str] = ("vcan0",),
    env: Mapping[str, str] | None = None,
    cwd: str | None = None,
) -> VcanResult:
    """Run ``script`` with /bin/sh while the named vcan interfaces exist and are up.

    Natively when the host kernel has SocketCAN (the interfaces are created if missing, which
    needs CAP_NET_ADMIN), otherwise as root inside a fresh User-Mode Linux kernel whose
    interfaces exist only for this run.  ``PATH`` starts with the directory of
    ``sys.executable`` (so ``python``, ``sim-ecu`` and ``motor-monitor`` resolve), then the
    system directories; ``HOME``, ``TMPDIR=/tmp`` and ``LANG=C.UTF-8`` are set, ``PYTHONPATH``,
    ``VIRTUAL_ENV``, ``NUMBA_CACHE_DIR`` and ``XDG_CACHE_HOME`` are passed through, and ``env``
    is added last.  ``cwd`` defaults to the project root.  After ``timeout`` seconds (boot
    included) the script is killed and the result has ``returncode`` 124 with whatever output
    was written.

    Raises :class:`VcanSetupError` if the environment cannot be set up, and ``ValueError`` for
    invalid interface or variable names.
    """
    names = _check_ifaces(interfaces)
    workdir_cwd = str(Path(cwd).resolve()) if cwd is not None else str(ROOT)
    home = os.environ.get("HOME") or "/root"
    script_env = _script_env(env, home)
    backend = _backend()
    if backend == "native" and not native_vcan_available():
        raise VcanSetupError("the host kernel has no usable SocketCAN/vcan")
    workdir = Path(tempfile.mkdtemp(prefix="vcan-", dir="/tmp"))
    keep = os.environ.get("VCAN_HARNESS_KEEP", "").strip().lower() in ("1", "true", "yes")
    try:
        (workdir / "script.sh").write_text(script)
        job = _Job(timeout, names, script_env, workdir_cwd, workdir)
        return _run_native(job) if backend == "native" else _run_uml(job)
    finally:
        if keep:
            print(f"vcan_harness: kept {workdir}", file=sys.stderr)
        else:
            shutil.rmtree(workdir, ignore_errors=True)
