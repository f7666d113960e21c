#!/bin/sh
# tests/rig/test_canfd_vcan.py (run by tests/support/vcan_scripts.py with /bin/sh, vcan0 and
# vcan1 up): vcan0 made classic (MTU 16), where an FD-capable socket must still read classic
# frames and cannot send FD (classic_probe.py); vcan1 made CAN FD (MTU 72), with candump, the
# FD rig's monitor (node 1, raw record in raw/, metrics in rig.prom) and a monitor of our
# classic bus (ours.prom); four hand-made frames (cansend ID##<flags>...), then the rig's twin;
# the rig's monitor is stopped, then candump, then our bus's monitor.
#
# Parameters (environment): SCRIPTS, this directory; OUT, the directory to write into; RIG,
# the FD rig file.

: "${SCRIPTS:?}" "${OUT:?}" "${RIG:?}"
# shellcheck source-path=SCRIPTDIR source=common.sh
. "$SCRIPTS/common.sh"
cd "$OUT" || exit 1

# (this kernel's vcan starts as CAN FD, MTU 72: set both)
vcan_up vcan0 16
vcan_up vcan1 72
echo "mtu0=$(cat /sys/class/net/vcan0/mtu)"
echo "mtu1=$(cat /sys/class/net/vcan1/mtu)"
python "$SCRIPTS/classic_probe.py" vcan0 > classic.out 2> classic.err
cat classic.out
start_candump vcan1
mkdir -p raw
start_monitor -v run --interface socketcan --channel vcan1 --rig "$RIG" --nodes 1 \
    --events "$OUT/ev.jsonl" --raw-dir "$OUT/raw" --raw-format log \
    --metrics "$OUT/rig.prom" --receive-buffer-kib 2048
# (no --nodes: no node of ours ever sends, so this monitor publishes no diagnosis frames)
motor-monitor run --interface socketcan --channel vcan1 \
    --metrics "$OUT/ours.prom" --receive-buffer-kib 2048 2> ours.err &
OURS=$!
started
ready mon.err "monitoring" 240 ours.err "monitoring" 240
# payload: COUNT bytes of the hex byte BYTE
payload() { i=0; while [ "$i" -lt "$2" ]; do printf '%s' "$1"; i=$((i + 1)); done; }
cansend vcan1 "110##1$(payload 11 8)"; echo "cs1=$?"
cansend vcan1 "110##3$(payload 22 64)"; echo "cs2=$?"
cansend vcan1 "7FF##0$(payload 33 12)"; echo "cs3=$?"
cansend vcan1 023#0000000000000000; echo "cs4=$?"
sim-ecu --interface socketcan --channel vcan1 --rig "$RIG" --node 1 \
    --scenario fault-outage-recovery --seed 1 --max-catch-up "$CATCH_UP" 2> ecu.err
echo "ecu_rc=$?"
finish
stop ours "$OURS"
