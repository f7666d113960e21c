#!/bin/sh
# The live runs of tests/integration/test_integration_vcan.py (run by
# tests/support/vcan_scripts.py with /bin/sh): candump and the monitor on vcan0, then, by RUN:
#   live       one ECU (node 0, fault-outage-recovery), the monitor recording to live.rrd;
#   player     canplayer replaying $OUT/short.log (recorded on "can0") into vcan0;
#   two_nodes  node 0 (fault-outage-recovery) and node 1 (healthy, 16 s) at once.
# Then the monitor is stopped (SIGTERM) and candump.
#
# Parameters (environment): SCRIPTS, this directory; OUT, the directory to write into; RUN.

: "${SCRIPTS:?}" "${OUT:?}" "${RUN:?live, player or two_nodes}"
# shellcheck source-path=SCRIPTDIR source=common.sh
. "$SCRIPTS/common.sh"
cd "$OUT" || exit 1

start_candump vcan0
case "$RUN" in
  # A recording monitor hands its recording to the .rrd file every 0.25 s, the most allowed
  # without --raw-dir: in the one-CPU guest every chunk handed to Rerun costs ~5 ms of CPU in
  # the SDK's threads, 50 chunks/s at the default 0.1 s. What a SIGKILL loses at the default
  # is boot B's test.
  live) set -- 0 --rrd "$OUT/live.rrd" --record-flush-s 0.25 ;;
  player) set -- 0 ;;
  two_nodes) set -- 0,1 ;;
  *) echo "RUN: live, player or two_nodes, not $RUN" >&2; exit 2 ;;
esac
nodes=$1; shift
start_monitor run --interface socketcan --channel vcan0 --nodes "$nodes" \
    --events "$OUT/ev.jsonl" "$@"
# The monitor is up when its MonitorDiagnosis frames (no_data at 10 Hz for the nodes it was
# told to watch) reach candump: that proves both are running (the monitor's start-up, with
# its compiled kernels, takes ~15 s in UML).
ready cap.log ' 180#' 150
case "$RUN" in
  live)
    sim-ecu --interface socketcan --channel vcan0 --node 0 --scenario fault-outage-recovery \
        --seed 1 --max-catch-up "$CATCH_UP" 2> ecu.err
    echo "ecu_rc=$?"
    ;;
  player)
    canplayer -I "$OUT/short.log" vcan0=can0 2> player.err
    echo "player_rc=$?"
    ;;
  two_nodes)
    sim-ecu --interface socketcan --channel vcan0 --node 0 --scenario fault-outage-recovery \
        --seed 1 --max-catch-up "$CATCH_UP" 2> ecu0.err &
    E0=$!
    sim-ecu --interface socketcan --channel vcan0 --node 1 --scenario healthy --duration 16 \
        --seed 0 --max-catch-up "$CATCH_UP" 2> ecu1.err &
    E1=$!
    wait "$E0"
    echo "ecu0_rc=$?"
    wait "$E1"
    echo "ecu1_rc=$?"
    ;;
esac
finish
