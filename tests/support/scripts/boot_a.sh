#!/bin/sh
# Boot A of the robustness tests (tests/support/boots.py; run by the vcan harness with
# /bin/sh): the daemon, a healthy ECU and candump; every kind of bad frame; the interface
# down and up; a silent ECU; a replay; the interface deleted and re-created; SIGTERM.
#
# Parameters (environment): SCRIPTS, this directory; OUT and GAP (see common.sh);
# INJECT, a file of lines "KEY FRAME..." (cansend syntax), one bad-frame window each;
# REPLAYS, how many times the ECU's last current frame is sent again.

: "${SCRIPTS:?}" "${OUT:?}" "${GAP:?}" "${INJECT:?}" "${REPLAYS:?}"
# shellcheck source-path=SCRIPTDIR source=common.sh
. "$SCRIPTS/common.sh"
cd "$OUT" || exit 1

# --record-flush-s 0.25: fewer chunks for Rerun's threads on the guest's one CPU (~5 ms each);
# what a SIGKILL loses at the default 0.1 s is boot B's test.
# candump on every interface, error frames included: it survives vcan0 being deleted
start_candump any,0:0,#FFFFFFFF
start_monitor -v run --interface socketcan --channel vcan0 --nodes 0 --rrd "$OUT/a.rrd" \
    --events "$OUT/ev.jsonl" --record-flush-s 0.25
ecu 1 ecu1.err
# Wrong CLI on a real SocketCAN kernel, while the daemon starts: a channel that does not exist.
( nice -n 19 motor-monitor run --interface socketcan --channel vcan9 > /dev/null \
      2> cli_mon_nochan.err
  echo "$?" > cli_mon_nochan.rc ) &
CLI1=$!
( nice -n 19 sim-ecu --interface socketcan --channel vcan9 --node 0 --scenario healthy > /dev/null \
      2> cli_ecu_nochan.err
  echo "$?" > cli_ecu_nochan.rc ) &
CLI2=$!
ready cap.log ' 180#' 200 cap.log ' 110#' 200
wait "$CLI1" "$CLI2"
sleep 2
mark bad_start
# the bad frames, one window per line of $INJECT
while read -r key frames; do
  # shellcheck disable=SC2086 # one word per frame: cansend syntax has no blanks or globs
  inject "$key" $frames
done < "$INJECT"
# interface down for 1 s and up again, the ECU running
mark down
ip link set down vcan0
sleep 1
vcan_up vcan0
mark up
echo "alive_linkdown=$(alive)"
sleep 2.5
# a silent ECU
mark ecu_stop
stop ecu1 "$ECU"
mark ecu_stopped
sleep 1.5
# a replay: the ECU's last current frame again, same alive counter
LAST=$(grep ' vcan0 110#' cap.log | tail -n 1 | awk '{print $3}')
echo "replayed=$LAST"
set --
if [ -n "$LAST" ]; then
  i=0
  while [ "$i" -lt "$REPLAYS" ]; do set -- "$@" "$LAST"; i=$((i + 1)); done
fi
inject replay "$@"
# the interface deleted and re-created under the running daemon; a new ECU
mark del
ip link del vcan0
sleep 1
vcan_up vcan0
mark add
echo "alive_linkdel=$(alive)"
N0=$(wc -l < cap.log)
ecu 3 ecu2.err
if wait_for cap.log ' 110#' 200 $((N0 + 1)); then echo "ecu2_up=1"; else echo "ecu2_up=0"; fi
mark ecu2_up
sleep 2.5
mark term
stop mon "$MON"
mark term_done
stop ecu2 "$ECU"
stop_candump
