#!/usr/bin/env bash
# Create .venv with Python >= 3.11 and install the project with pinned versions.
# Usage: scripts/setup-venv.sh [EXTRAS]   e.g. scripts/setup-venv.sh dev
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-}"
if [[ -z "$PY" ]]; then
    for cand in python3.11 python3.12 python3.13 python3; do
        if command -v "$cand" >/dev/null 2>&1 \
            && "$cand" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
            PY="$cand"
            break
        fi
    done
fi
[[ -n "$PY" ]] || { echo "setup-venv: need Python >= 3.11" >&2; exit 1; }
if [[ ! -x .venv/bin/python ]]; then
    "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip
spec="."
extras="${1:-}"
# The development install also has the archive replay's extra (Dask, tqdm), which its tests use.
[[ ",$extras," == *,dev,* && ",$extras," != *,archive,* ]] && extras="$extras,archive"
[[ -n "$extras" ]] && spec=".[$extras]"
# setuptools announces every editable install with a multi-line notice (a warning category
# of its own, not a problem): a quiet install should not make a newcomer scroll past it.
PYTHONWARNINGS="ignore:Editable installation" \
    .venv/bin/python -m pip install -q -c constraints.txt -e "$spec"
# The estimator's kernels, made now so that nothing is compiled when the daemon starts: the
# ahead-of-time module (for the hardened unit: monitor/estimation/kernels_aot.py) and numba's
# cache of the JIT kernels, warmed in the directory the daemon reads (monitor/runtime/warm.py).
# A failure is one line (its own) and not the install's: the daemon then compiles at its
# first start.
.venv/bin/python -m monitor.estimation.kernels_aot --quiet || true
.venv/bin/python -m monitor.runtime.warm --quiet || true
