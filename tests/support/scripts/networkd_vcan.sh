#!/bin/sh
# tests/integration/test_systemd.py (run by the vcan harness with /bin/sh, as root): in a new
# network namespace (the host's interfaces untouched) and mount namespace, with a tmpfs on
# /run/systemd holding only our two files and a read-only sysfs (networkd then does not wait
# for udev, which is not running here), start systemd-networkd, wait until it reports vcan0
# configured, and print the link after "=== link"; networkd's log goes to
# $WORKDIR/networkd.log.
#
# Parameters (environment): SCRIPTS, this directory; WORKDIR, with 80-vcan0.netdev and
# 80-vcan0.network; NETWORKD, the systemd-networkd binary.

: "${SCRIPTS:?}" "${WORKDIR:?}" "${NETWORKD:?}"
# shellcheck source-path=SCRIPTDIR source=common.sh
. "$SCRIPTS/common.sh"

if [ "${1:-}" != "--inside" ]; then
  exec unshare --net --mount --propagation private /bin/sh "$SCRIPTS/networkd_vcan.sh" --inside
fi
set -e
log="$WORKDIR/networkd.log"
mount -t sysfs -o ro sysfs /sys
mount -t tmpfs tmpfs /run/systemd
mkdir -p /run/systemd/network
cp "$WORKDIR/80-vcan0.netdev" "$WORKDIR/80-vcan0.network" /run/systemd/network/
SYSTEMD_LOG_LEVEL=debug SYSTEMD_LOG_TARGET=console SYSTEMD_LOG_COLOR=0 \
    "$NETWORKD" >"$log" 2>&1 &
pid=$!
wait_for "$log" "vcan0: State changed: configuring -> configured" 10 || true
echo "=== link"
ip -details link show vcan0 || true
kill "$pid"; wait "$pid" || true
