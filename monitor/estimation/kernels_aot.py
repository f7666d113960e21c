"""The estimator's kernels made at install: `python -m monitor.estimation.kernels_aot`.

Nothing is compiled when the daemon starts (scripts/setup-venv.sh runs this after
`pip install`, and `monitor.runtime.warm`, which fills numba's cache of the JIT kernels).
The ahead-of-time build of the step kernel (`build`): numba's `pycc` compiles
`fuzzy_ukf_step`, with the kernels it calls, into an ordinary extension module
(`monitor/estimation/_fuzzy_ukf_aot.*.so`) that the dynamic linker loads like any other,
from the one source, the `@njit` functions of `monitor.estimation`. It is for the hardened
service, which forbids memory both writable and executable (MemoryDenyWriteExecute=yes):
there numba's JIT cannot run, and neither can the code it cached, which it maps executable
the same way. Generic x86-64 code, no LLVM at run time; it needs a C compiler and the
Python headers at install. The estimator picks it when the JIT is off
(`monitor.estimation.kernel.select_kernel`). numba 0.68 marks pycc "pending deprecation"
with its replacement still in development; without the module the service falls back to
the interpreted kernel (correct, about 40x slower). The JIT daemon cannot take the AOT
module instead: the event kernels call the step kernel inside numba, where an extension
module's function cannot be called, and the cached code is tuned to this machine's CPU.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

__all__ = ["MODULE", "SIGNATURE", "build", "main"]

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


def main(argv: list[str] | None = None) -> int:
    """Build the module; a failure is one line, and the exit status 1."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=None,
                    help="directory of the AOT module (default: the package)")
    ap.add_argument("-q", "--quiet", action="store_true", help="print failures only")
    args = ap.parse_args(argv)
    try:
        path = build(args.out)
    except Exception as exc:  # a missing compiler or headers: say so in one line
        print(f"kernels_aot: error: cannot build the AOT kernel ({exc}); the daemon runs "
              "the JIT, a service with NUMBA_DISABLE_JIT=1 the interpreted kernel",
              file=sys.stderr)
        return 1
    if not args.quiet:
        print(f"built {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
