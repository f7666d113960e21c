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
.venv/bin/pytest -q --durations=25 "$@"
