#!/bin/sh
# PID 1 of a User-Mode Linux guest of tests/support/vcan_harness.py, started as
# `init=/bin/sh -- THIS_FILE W` (the kernel appends arguments of its own after W): mounts the
# guest's pseudo file systems, loads the CAN modules, brings the vcan interfaces up, runs
# W/script.sh with only the environment of W/env.sh, writes its exit status to W/rc and powers
# off. Its own log goes to W/init.log; W/setup_failed says the guest could not be set up.
#
# Parameters: W, the host work directory (no white space), whose init.env sets SYSTEM_PATH,
# MODULES_DIR, MODULES (paths under MODULES_DIR, in load order), IFACES, CWD (the script's
# working directory) and DEADLINE (host epoch seconds when the script must be over).

W=$1
# shellcheck source=/dev/null # written by tests/support/vcan_harness.py for this run
. "$W/init.env"
export PATH="$SYSTEM_PATH"
exec >"$W/init.log" 2>&1
# shellcheck source-path=SCRIPTDIR source=common.sh
. "${0%/*}/common.sh"

fail() {
  echo "vcan-harness setup failed: $*"
  echo 125 >"$W/setup_failed"
  sync
  poweroff -f || halt -f
}

# The host root is mounted read-write via hostfs; these are the guest's own pseudo-fs.
mount -t proc proc /proc || fail "mount proc"
mount -t sysfs sysfs /sys || fail "mount sysfs"
# CONFIG_DEVTMPFS_MOUNT normally mounts /dev already; without it /dev is the host's /dev.
grep -q '^[^ ]* /dev devtmpfs ' /proc/mounts || mount -t devtmpfs devtmpfs /dev \
  || fail "mount devtmpfs"
[ -c /dev/null ] || fail "/dev/null missing"
mkdir -p /dev/shm /dev/pts
mount -t tmpfs -o mode=1777 tmpfs /dev/shm || fail "mount tmpfs on /dev/shm"
mount -t devpts devpts /dev/pts 2>/dev/null || true
ip link set lo up || true
for m in $MODULES; do
  insmod "$MODULES_DIR/$m" || fail "insmod $m"
done
for i in $IFACES; do
  vcan_up "$i" || fail "vcan_up $i"
done
cd "$CWD" || fail "cd $CWD"
# Stop at the host's deadline (the guest clock follows the host's), so output and status are
# flushed before the host would have to kill the whole kernel.
rem=$(awk -v d="$DEADLINE" -v n="$(date +%s.%N)" \
  'BEGIN { r = d - n; if (r < 0.1) r = 0.1; printf "%.3f", r }')
echo "running user script with ${rem}s left"
# env -i: the user script sees only env.sh (not TERM or kernel arguments such as mem=).
# shellcheck disable=SC2016 # $1 is expanded by the inner shell
timeout -k 2 "$rem" env -i /bin/sh -c '. "$1/env.sh" && exec /bin/sh "$1/script.sh"' sh "$W" \
  </dev/null >"$W/stdout" 2>"$W/stderr"
rc=$?
echo "user script exited with $rc"
sync
echo "$rc" >"$W/rc.tmp" && sync && mv "$W/rc.tmp" "$W/rc"
sync
poweroff -f || halt -f || echo o >/proc/sysrq-trigger
