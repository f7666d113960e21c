#!/bin/sh
# Boot B of the robustness tests (tests/support/boots.py; run by the vcan harness with
# /bin/sh): the daemon and a healthy ECU, a cangen flood while the daemon's RSS is sampled,
# 3 s of calm once the daemon has caught up, SIGKILL.
#
# Parameters (environment): SCRIPTS, this directory; OUT (see common.sh);
# FLOOD_S, seconds of flood.

: "${SCRIPTS:?}" "${OUT:?}" "${FLOOD_S:?}"
# shellcheck source-path=SCRIPTDIR source=common.sh
. "$SCRIPTS/common.sh"
cd "$OUT" || exit 1

start_monitor -v run --interface socketcan --channel vcan0 --nodes 0 --rrd "$OUT/b.rrd" \
    --events "$OUT/ev.jsonl"
ecu 2 ecu.err
ready ev.jsonl '"state":"fault_free"' 200
( while kill -0 "$MON" 2>/dev/null; do
    echo "$(now) $(awk '/^VmRSS/ {print $2}' "/proc/$MON/status" 2>/dev/null)"
    sleep 0.5
  done ) > rss.txt 2> /dev/null &
sleep 2
echo "tx_before=$(cat /sys/class/net/vcan0/statistics/tx_packets)"
mark flood_start
# the flooders at nice 10: on a real bus a flood comes from other nodes and takes
# none of the monitor's CPU; here they share the guest's one CPU with it
nice -n 10 cangen vcan0 -g 0 -I r -L r -D r -i 2> cangen1.err &
G1=$!
nice -n 10 cangen vcan0 -g 0 -m -i 2> cangen2.err &
G2=$!
sleep "$FLOOD_S"
kill -INT "$G1" "$G2"; wait "$G1" "$G2"
mark flood_end
echo "tx_after=$(cat /sys/class/net/vcan0/statistics/tx_packets)"
echo "alive_flood=$(alive)"
# The calm: from the moment the daemon has worked through what the flood left in its socket
# (at once on an idle machine; later when the guest's one CPU is shared with a loaded host).
BUSY=-1
if caught_up "$MON" 30; then echo "caught_up=1"; else echo "caught_up=0"; fi
echo "busy_ticks=$BUSY"
mark calm
sleep 3
mark kill
kill -KILL "$MON"
mark killed
wait "$MON"; echo "mon_rc=$?"
stop ecu "$ECU"
