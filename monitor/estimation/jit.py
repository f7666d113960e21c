"""`njit`: numba's, unless the JIT is off.

Under the hardened service (MemoryDenyWriteExecute=yes) even `import numba` fails: numba
0.68 asks llvmlite at import whether it may map executable memory, which the unit forbids
("cannot allocate executable memory"). With NUMBA_DISABLE_JIT set -- as the units set it --
this decorator returns the function unchanged and numba is never imported; the estimator
then runs the ahead-of-time build (`monitor.estimation.kernels_aot`) or the plain Python.
Otherwise it is ``numba.njit(cache=True, nogil=True)``.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any, TypeVar, cast

__all__ = ["JIT_DISABLED", "njit"]

F = TypeVar("F", bound=Callable[..., Any])

JIT_DISABLED = os.environ.get("NUMBA_DISABLE_JIT", "0") not in ("", "0")


def njit(fn: F) -> F:
    """Compile `fn` with numba (cached, without the GIL), unless the JIT is disabled."""
    if JIT_DISABLED:
        return fn
    import numba

    return cast(F, numba.njit(cache=True, nogil=True)(fn))
