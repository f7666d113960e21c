#!/bin/sh
# tests/rig/test_rig_vcan.py (run by tests/support/vcan_scripts.py with /bin/sh): candump and
# `motor-monitor run --rig` (node 2, a raw record in raw/) on vcan0, then the rig's virtual
# twin (`sim-ecu --rig`, fault-outage-recovery); the monitor is stopped, then candump.
#
# Parameters (environment): SCRIPTS, this directory; OUT, the directory to write into; RIG,
# the rig file.

: "${SCRIPTS:?}" "${OUT:?}" "${RIG:?}"
# shellcheck source-path=SCRIPTDIR source=common.sh
. "$SCRIPTS/common.sh"
cd "$OUT" || exit 1

start_candump vcan0
mkdir -p raw
start_monitor run --interface socketcan --channel vcan0 --rig "$RIG" --nodes 2 \
    --events "$OUT/ev.jsonl" --raw-dir "$OUT/raw"
ready mon.err "monitoring" 150
# every sample sent, late if the one-CPU guest is busy (the rig's alive counter tells the
# monitor the true sample period; a skipped sample would be a loss)
nice -n 10 sim-ecu --interface socketcan --channel vcan0 --rig "$RIG" --node 2 \
    --scenario fault-outage-recovery --seed 1 --max-catch-up "$CATCH_UP" 2> ecu.err
echo "ecu_rc=$?"
finish
