# shellcheck shell=sh
# The shell functions of every vcan script in this directory, each once: the test scripts
# (run by tests/support/vcan_scripts.py and tests/support/boots.py with /bin/sh, so POSIX sh)
# and the User-Mode Linux init of tests/support/vcan_harness.py (uml_init.sh) source this file.
# Sourcing it only sets -u, STARTED and CATCH_UP and defines functions; a test script then
# enters its directory:
#   : "${SCRIPTS:?}" "${OUT:?}"
#   . "$SCRIPTS/common.sh"
#   cd "$OUT" || exit 1
#
# Variables the functions use: GAP (inject), seconds of calm after each inject window. They
# set: MON (start_monitor), DUMP (start_candump), ECU (ecu), BUSY (caught_up), STARTED (every
# PID started in the background, which `ready` stops when the run cannot start).

set -u
STARTED=""
# The ECUs share the guest's one CPU with the monitor and candump at the same priority (at
# nice 10 they were held up 0.1-0.25 s at a time behind them): their late samples go out late
# rather than being skipped (a skip is a loss to the monitor), which reads a frame up to 15
# periods late as late (monitor.pipeline.periods) and takes a held-up socket's backlog in
# batches. sim-ecu --max-catch-up takes this.
CATCH_UP=100000

now() { date +%s.%N; }

# mark NAME: print mark_NAME=<guest time>, the clock of the kernel's frame time stamps
mark() { echo "mark_$1=$(now)"; }

# alive: 1 if the daemon ($MON) is still running, else 0
alive() { if kill -0 "$MON" 2>/dev/null; then echo 1; else echo 0; fi; }

# vcan_up NAME [MTU]: create the vcan interface NAME unless it exists, set its MTU (default
# 72, CAN FD's: vcan's before Linux 6.2 and a CAN FD controller's; a newer kernel's vcan
# starts at CAN XL's 2060, on which can-utils 2021 refuses FD frames; an interface must be
# down for that), and bring it up
vcan_up() {
  [ -e "/sys/class/net/$1" ] || ip link add dev "$1" type vcan || return 1
  ip link set "$1" down && ip link set "$1" mtu "${2:-72}" || return 1
  ip link set up "$1"
}

# wait_for FILE PATTERN SECONDS [FROM_LINE]: poll until FILE has PATTERN (from line FROM_LINE
# on); returns 1 after SECONDS without it
wait_for() {
  n=0
  while ! tail -n +"${4:-1}" "$1" 2>/dev/null | grep -q -- "$2"; do
    n=$((n + 1))
    [ "$n" -gt $(($3 * 10)) ] && return 1
    sleep 0.1
  done
}

# settled FILE SECONDS: wait until FILE has not grown for a second (at most SECONDS)
settled() {
  n=0; last=-1
  while [ "$n" -lt "$2" ]; do
    size=$(stat -c %s "$1" 2>/dev/null || echo 0)
    [ "$size" = "$last" ] && return 0
    last=$size; n=$((n + 1)); sleep 1
  done
}

# caught_up PID SECONDS: wait until the process PID keeps up with its input, i.e. uses under
# 60 % of the CPU over half a second (from its utime + stime in /proc, USER_HZ = 100), for at
# most SECONDS; returns 1 if it never did. BUSY: its CPU ticks in the last half second. A
# daemon still working through a backlog has frames unread in its socket, which no flush of
# its outputs can save.
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

# started: record the last background process ($!) in STARTED
started() { STARTED="$STARTED $!"; }

# ready FILE PATTERN SECONDS [FILE PATTERN SECONDS]...: once every FILE has its PATTERN,
# print ready=1; else print ready=0, stop every process in STARTED and exit 3
ready() {
  while [ "$#" -ge 3 ]; do
    if ! wait_for "$1" "$2" "$3"; then
      echo "ready=0"
      # shellcheck disable=SC2086 # one word per PID
      kill $STARTED 2>/dev/null
      exit 3
    fi
    shift 3
  done
  echo "ready=1"
}

# stop NAME PID [SIGNAL]: send SIGNAL (default TERM) to PID, wait for it, print NAME_rc=status
stop() {
  kill -"${3:-TERM}" "$2"
  wait "$2"
  echo "$1_rc=$?"
}

# start_monitor ARG...: motor-monitor ARG... in the background, its stderr into mon.err; its
# PID in MON
start_monitor() {
  motor-monitor "$@" 2> mon.err &
  MON=$!
  started
}

# finish: 2 s on (past the monitor's 0.5 s silence timeout: its nodes turn no_data), stop the
# monitor ($MON), then candump; prints mon_rc= and dump_rc=
finish() {
  sleep 2
  stop mon "$MON"
  stop_candump
}

# start_candump CHANNELS: candump -L of CHANNELS (candump syntax) into cap.log; its PID in
# DUMP. A 4 MiB socket buffer: on a loaded guest candump falls behind for a while instead of
# losing frames (its capture is the reference the checks read).
start_candump() {
  candump -r 4194304 -L "$1" > cap.log 2> candump.err &
  DUMP=$!
  started
}

# stop_candump: once candump has written its backlog (cap.log no longer grows), stop it and
# print dump_rc=status
stop_candump() {
  settled cap.log 30
  stop dump "$DUMP" INT
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
  sleep "${GAP:?seconds between inject windows}"
}

# ecu SEED LOG: start a healthy node-0 ECU (until stopped); its PID in $ECU. It shares the
# guest's one CPU with the monitor, at the same priority (the injectors and the command-line
# checks run at nice 19). No SimTruth frames: the boots compare with the capture, not with the
# truth, and in the guest every system call costs some 0.3 ms of its CPU.
ecu() {
  sim-ecu --interface socketcan --channel vcan0 --node 0 --scenario healthy --duration 0 \
      --no-truth --seed "$1" --max-catch-up "$CATCH_UP" 2> "$2" &
  # shellcheck disable=SC2034 # read by the boot scripts that source this file
  ECU=$!
  started
}
