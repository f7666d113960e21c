#!/usr/bin/env bash
# Fresh machine -> everything checked: system packages (apt-get), the virtual environment,
# lint (ruff, and shellcheck on the shell), types (mypy), the direction of the imports (import-linter: the contracts in
# pyproject.toml) and the whole test suite, vcan integration tests included
# (through User-Mode Linux where the kernel has no SocketCAN).
set -euo pipefail
cd "$(dirname "$0")/.."
bash .ci/install-system.sh
bash scripts/setup-venv.sh dev
.venv/bin/ruff check .
shellcheck -x scripts/*.sh .ci/run .ci/*.sh tests/support/scripts/*.sh tests/systemd_guest/*.sh
.venv/bin/mypy
.venv/bin/lint-imports --no-cache
# Two runs of pytest: the tests that need no bus in parallel (pytest-xdist, one worker a
# core, at most 4: they are CPU-bound), then the vcan tests (marker `vcan`) alone, one
# after the other, since their guest's timing is what they measure. Exit status 5 is "no
# test selected" (arguments that name only tests of the other run).
workers=$(nproc)
(( workers > 4 )) && workers=4
status=0
.venv/bin/pytest -q -n "$workers" -m "not vcan" --durations=25 "$@" || status=$?
[[ $status -eq 5 ]] && status=0
vcan_status=0
.venv/bin/pytest -q -m vcan --durations=10 "$@" || vcan_status=$?
[[ $vcan_status -eq 5 ]] && vcan_status=0
exit $(( status != 0 ? status : vcan_status ))
