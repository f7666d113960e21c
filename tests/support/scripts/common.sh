# shellcheck shell=sh
# Functions of the robustness boots (boot_a.sh, boot_b.sh source this file; see
# tests/support/boots.py). POSIX sh: the vcan harness runs the boot scripts with /bin/sh.
#
# Parameters (environment): OUT, the host directory the boot writes into (also its working
# directory); GAP, seconds of calm after each inject window.

set -u
: "${OUT:?the directory to write into}" "${GAP:?seconds between inject windows}"
cd "$OUT" || exit 1

now() { date +%s.%N; }

# mark NAME: print mark_NAME=<guest time>, the clock of the kernel's frame time stamps
mark() { echo "mark_$1=$(now)"; }

# alive: 1 if the daemon ($MON) is still running, else 0
alive() { if kill -0 "$MON" 2>/dev/null; then echo 1; else echo 0; fi; }

# wait_for FILE PATTERN SECONDS [FROM_LINE]: poll until FILE has PATTERN after FROM_LINE
wait_for() {
  n=0
  while ! tail -n +"${4:-1}" "$1" 2>/dev/null | grep -q -- "$2"; do
    n=$((n + 1))
    [ "$n" -gt $(($3 * 10)) ] && return 1
    sleep 0.1
  done
}

# caught_up PID SECONDS: wait until the process PID keeps up with its input, i.e. uses under
# 60 % of the CPU over half a second (from its utime + stime in /proc, USER_HZ = 100), for at
# most SECONDS; returns 1 if it never did. BUSY: its CPU ticks in the last half second. A daemon still working through a backlog has
# frames unread in its socket, which no flush of its outputs can save.
caught_up() {
  n=0
  prev=$(awk '{print $14 + $15}' "/proc/$1/stat" 2>/dev/null) || return 1
  while [ "$n" -lt $(($2 * 2)) ]; do
    sleep 0.5
    cur=$(awk '{print $14 + $15}' "/proc/$1/stat" 2>/dev/null) || return 1
    BUSY=$((cur - prev))
    [ "$BUSY" -lt 30 ] && return 0
    prev=$cur
    n=$((n + 1))
  done
  return 1
}

# inject KEY FRAME...: cansend each frame, in a window marked by mark_KEY_start/end
inject() {
  key=$1; shift
  mark "${key}_start"
  ok=0
  for f in "$@"; do nice -n 19 cansend vcan0 "$f" && ok=$((ok + 1)); done
  mark "${key}_end"
  echo "sent_${key}=$ok"
  echo "alive_${key}=$(alive)"
  sleep "$GAP"
}

# ecu SEED LOG: start a healthy node-0 ECU (until stopped); its PID in $ECU. It shares the
# guest's one CPU with the monitor, at the same priority (the injectors and the command-line
# checks run at nice 19). No SimTruth frames: the boots compare with the capture, not with the
# truth, and in the guest every system call costs some 0.3 ms of its CPU. Held up, it sends its
# late samples late rather than skipping them (the monitor reads up to 15 periods late as late).
ecu() {
  sim-ecu --interface socketcan --channel vcan0 --node 0 --scenario healthy --duration 0 \
      --no-truth --seed "$1" --max-catch-up 100000 2> "$2" &
  # shellcheck disable=SC2034 # read by the boot scripts that source this file
  ECU=$!
}
