#!/bin/sh
# tests/integration/test_canopen_vcan.py (run by tests/support/vcan_scripts.py with /bin/sh):
# candump and `motor-monitor run --rig` (node 1) on vcan0, a CANopen master
# (canopen_master.py, the canopen library's Network) listening, then the CiA 402 twin
# (`sim-ecu --rig`) running scenario.toml; the master ends once the twin is done (ecu.done),
# then the monitor, then candump.
#
# Parameters (environment): SCRIPTS, this directory; OUT, the directory to write into (with
# scenario.toml); RIG, the rig file; EDS, the drive's EDS.

: "${SCRIPTS:?}" "${OUT:?}" "${RIG:?}" "${EDS:?}"
# shellcheck source-path=SCRIPTDIR source=common.sh
. "$SCRIPTS/common.sh"
cd "$OUT" || exit 1

start_candump vcan0
start_monitor run --interface socketcan --channel vcan0 --rig "$RIG" --nodes 1 \
    --events "$OUT/ev.jsonl"
ready mon.err "monitoring" 150
python "$SCRIPTS/canopen_master.py" "$EDS" 60 > master.out 2> master.err &
MASTER=$!
started
wait_for master.out "master up" 60 || { echo "master=0"; exit 4; }
nice -n 10 sim-ecu --interface socketcan --channel vcan0 --rig "$RIG" --node 1 \
    --scenario scenario.toml --seed 1 --max-catch-up "$CATCH_UP" 2> ecu.err
echo "ecu_rc=$?"
touch ecu.done
wait "$MASTER"; echo "master_rc=$?"
finish
