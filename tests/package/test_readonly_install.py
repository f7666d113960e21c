"""A read-only install works (issue 17 item 6): numba's compiled kernels are cached in a
directory the user owns, never in the installed package.

The package is copied to a directory of its own (made read-only where the tests do not run
as root, who could write it anyway) and run from there in a new process, with
NUMBA_CACHE_DIR unset: a tiny replay compiles the columnar and estimator kernels, and
afterwards the package holds exactly the files it held before while
$XDG_CACHE_HOME/motor-monitor/numba holds the cache. With no writable cache directory at
all, the kernels are compiled without a cache and the run still works.
"""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from monitor.jit import CACHE_SUBDIR, JIT_DISABLED, numba_cache_dir
from tests.archive.logs import ecu_frames, write_log
from tests.support.paths import ROOT

pytestmark = pytest.mark.skipif(JIT_DISABLED, reason="numba compiles nothing: no cache")


REPLAY = """
import sys
import monitor
from monitor.bus.codec import load_database
from monitor.columnar import replay_file
from monitor.pipeline import MonitorConfig
result = replay_file(sys.argv[1], load_database(), MonitorConfig(nodes=(0,)))
print(monitor.__file__, result.frames, result.counters.get("samples/estimated", 0))
"""

READ = """
import sys
import monitor
from monitor.columnar import read_chunks
print(monitor.__file__, sum(len(c) for c in read_chunks(sys.argv[1])))
"""


def _tree(root: Path) -> dict[str, int]:
    """Every file and directory below `root`, with its size (directories 0)."""
    return {str(p.relative_to(root)): 0 if p.is_dir() else p.stat().st_size
            for p in sorted(root.rglob("*"))}


def _numba_files(root: Path) -> set[Path]:
    return {p for pattern in ("*.nbi", "*.nbc") for p in root.rglob(pattern)}


def _set_writable(root: Path, writable: bool) -> None:
    for p in [root, *root.rglob("*")]:
        mode = p.stat().st_mode
        bits = stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH
        p.chmod(mode | stat.S_IWUSR if writable else mode & ~bits)


@pytest.fixture
def installed(tmp_path: Path) -> Iterator[Path]:
    """The package copied to tmp_path/site (without caches), read-only for a user that is
    not root."""
    site = tmp_path / "site"
    shutil.copytree(ROOT / "monitor", site / "monitor",
                    ignore=shutil.ignore_patterns("__pycache__"))
    _set_writable(site, False)
    try:
        yield site
    finally:
        _set_writable(site, True)


@pytest.fixture
def tiny_log(tmp_path: Path) -> Path:
    return write_log(tmp_path / "tiny.log", ecu_frames(("healthy",), duration=1.0))


def _run(code: str, log: Path, site: Path, cwd: Path,
         **env: str) -> subprocess.CompletedProcess[str]:
    clean = {k: v for k, v in os.environ.items()
             if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME", "PYTHONPATH")}
    clean.update(PYTHONPATH=str(site), PYTHONDONTWRITEBYTECODE="1", NUMBA_DISABLE_JIT="0",
                 **env)
    return subprocess.run([sys.executable, "-c", code, str(log)], cwd=cwd, env=clean,
                          capture_output=True, text=True, timeout=900)


def test_kernels_are_cached_in_the_users_cache_not_in_the_package(
        tmp_path: Path, installed: Path, tiny_log: Path) -> None:
    before = _tree(installed)
    in_repo = _numba_files(ROOT / "monitor")
    cache = tmp_path / "xdg-cache"
    home = tmp_path / "home"
    home.mkdir()
    proc = _run(REPLAY, tiny_log, installed, tmp_path, XDG_CACHE_HOME=str(cache),
                HOME=str(home))
    assert proc.returncode == 0, proc.stderr
    where, frames, samples = proc.stdout.split()
    assert Path(where).is_relative_to(installed)  # the copy ran, not the repository
    assert int(frames) == 220 and int(samples) > 50
    assert _tree(installed) == before  # nothing written into the package
    assert _numba_files(ROOT / "monitor") <= in_repo  # nor into the repository's
    cached = _numba_files(cache / CACHE_SUBDIR)
    assert any(p.name.startswith("candump._scan_candump") for p in cached), sorted(cached)
    assert any("kernels" in p.name or "fuzzy" in p.name for p in cached), sorted(cached)
    assert not list(home.rglob("*"))  # ~/.cache is the fallback only


def test_without_a_writable_cache_directory_the_kernels_run_uncached(
        tmp_path: Path, installed: Path, tiny_log: Path) -> None:
    before = _tree(installed)
    not_a_directory = tmp_path / "file"
    not_a_directory.write_text("a file where the cache directories would go\n")
    proc = _run(READ, tiny_log, installed, tmp_path, XDG_CACHE_HOME=str(not_a_directory),
                HOME=str(not_a_directory))
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split()[1] == "220"
    assert "no writable directory for numba's kernel cache" in proc.stderr, proc.stderr
    assert _tree(installed) == before


def test_the_cache_directory_is_chosen_in_order(tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    given = tmp_path / "given"
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(given))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert numba_cache_dir() == given and given.is_dir()
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    assert numba_cache_dir() == tmp_path / "xdg" / CACHE_SUBDIR
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/ignored")  # the XDG spec: absolute only
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert numba_cache_dir() == tmp_path / "home" / ".cache" / CACHE_SUBDIR
    blocked = tmp_path / "blocked"
    blocked.write_text("")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(blocked / "sub"))  # cannot be made
    assert numba_cache_dir() is None
