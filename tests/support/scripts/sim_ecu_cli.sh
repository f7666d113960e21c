#!/bin/sh
# tests/sim_ecu/test_sim_ecu.py (run by tests/support/vcan_scripts.py with /bin/sh): sim-ecu's
# command line on real SocketCAN: a second of a fault run
# captured by candump into cap.log (every sample sent, late if the guest is loaded: the
# frames are compared with an offline run), a missing interface, an interface set down.
# Prints ecu_rc, bad_rc, down_rc and dump_rc. Parameters (environment): SCRIPTS, this
# directory; OUT, the directory to write into.

: "${SCRIPTS:?}" "${OUT:?}"
# shellcheck source-path=SCRIPTDIR source=common.sh
. "$SCRIPTS/common.sh"
cd "$OUT" || exit 1

start_candump vcan0
sleep 0.3
sim-ecu --interface socketcan --channel vcan0 --node 2 --scenario fault-outage-recovery \
    --duration 1 --seed 5 --max-catch-up "$CATCH_UP" 2> ecu.err
echo "ecu_rc=$?"
stop_candump
sim-ecu --interface socketcan --channel doesnotexist0 --node 2 --scenario healthy 2> bad.err
echo "bad_rc=$?"
ip link set vcan0 down
sim-ecu --interface socketcan --channel vcan0 --node 2 --scenario healthy --duration 0.3 \
    2> down.err
echo "down_rc=$?"
