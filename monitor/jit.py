"""`njit`: numba's, unless the JIT is off.

Under the hardened service (MemoryDenyWriteExecute=yes) even `import numba` fails: numba
0.68 asks llvmlite at import whether it may map executable memory, which the unit forbids
("cannot allocate executable memory"). With NUMBA_DISABLE_JIT set -- as the units set it --
this decorator returns the function unchanged and numba is never imported; the estimator
then runs the ahead-of-time build (`monitor.estimation.kernels_aot`) or the plain Python.
Otherwise it is ``numba.njit(cache=True, nogil=True)``.

Where the compiled kernels are cached: numba's default is a ``__pycache__`` beside each
module, inside the installed package, which a read-only install (a system package, a
container image, ``ProtectSystem=strict``) refuses at run time. So before numba is first
imported, `numba_cache_dir` chooses a directory the user owns and hands it to numba
(``NUMBA_CACHE_DIR``): ``$NUMBA_CACHE_DIR`` if set (the systemd unit sets its
CacheDirectory=), else ``$XDG_CACHE_HOME/motor-monitor/numba``, else
``~/.cache/motor-monitor/numba``. When none of them can be written, the kernels are
compiled without a cache (every start compiles them again; nothing fails). The install
fills that directory (`monitor.estimation.kernels_aot`, run by scripts/setup-venv.sh), so
the daemon's first start loads its kernels instead of compiling them.
"""

from __future__ import annotations

import logging
import os
import tempfile
from collections.abc import Callable
from functools import cache
from pathlib import Path
from typing import Any, TypeVar, cast

__all__ = ["CACHE_SUBDIR", "JIT_DISABLED", "njit", "numba_cache_dir"]

F = TypeVar("F", bound=Callable[..., Any])

JIT_DISABLED = os.environ.get("NUMBA_DISABLE_JIT", "0") not in ("", "0")
CACHE_SUBDIR = Path("motor-monitor") / "numba"

log = logging.getLogger("motor_monitor")


def _writable(directory: Path) -> bool:
    """Whether files can be created in `directory` (made if missing): tried, because
    permissions do not tell of a read-only mount."""
    try:
        directory.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=directory):
            pass
    except OSError:
        return False
    return True


def numba_cache_dir() -> Path | None:
    """The directory for numba's kernel cache (see the module docstring), or None when
    there is none that can be written."""
    given = os.environ.get("NUMBA_CACHE_DIR")
    if given:
        return Path(given) if _writable(Path(given)) else None
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg) if xdg and Path(xdg).is_absolute() else Path.home() / ".cache"
    directory = base / CACHE_SUBDIR
    return directory if _writable(directory) else None


@cache
def _numba() -> tuple[Any, bool]:
    """numba, imported once its cache directory is set; and whether to cache."""
    directory = numba_cache_dir()
    if directory is not None:
        os.environ["NUMBA_CACHE_DIR"] = str(directory)
    else:
        log.warning("no writable directory for numba's kernel cache (NUMBA_CACHE_DIR, "
                    "XDG_CACHE_HOME, ~/.cache): kernels are compiled at every start")
    import numba
    from numba.core import config

    if directory is not None:
        # numba read its configuration at import: if something imported it before us,
        # this is where its cache locator looks (a name numba's config makes at run time)
        config.CACHE_DIR = str(directory)  # type: ignore[attr-defined]
    return numba, directory is not None


def njit(fn: F) -> F:
    """Compile `fn` with numba (cached, without the GIL), unless the JIT is disabled."""
    if JIT_DISABLED:
        return fn
    numba, caching = _numba()
    return cast(F, numba.njit(cache=caching, nogil=True)(fn))
