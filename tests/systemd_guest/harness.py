"""Boot a real systemd (PID 1) in User-Mode Linux and run the guest checks in it.

Never the host's own root: the guest's root file system is a small Debian (mmdebstrap
minbase with systemd, udev, networkd, dbus, can-utils, ...), built once and cached as a
tarball under ``~/.cache/motor-monitor/systemd-guest/`` keyed by the recipe (suite,
packages, options), and unpacked afresh for every run into a private directory under /tmp
that User-Mode Linux mounts as its root (hostfs). See /work/shared/SYSTEMD-UML.md.

Into that root the harness installs what systemd/README.md installs, verbatim: the two
units in /etc/systemd/system, the network files in /etc/systemd/network with
systemd-networkd enabled. The project -- the checkout as it is, with its AOT estimator
kernel and byte code built on the host beforehand (the guest has no compiler and the units
write no byte code) -- is mounted read-only (hostfs) and linked where the unit expects it,
/opt/motor-monitor. ``/opt/motor-monitor/.venv`` is a virtual environment as an install
would make it: its Python is the host venv's base Python, mounted read-only at
/opt/host-python (not under /root or /home, which ``ProtectHome=yes`` hides), its
site-packages are the host venv's (read-only), the project importable from
/opt/motor-monitor. Where services write (state, cache, /tmp), the guest has tmpfs: hostfs
would make every new file root's. ``guest-checks.service`` (wanted by multi-user.target)
runs ``guest_checks.sh``, which leaves its evidence in /results (with a copy of the state
directory) and powers the guest off; the host reads it after linux.uml has exited.

Environment knobs: ``SYSTEMD_GUEST_KEEP=1`` keeps the run directory (its path is printed),
``SYSTEMD_GUEST_CACHE`` replaces the cache directory. Needs root (hostfs keeps the host's
file owners) and is marked ``vcan`` (tests/conftest.py: no skip when CI is set).
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import re
import secrets
import shutil
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from tests.support.paths import ROOT
from tests.support.vcan_harness import (
    UML_KERNEL,
    _kill_group,
    _read,
    _tail,
    _uml_mem,
    _uml_modules_dir,
    _uml_process_env,
    uml_available,
)

__all__ = [
    "GUEST_INSTALL",
    "GUEST_STATE",
    "GuestRun",
    "GuestSetupError",
    "boot_guest",
    "compile_bytecode",
    "ensure_aot_kernel",
    "keep_workdir",
    "new_workdir",
    "rootfs_tarball",
    "unavailable_reason",
]

HERE = Path(__file__).resolve().parent
SUITE = "bookworm"
PACKAGES = ("systemd", "systemd-sysv", "udev", "iproute2", "kmod", "python3", "dbus",
            "libnss-systemd", "can-utils")
#: Documentation is not needed in a test guest: a smaller tarball unpacks faster.
DPKG_OPTIONS = tuple(f"path-exclude=/usr/share/{d}/*" for d in ("man", "doc", "info", "locale"))
#: Bump when the recipe changes in a way the key does not see.
RECIPE_VERSION = 1

IFACE = "vcan0"
GUEST_INSTALL = "/opt/motor-monitor"  # where the unit's ExecStart= expects the project
GUEST_PYTHON = "/opt/host-python"  # the host venv's base Python, read-only
GUEST_PROJECT = "/opt/.project"  # the project's checkout, read-only
GUEST_SITE = "/opt/.host-site-packages"  # the host venv's site-packages, read-only
#: The project's own packages: imported from /opt/motor-monitor, never from site-packages.
PROJECT_PACKAGES = ("monitor", "sim_ecu", "experiments")
GUEST_RESULTS = "/results"
#: The state directory as root sees it (StateDirectory= with DynamicUser=yes).
GUEST_STATE = f"/var/lib/private/motor-monitor/{IFACE}"
#: The CAN modules of the UML kernel that the guest's modprobe may need (vcan, can-dev).
CAN_MODULE_DIRS = ("kernel/net/can", "kernel/drivers/net/can")
#: Units a test guest does not need (a getty on the console, logins, timers and the
#: coldplug of devices of a real system): boot takes half as long without them.
MASKED = ("getty.target", "console-getty.service", "systemd-timesyncd.service",
          "systemd-logind.service", "e2scrub_reap.service", "modprobe@.service",
          "systemd-udev-trigger.service", "apt-daily.timer", "apt-daily-upgrade.timer",
          "e2scrub_all.timer", "fstrim.timer", "systemd-tmpfiles-clean.timer", "man-db.timer")

#: hostfs creates every file as the user running linux.uml (root), whoever creates it in
#: the guest: a dynamic user could not reopen its own files after a restart. Where services
#: write (StateDirectory=, CacheDirectory=, PrivateTmp=), the guest has its own file systems,
#: which keep owners; guest_checks.sh copies the state directory into /results at the end.
TMPFS_FSTAB = """\
# guest file systems where services write: hostfs would make every new file root's
tmpfs /var/lib/private tmpfs mode=0700 0 0
tmpfs /var/cache/private tmpfs mode=0700 0 0
tmpfs /tmp tmpfs mode=1777 0 0
tmpfs /var/tmp tmpfs mode=1777 0 0
"""

#: The guest checks give up after this long (RuntimeMaxSec= of guest-checks.service; they
#: take 1.5 to 2.5 minutes, more on a loaded host: UML has one CPU and gets what is left).
GUEST_RUNTIME_S = int(re.search(r"^RuntimeMaxSec=(\d+)s$", (HERE / "guest-checks.service")
                                .read_text(), re.M).group(1))  # type: ignore[union-attr]
#: Boot and power-off allowance on top of that, before the host kills linux.uml.
BOOT_ALLOWANCE_S = 90
#: On the console: the guest will not get to the checks (a failed mount, a panic).
STUCK = ("You are in emergency mode", "Kernel panic")


class GuestSetupError(RuntimeError):
    """The guest could not be built or booted (not a failure of a check)."""


def cache_dir() -> Path:
    env = os.environ.get("SYSTEMD_GUEST_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "motor-monitor" / "systemd-guest"


def _recipe_key() -> str:
    recipe = {"suite": SUITE, "variant": "minbase", "packages": sorted(PACKAGES),
              "dpkg": list(DPKG_OPTIONS), "version": RECIPE_VERSION}
    return hashlib.sha256(json.dumps(recipe, sort_keys=True).encode()).hexdigest()[:16]


def _tarball_path() -> Path:
    return cache_dir() / f"rootfs-{SUITE}-{_recipe_key()}.tar"


def host_venv() -> Path:
    """The project's virtual environment (the one running the tests)."""
    return Path(sys.prefix)


