"""The estimator's kernels made at install: `python -m monitor.estimation.kernels_aot`.

Nothing is compiled when the daemon starts, so its first frame is not seconds of JIT away
(scripts/setup-venv.sh runs this after `pip install`). Two forms, both made from the one
source, the `@njit` functions of `monitor.estimation`:

* the ahead-of-time build of the step kernel (`build`): numba's `pycc` compiles
  `fuzzy_ukf_step`, with the kernels it calls, into an ordinary extension module
  (`monitor/estimation/_fuzzy_ukf_aot.*.so`) that the dynamic linker loads like any other.
  It is for the hardened service, which forbids memory both writable and executable
  (MemoryDenyWriteExecute=yes): there numba's JIT cannot run, and neither can the code it
  cached, which it maps executable the same way. Generic x86-64 code, no LLVM at run time;
  it needs a C compiler and the Python headers at install. The estimator picks it when the
  JIT is off (`monitor.estimation.kernel.select_kernel`). numba 0.68 marks pycc "pending
  deprecation" with its replacement still in development; without the module the service
  falls back to the interpreted kernel (correct, about 40x slower).
* the JIT cache, warmed (`warm_jit_cache`): every kernel the daemon compiles before its
  first frame -- the step kernel and what it calls (the UKF, the fuzzy system), the
  structure event's onset search and re-processing -- compiled by the same warm-up the
  pipeline runs, into the cache directory the daemon reads (`monitor.jit`).
  The JIT daemon cannot take the AOT module instead: the event kernels call the step
  kernel inside numba, where an extension module's function cannot be called, and the
  cached code is tuned to this machine's CPU. numba keys the cache by the kernels' source
  (a content hash), their directory and the CPU: an edited source, a moved install or
  another CPU compiles once at the next start, and caches again.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

__all__ = ["MODULE", "SIGNATURE", "build", "main", "warm_jit_cache"]

MODULE = "_fuzzy_ukf_aot"
# (mdl, u, y, prm, st, centres, counts, cons, var, rule_idx, rule_w, wk, out, lay, n, m, p,
# max_mf). mdl, prm, st, wk and out are flat buffers whose layout (`layout.KERNEL_LAYOUT`,
# derived from its tables) changes without changing the signature: a stale build is told
# apart by its exported kernel_layout().
SIGNATURE = (
    "void(f8[::1], f8[::1], f8[::1], f8[::1], f8[::1], f8[:, ::1], i8[::1], f8[:, ::1], "
    "f8[:, ::1], i8[::1], f8[::1], f8[::1], f8[::1], i8[::1], i8, i8, i8, i8)"
)


def build(out_dir: Path | None = None) -> Path:
    """Compile the kernel into `out_dir` (default: the monitor package) and return the file."""
    with warnings.catch_warnings():
        # pycc is "pending deprecation" in numba 0.68 with no replacement released yet
        warnings.simplefilter("ignore")
        from numba.pycc import CC

    from monitor.estimation.kernel import fuzzy_ukf_step, kernel_layout

    target = Path(out_dir) if out_dir is not None else Path(__file__).resolve().parent
    target.mkdir(parents=True, exist_ok=True)
    cc = CC(MODULE)
    cc.output_dir = str(target)
    cc.verbose = False
    py_func = getattr(fuzzy_ukf_step, "py_func", fuzzy_ukf_step)
    cc.export("fuzzy_ukf_step", SIGNATURE)(py_func)
    # the buffer layout the kernel reads, checked by select_kernel against a stale build
    cc.export("kernel_layout", "i8()")(kernel_layout)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pycc's own deprecation notices
        cc.compile()
    found = sorted(target.glob(f"{MODULE}*.so"))
    if not found:
        raise RuntimeError(f"numba pycc produced no {MODULE} module in {target}")
    return found[-1]


def warm_jit_cache() -> Path | None:
    """Compile into numba's cache every kernel the daemon loads before its first frame,
    and return the cache directory; None when there is nothing to warm (the JIT is off).

    The warm-up is the pipeline's own (`FuzzyUKF.warm_up` on a scratch estimator): the
    kernels' argument types do not depend on the plant's size, so the packaged DC motor
    warms them for every rig. Raises RuntimeError when no cache directory can be written
    (the kernels would then be compiled at every start)."""
    from monitor import jit

    if jit.JIT_DISABLED:
        return None
    directory = jit.numba_cache_dir()
    if directory is None:
        raise RuntimeError("no writable directory for numba's kernel cache (NUMBA_CACHE_DIR, "
                           "XDG_CACHE_HOME, ~/.cache)")
    from monitor.diagnosis import rules
    from monitor.diagnosis.thresholds import DEFAULT_THRESHOLDS
    from monitor.estimation.fuzzy_ukf import FuzzyUKF
    from monitor.estimation.model import dc_motor

    FuzzyUKF(dc_motor().discretize(0.01)).warm_up()
    rules.warm_up(rules.params(DEFAULT_THRESHOLDS))  # the classifier's steps
    return directory


def main(argv: list[str] | None = None) -> int:
    """Both forms (or one, `--only`); each failure is one line, and the exit status 1."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=None,
                    help="directory of the AOT module (default: the package)")
    ap.add_argument("--only", choices=("aot", "cache"), default=None,
                    help="make one form: the AOT module, or the warmed JIT cache")
    ap.add_argument("-q", "--quiet", action="store_true", help="print failures only")
    args = ap.parse_args(argv)
    failed = False
    if args.only in (None, "aot"):
        try:
            path = build(args.out)
        except Exception as exc:  # a missing compiler or headers: say so in one line
            print(f"kernels_aot: error: cannot build the AOT kernel ({exc}); the daemon runs "
                  "the JIT, a service with NUMBA_DISABLE_JIT=1 the interpreted kernel",
                  file=sys.stderr)
            failed = True
        else:
            if not args.quiet:
                print(f"built {path}")
    if args.only in (None, "cache"):
        try:
            cache = warm_jit_cache()
        except Exception as exc:
            print(f"kernels_aot: error: cannot warm the JIT cache ({exc}); the daemon "
                  "compiles its kernels at start", file=sys.stderr)
            failed = True
        else:
            if not args.quiet:
                print("JIT off (NUMBA_DISABLE_JIT): no cache to warm" if cache is None
                      else f"JIT cache warmed in {cache}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
