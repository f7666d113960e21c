#!/bin/sh
# tests/integration/test_vcan_harness.py, real peers on vcan0 and vcan1 (run by the vcan
# harness with /bin/sh): (a) cansend -> candump; (b) python-can <-> can-utils; (c) ip link
# down/up/del/add.
# Prints key=value lines and the captures (A: ..., B: ..., B_JSON: ..., C_...: ...).
#
# Parameters (environment): SCRIPTS, this directory.

: "${SCRIPTS:?}"
# shellcheck source-path=SCRIPTDIR source=common.sh
. "$SCRIPTS/common.sh"
T=$(mktemp -d)

# (a) candump must be listening before the frame is sent: resend until it has captured one.
candump -L -n 1 vcan0 >"$T/a.log" 2>"$T/a.err" &
dump=$!
i=0
while [ ! -s "$T/a.log" ] && [ "$i" -lt 100 ]; do
  cansend vcan0 123#DEADBEEF
  sleep 0.1
  i=$((i + 1))
done
wait "$dump"
echo "a_rc=$?"
sed 's/^/A: /' "$T/a.log"

# (b) python-can sends (candump sees it) and receives what cansend sent.
candump -L -n 1 vcan0,321:7FF >"$T/b.log" 2>"$T/b.err" &
dump=$!
python - "$T/b.log" <<'PY'
import json, os, subprocess, sys, time

import can

log = sys.argv[1]
out = {}
with can.Bus(
    interface="socketcan",
    channel="vcan0",
    can_filters=[{"can_id": 0x456, "can_mask": 0x7FF, "extended": False}],
) as bus:
    tx = can.Message(arbitration_id=0x321, data=[1, 2, 3, 4], is_extended_id=False)
    for _ in range(100):
        bus.send(tx)
        time.sleep(0.1)
        if os.path.getsize(log) > 0:
            break
    t0 = time.time()
    subprocess.run(["cansend", "vcan0", "456#CAFE"], check=True)
    rx = bus.recv(timeout=10)
    t1 = time.time()
    out["channel_info"] = bus.channel_info
out["t0"], out["t1"] = t0, t1
if rx is not None:
    out["rx_id"] = rx.arbitration_id
    out["rx_data"] = rx.data.hex()
    out["rx_ts"] = rx.timestamp
    out["rx_channel"] = rx.channel
print("B_JSON:", json.dumps(out))
PY
echo "b_py_rc=$?"
wait "$dump"
echo "b_rc=$?"
sed 's/^/B: /' "$T/b.log"

# (c) link down: sends fail; up again: sends work.  Also delete and add interfaces.
ip link set vcan0 down && echo "c_down_rc=0"
echo "C_DOWN: $(ip -o link show vcan0)"
if cansend vcan0 001#00 2>"$T/c.err"; then echo "c_send_down=ok"; else echo "c_send_down=fail"; fi
echo "C_DOWN_ERR: $(cat "$T/c.err")"
ip link set vcan0 up && echo "c_up_rc=0"
echo "C_UP: $(ip -o link show vcan0)"
if cansend vcan0 001#00; then echo "c_send_up=ok"; else echo "c_send_up=fail"; fi
ip link del vcan1 && echo "c_del_rc=0"
vcan_up vcan2 && echo "c_add_rc=0"
echo "C_LINKS: $(ip -o link show type vcan | awk -F': ' '{print $2}' | tr '\n' ' ')"
rm -rf "$T"