def _venv_home(venv: Path) -> Path:
    """The base Python's prefix of ``venv`` (pyvenv.cfg ``home`` is its bin directory)."""
    cfg = (venv / "pyvenv.cfg").read_text()
    m = re.search(r"^home\s*=\s*(.+?)\s*$", cfg, re.M)
    if m is None:
        raise GuestSetupError(f"{venv}/pyvenv.cfg names no home")
    return Path(m.group(1)).resolve().parent


def _site_packages(venv: Path) -> Path:
    found = sorted(venv.glob("lib/python3.*/site-packages"))
    if len(found) != 1:
        raise GuestSetupError(f"expected one site-packages in {venv}, found {found}")
    return found[0]


def unavailable_reason() -> str | None:
    """None if the guest can be booted here, else why not."""
    if os.geteuid() != 0:
        return ("needs root: the guest's root file system is a host directory whose files "
                "must belong to root (hostfs), and mmdebstrap builds it as root")
    if not uml_available():
        return f"User-Mode Linux is not installed ({UML_KERNEL}; .ci/install-system.sh)"
    if not _tarball_path().exists() and shutil.which("mmdebstrap") is None:
        return "mmdebstrap is not installed (Debian package mmdebstrap; .ci/install-system.sh)"
    if sys.prefix == sys.base_prefix:
        return "the tests must run from the project's virtual environment"
    return None


# ---------------------------------------------------------------------------- build


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def rootfs_tarball() -> tuple[Path, float]:
    """The cached root file system tarball (built now if missing) and the build time, s."""
    path = _tarball_path()
    with _locked(path.with_suffix(".lock")):
        if path.exists():
            return path, 0.0
        exe = shutil.which("mmdebstrap")
        if exe is None:
            raise GuestSetupError("mmdebstrap is not installed (.ci/install-system.sh)")
        tmp = path.with_name(f".{os.getpid()}.{path.name}")
        cmd = [exe, "--quiet", "--variant=minbase", "--format=tar",
               f"--include={','.join(PACKAGES)}",
               *(f"--dpkgopt={o}" for o in DPKG_OPTIONS), SUITE, str(tmp)]
        start = time.monotonic()
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=900, check=False)
        if proc.returncode != 0:
            tmp.unlink(missing_ok=True)
            raise GuestSetupError(f"{' '.join(cmd)} failed ({proc.returncode}):\n"
                                  f"{_tail(proc.stdout + proc.stderr)}")
        tmp.rename(path)
        for old in path.parent.glob(f"rootfs-{SUITE}-*.tar"):  # earlier recipes
            if old != path:
                old.unlink(missing_ok=True)
        return path, time.monotonic() - start


