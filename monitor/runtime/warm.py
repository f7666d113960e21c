"""numba's cache of every kernel the daemon and a replay load, warmed at install:
`python -m monitor.runtime.warm`.

Nothing is compiled when the daemon starts (scripts/setup-venv.sh runs this after
`pip install`, beside the estimator's ahead-of-time build, `monitor.estimation.kernels_aot`):
the warm-up is the engines' own, on scratch state -- the estimator's step kernel and what
it calls (the UKF, the fuzzy system), its loop over many samples, the structure event's
onset search and re-processing (`FuzzyUKF.warm_up`), the diagnosis rules' steps and their
loop (`monitor.diagnosis.rules.warm_up`), the admission of samples and its column forms
(`monitor.pipeline.admission.warm_up`) and the columnar engine's ticks -- compiled into the cache
directory the daemon reads (`monitor.jit`). The kernels' argument types do not depend on the
plant's size, so the packaged DC motor warms them for every rig. numba keys the cache by
the kernels' source (a content hash), their directory and the CPU: an edited source, a
moved install or another CPU compiles once at the next start, and caches again.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from monitor import jit

__all__ = ["main", "warm_jit_cache"]


def warm_jit_cache() -> Path | None:
    """Compile into numba's cache every kernel the daemon loads before its first frame,
    and return the cache directory; None when there is nothing to warm (the JIT is off).
    Raises RuntimeError when no cache directory can be written (the kernels would then be
    compiled at every start)."""
    if jit.JIT_DISABLED:
        return None
    directory = jit.numba_cache_dir()
    if directory is None:
        raise RuntimeError("no writable directory for numba's kernel cache (NUMBA_CACHE_DIR, "
                           "XDG_CACHE_HOME, ~/.cache)")
    from monitor.columnar import kernels as columnar_kernels
    from monitor.diagnosis import rules
    from monitor.diagnosis.thresholds import DEFAULT_THRESHOLDS
    from monitor.estimation.fuzzy_ukf import FuzzyUKF
    from monitor.estimation.model import dc_motor
    from monitor.pipeline import admission

    FuzzyUKF(dc_motor().discretize(0.01)).warm_up()
    rules.warm_up(rules.params(DEFAULT_THRESHOLDS))
    admission.warm_up()
    columnar_kernels.warm_up()
    return directory


def main(argv: list[str] | None = None) -> int:
    """Warm the cache; a failure is one line and the exit status 1."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-q", "--quiet", action="store_true", help="print failures only")
    args = ap.parse_args(argv)
    try:
        cache = warm_jit_cache()
    except Exception as exc:  # a cache that cannot be written: say so in one line
        print(f"warm: error: cannot warm the JIT cache ({exc}); the daemon compiles its "
              "kernels at start", file=sys.stderr)
        return 1
    if not args.quiet:
        print("JIT off (NUMBA_DISABLE_JIT): no cache to warm" if cache is None
              else f"JIT cache warmed in {cache}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
