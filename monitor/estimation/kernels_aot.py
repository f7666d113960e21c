"""Ahead-of-time build of the fuzzy UKF step kernel: `python -m monitor.estimation.kernels_aot`.

The hardened service forbids memory that is both writable and executable
(MemoryDenyWriteExecute=yes), which numba's JIT needs. Compiled ahead of time by numba's
`pycc` into an ordinary extension module (`monitor/_fuzzy_ukf_aot.*.so`, loaded by the
dynamic linker like any other), the same kernel runs at full speed without W+X memory.
Build it once at install time (it needs a C compiler and the Python headers); the estimator
picks it up when the JIT is off (see `monitor.estimation.fuzzy_ukf.select_kernel`). numba 0.68 marks
pycc "pending deprecation" with its replacement still in development; without the AOT
module the service falls back to the interpreted kernel (correct, about 40x slower).
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

__all__ = ["MODULE", "SIGNATURE", "build"]

MODULE = "_fuzzy_ukf_aot"
# (mdl, u, y, prm, st, centres, counts, cons, var, rule_idx, rule_w, wk, out, n, m, p, max_mf)
# prm, st and wk are flat buffers whose layout (fuzzy_ukf.KERNEL_LAYOUT, see
# _fuzzy_ukf_step) changes without changing the signature: a stale build is told apart by
# its exported kernel_layout().
SIGNATURE = (
    "void(f8[::1], f8[::1], f8[::1], f8[::1], f8[::1], f8[:, ::1], i8[::1], f8[:, ::1], "
    "f8[:, ::1], i8[::1], f8[::1], f8[::1], f8[::1], i8, i8, i8, i8)"
)


def build(out_dir: Path | None = None) -> Path:
    """Compile the kernel into `out_dir` (default: the monitor package) and return the file."""
    with warnings.catch_warnings():
        # pycc is "pending deprecation" in numba 0.68 with no replacement released yet
        warnings.simplefilter("ignore")
        from numba.pycc import CC

    from monitor.estimation.fuzzy_ukf import _fuzzy_ukf_step, kernel_layout

    target = Path(out_dir) if out_dir is not None else Path(__file__).resolve().parent
    target.mkdir(parents=True, exist_ok=True)
    cc = CC(MODULE)
    cc.output_dir = str(target)
    cc.verbose = False
    py_func = getattr(_fuzzy_ukf_step, "py_func", _fuzzy_ukf_step)
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
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=None, help="directory (default: the package)")
    args = ap.parse_args(argv)
    try:
        path = build(args.out)
    except Exception as exc:  # a missing compiler or headers: say so in one line
        print(f"kernels_aot: error: cannot build the AOT kernel: {exc}", file=sys.stderr)
        return 1
    print(f"built {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