def ensure_aot_kernel() -> str:
    """Build the AOT estimator kernel on the host unless a current one is there: the guest
    mounts the project read-only and has no compiler. Returns "present" or "built"."""
    est = ROOT / "monitor" / "estimation"
    # the step kernel, the kernels and layout it compiles in, the build, the numba switch
    sources = [*est.glob("*.py"), ROOT / "monitor" / "jit.py"]
    newest_source = max(p.stat().st_mtime for p in sources)
    built = sorted(est.glob("_fuzzy_ukf_aot*.so"))
    check = ("from monitor.estimation.fuzzy_ukf import select_kernel; "
             "assert select_kernel('aot')[0] == 'aot'")
    if built and built[-1].stat().st_mtime >= newest_source:
        ok = subprocess.run([sys.executable, "-c", check], capture_output=True,
                            cwd=ROOT, timeout=120, check=False)
        if ok.returncode == 0:
            return "present"
    proc = subprocess.run(
        [sys.executable, "-m", "monitor.estimation.kernels_aot"],
        capture_output=True, text=True, cwd=ROOT, timeout=600, check=False)
    if proc.returncode != 0:
        raise GuestSetupError(f"cannot build the AOT kernel: {proc.stdout}{proc.stderr}")
    return "built"


def compile_bytecode() -> None:
    """Byte-compile the project on the host: the guest mounts it read-only and the units
    set PYTHONDONTWRITEBYTECODE=1, so without this every start would compile every module
    again on the guest's slow CPU."""
    subprocess.run([sys.executable, "-m", "compileall", "-q", "monitor", "sim_ecu"],
                   cwd=ROOT, capture_output=True, timeout=300, check=False)


# ---------------------------------------------------------------------------- the root


def _fstab(project: Path, venv: Path) -> str:
    """hostfs mounts (the data string is the host path), all read-only, and the guest's own
    file systems where services write."""
    lines = [
        f"none {GUEST_PROJECT} hostfs ro,{project} 0 0",
        f"none {GUEST_SITE} hostfs ro,{_site_packages(venv)} 0 0",
        f"none {GUEST_PYTHON} hostfs ro,{_venv_home(venv)} 0 0",
    ]
    for line in lines:
        if line.split()[3].count(",") != 1 or any(c.isspace() for c in line.split()[3]):
            raise GuestSetupError(f"path not usable as a hostfs mount option: {line}")
    return ("# tests/systemd_guest: the project, its venv and Python, read-only from the host\n"
            + "\n".join(lines) + "\n" + TMPFS_FSTAB)


def _install_project(root: Path, project: Path) -> None:
    """/opt/motor-monitor: the project's files (links into its read-only mount), and a
    .venv of its own (_install_venv)."""
    d = root / GUEST_INSTALL.lstrip("/")
    d.mkdir(parents=True)
    for entry in project.iterdir():
        if entry.name not in (".venv", ".git"):
            (d / entry.name).symlink_to(f"{GUEST_PROJECT}/{entry.name}")


def _install_venv(root: Path, venv: Path) -> None:
    """/opt/motor-monitor/.venv as an install makes it: pyvenv.cfg naming the base Python,
    python links, console scripts whose #! names it, and site-packages: the host venv's
    entries (links into its read-only mount) with the project found in /opt/motor-monitor
    (a .pth) instead of the checkout the host's editable install names -- which may lie
    under /home, hidden from the service by ProtectHome=yes."""
    d = root / GUEST_INSTALL.lstrip("/") / ".venv"
    home = _venv_home(venv)
    py = f"python{sys.version_info.major}.{sys.version_info.minor}"
    site = _site_packages(venv)
    guest_site = d / site.relative_to(venv)
    (d / "bin").mkdir(parents=True)
    guest_site.mkdir(parents=True)
    cfg = (venv / "pyvenv.cfg").read_text()
    cfg = re.sub(r"^home\s*=.*$", f"home = {GUEST_PYTHON}/bin", cfg, flags=re.M)
    cfg = re.sub(r"^(executable|command)\s*=.*\n", "", cfg, flags=re.M)
    (d / "pyvenv.cfg").write_text(cfg)
    (d / "bin" / py).symlink_to(f"{GUEST_PYTHON}/bin/{py}")
    for alias in ("python", "python3"):
        (d / "bin" / alias).symlink_to(py)
    for script in ("motor-monitor", "sim-ecu"):
        body = (venv / "bin" / script).read_text().split("\n", 1)[1]
        (d / "bin" / script).write_text(f"#!{GUEST_INSTALL}/.venv/bin/python\n{body}")
        (d / "bin" / script).chmod(0o755)
    for entry in site.iterdir():
        if entry.name.startswith("__editable__") or entry.name in PROJECT_PACKAGES:
            continue
        (guest_site / entry.name).symlink_to(f"{GUEST_SITE}/{entry.name}")
    (guest_site / "motor_monitor_install.pth").write_text(f"{GUEST_INSTALL}\n")
    # The host Python may link libpython with an RUNPATH under /root (pyenv), hidden from
    # the service by ProtectHome=yes: the loader finds it in a default directory instead.
    lib = home / "lib" / f"lib{py}.so.1.0"
    if lib.exists():
        for multiarch in root.glob("usr/lib/*-linux-gnu"):
            link = multiarch / lib.name
            if not link.exists() and not link.is_symlink():
                link.symlink_to(f"{GUEST_PYTHON}/lib/{lib.name}")


