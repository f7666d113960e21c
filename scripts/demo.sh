#!/usr/bin/env bash
# Fresh machine -> the demo: virtual ECU and monitor over python-can's in-process bus,
# writing out/demo/demo.rrd and a PNG report. No CAN hardware needed.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup-venv.sh experiments
.venv/bin/motor-monitor demo --out out/demo "$@"