def _systemctl_root(root: Path, *args: str) -> None:
    exe = shutil.which("systemctl") or "/bin/systemctl"
    proc = subprocess.run([exe, f"--root={root}", "--quiet", *args], capture_output=True,
                          text=True, timeout=60, check=False)
    if proc.returncode != 0:
        raise GuestSetupError(f"systemctl --root {' '.join(args)}: {proc.stderr.strip()}")


def prepare_root(root: Path, tarball: Path) -> None:
    """Unpack the cached root file system into ``root`` and install the units, the network
    files, the guest checks and the mounts."""
    root.mkdir()
    proc = subprocess.run(["tar", "-C", str(root), "-xf", str(tarball)], capture_output=True,
                          text=True, timeout=300, check=False)
    if proc.returncode != 0:
        raise GuestSetupError(f"unpacking {tarball}: {proc.stderr.strip()}")
    modules = _uml_modules_dir()
    if modules is None:
        raise GuestSetupError("the UML kernel's modules are missing")
    version_dir = modules.parent
    dest = root / "usr/lib/modules" / version_dir.name
    for rel in CAN_MODULE_DIRS:
        shutil.copytree(version_dir / rel, dest / rel)
    for f in version_dir.glob("modules.*"):
        shutil.copy2(f, dest / f.name)
    # What systemd/README.md installs, verbatim.
    system = root / "etc/systemd/system"
    for unit in ("motor-monitor@.service", "sim-ecu@.service"):
        shutil.copy(ROOT / "systemd" / unit, system / unit)
    network = root / "etc/systemd/network"
    network.mkdir(parents=True, exist_ok=True)
    for name in ("80-vcan0.netdev", "80-vcan0.network"):
        shutil.copy(ROOT / "systemd" / name, network / name)
    # The project, its venv and Python.
    venv = host_venv()
    for mountpoint in (GUEST_PROJECT, GUEST_PYTHON, GUEST_SITE):
        (root / mountpoint.lstrip("/")).mkdir(parents=True)
    _install_project(root, ROOT)
    _install_venv(root, venv)
    (root / "etc/fstab").write_text(_fstab(ROOT, venv))
    # Settings of the units (world-readable, as systemd/README.md asks) and the SecOC key
    # (root only, delivered by LoadCredential=).
    etc = root / "etc/motor-monitor"
    etc.mkdir()
    shutil.copy(HERE / "short-fault.toml", etc / "short-fault.toml")
    (etc / f"sim-ecu-{IFACE}.env").write_text(
        "NODE=0\nSCENARIO=/etc/motor-monitor/short-fault.toml\n")
    fd = os.open(etc / "secoc.key", os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(secrets.token_hex(16) + "\n")
    # The guest checks.
    shutil.copy(HERE / "guest-checks.service", system / "guest-checks.service")
    (root / "etc/guest-checks.env").write_text(
        f"INSTALL={GUEST_INSTALL}\nRESULTS={GUEST_RESULTS}\n"
        f"IFACE={IFACE}\nSTATE={GUEST_STATE}\n")
    (root / GUEST_RESULTS.lstrip("/")).mkdir()
    # A persistent journal: the host reads it after the guest has gone (journalctl -D).
    (root / "var/log/journal").mkdir(parents=True, exist_ok=True)
    (root / "etc/hostname").write_text("motor-monitor-guest\n")
    _systemctl_root(root, "enable", "systemd-networkd.service", "guest-checks.service")
    _systemctl_root(root, "mask", *MASKED)


# ---------------------------------------------------------------------------- boot


@dataclass
class GuestRun:
    """What one boot left behind: the guest's root (results, state directory) and timings."""

    root: Path
    timings: dict[str, float] = field(default_factory=dict)
    returncode: int | None = None

    @property
    def results(self) -> Path:
        return self.root / GUEST_RESULTS.lstrip("/")

    @property
    def state(self) -> Path:
        """The copy of the state directory that the guest left in /results."""
        return self.results / "state"

    def text(self, name: str) -> str:
        return _read(self.results / name)

    def values(self) -> dict[str, str]:
        out: dict[str, str] = {}
        for line in self.text("values").splitlines():
            k, sep, v = line.partition("=")
            if sep:
                out[k] = v
        return out

    def kernel_log(self) -> str:
        return _read(self.root.parent / "kernel.log")

    def journal(self) -> str:
        """The guest's persistent journal, read on the host (journalctl -D)."""
        exe = shutil.which("journalctl") or "/bin/journalctl"
        proc = subprocess.run([exe, "-D", str(self.root / "var/log/journal"), "--no-pager",
                               "-o", "short-monotonic"], capture_output=True, text=True,
                              timeout=60, check=False)
        return proc.stdout + proc.stderr

    def journal_entries(self, *matches: str) -> list[dict[str, str]]:
        """Entries of the guest's journal that journalctl's own matching selects
        (``FIELD=value`` each), as its JSON output gives them."""
        exe = shutil.which("journalctl") or "/bin/journalctl"
        proc = subprocess.run([exe, "-D", str(self.root / "var/log/journal"), "--no-pager",
                               "-o", "json", *matches], capture_output=True, text=True,
                              timeout=60, check=False)
        return [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]

    def diagnostics(self) -> str:
        """The tails of the guest script's log, the journal and the kernel log."""
        return (f"--- guest.log (tail) ---\n{_tail(self.text('guest.log'), 40)}\n"
                f"--- journal (tail) ---\n{_tail(self.journal(), 40)}\n"
                f"--- kernel log (tail) ---\n{_tail(self.kernel_log(), 20)}")


def boot_guest(workdir: Path, tarball: Path) -> GuestRun:
    """Prepare a root under ``workdir``, boot it with systemd as PID 1 and wait until the
    guest has powered off (or the host's deadline passed)."""
    if any(c.isspace() or c == "," for c in str(workdir)):
        raise GuestSetupError(f"work directory unusable for hostfs: {workdir}")
    root = workdir / "root"
    t0 = time.monotonic()
    prepare_root(root, tarball)
    run = GuestRun(root=root)
    run.timings["prepare_s"] = time.monotonic() - t0
    mem = _uml_mem()
    cmd = [
        UML_KERNEL, f"mem={mem}", f"umid=sdguest-{os.getpid()}-{uuid.uuid4().hex[:8]}",
        f"uml_dir={workdir}", "root=/dev/root", "rootfstype=hostfs", f"rootflags={root}",
        "rw", "init=/lib/systemd/systemd", "con=null", "ssl=null", "con0=fd:0,fd:1",
        "systemd.unit=multi-user.target", "systemd.show_status=0",
    ]
    t1 = time.monotonic()
    with (workdir / "kernel.log").open("wb") as log:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=log,
                                stderr=subprocess.STDOUT, cwd=workdir,
                                env=_uml_process_env(workdir, mem), start_new_session=True)
        deadline = t1 + GUEST_RUNTIME_S + BOOT_ALLOWANCE_S
        stuck = None
        while run.returncode is None and time.monotonic() < deadline:
            try:
                run.returncode = proc.wait(timeout=1.0)
            except subprocess.TimeoutExpired:
                stuck = next((s for s in STUCK if s in _read(workdir / "kernel.log")), None)
                if stuck is not None:
                    break
        _kill_group(proc)
    run.timings["guest_s"] = time.monotonic() - t1
    if stuck is not None:
        raise GuestSetupError(f"the guest did not boot ({stuck!r} on its console):\n"
                              f"{_tail(run.kernel_log(), 60)}")
    return run


def new_workdir() -> Path:
    return Path(tempfile.mkdtemp(prefix="systemd-guest-", dir="/tmp"))


def keep_workdir() -> bool:
    return os.environ.get("SYSTEMD_GUEST_KEEP", "").strip().lower() in ("1", "true", "yes")
