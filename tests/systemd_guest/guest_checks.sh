#!/bin/bash
# The checks of tests/systemd_guest, run inside the User-Mode Linux guest by
# guest-checks.service once boot has finished, with systemd as PID 1. It only gathers
# evidence: command outputs into $RESULTS/*.txt and KEY=VALUE lines into $RESULTS/values;
# the host (test_systemd_guest.py) judges them after the guest has powered off.
# Settings from /etc/guest-checks.env: INSTALL (/opt/motor-monitor: the project, mounted
# read-only, with its .venv), RESULTS, IFACE, STATE (the state directory as root sees it).
#
# The guest has one slow CPU and a daemon start costs ~20 s of it, so the order keeps the
# starts to three: (1) the unit as shipped: checks 1, 2, 7 (with sim-ecu@), 5a; SIGSTOP ->
# the watchdog restarts it (2): check 3; with the probe and SecOC drop-ins installed,
# SIGKILL -> restarted (3): checks 4, 5b, 6.
set -u
R=${RESULTS:?}
U=motor-monitor@${IFACE:?}.service
E=sim-ecu@${IFACE}.service
DROPINS=$INSTALL/tests/systemd_guest/dropins
PROBE=$INSTALL/tests/systemd_guest/sandbox_probe.py
PS4='+ ${EPOCHREALTIME} '
set -x

rec() { printf '%s=%s\n' "$1" "$2" >>"$R/values"; }
since() { awk -v a="$1" -v b="$EPOCHREALTIME" 'BEGIN { printf "%.2f", b - a }'; }
prop() { systemctl show -P "$1" "$U"; }
snap() { systemctl show "$U" -p ActiveState,SubState,Result,NRestarts,MainPID \
    -p ExecMainCode,ExecMainStatus,StatusText | paste -sd'|'; }
field() { # FIELD |SNAPSHOT
    local v=${2#*"|$1="}
    echo "${v%%|*}"
}
# wait_until SECONDS CMD...: poll CMD once a second until it succeeds (a systemctl call
# costs the guest's one CPU a tenth of a second, which the daemon's start needs)
wait_until() {
    local end=$((SECONDS + $1))
    shift
    until "$@"; do
        ((SECONDS < end)) || return 1
        sleep 1
    done
}
# wait_restarted OLD_PID LOG: poll (cheap: the daemon is down) until systemd has seen
# OLD_PID go, then block in `systemctl start` until the automatic restart is active (a start
# job waits for a pending automatic restart). Every state seen is appended to LOG.
wait_restarted() {
    local s end=$((SECONDS + 60))
    while :; do
        s="|$(snap)"
        echo "$EPOCHREALTIME$s" >>"$2"
        [ "$(field MainPID "$s")" != "$1" ] && break
        ((SECONDS < end)) || return 1
        sleep 1
    done
    timeout 120 systemctl start "$U"
    echo "$EPOCHREALTIME|$(snap)" >>"$2"
}
counter() { # NAME: a count of the daemon's STATUS= line ("... 120 frames, 54 estimated, ...")
    local s
    s=$(prop StatusText)
    [[ $s =~ ([0-9]+)\ $1 ]] && echo "${BASH_REMATCH[1]}" || echo 0
}
journal_sync() { journalctl --sync 2>/dev/null || sleep 1; }
files() { ls -ln --time-style=+%s "$STATE" >"$1" 2>&1; }
# finish: stop the daemon (SIGTERM: it closes its last recording), leave the evidence, end
finish() {
    local t=$EPOCHREALTIME
    systemctl stop "$U" "$E"
    rec stop_s "$(since "$t")"
    systemctl show "$U" -p ActiveState,Result,NRestarts >"$R/end.txt"
    files "$R/end-files.txt"
    cp -a "$STATE" "$R/state"  # a tmpfs in the guest (harness.py): the host reads this copy
    journalctl -b --no-pager -o short-monotonic -u "$U" -u "$E" >"$R/unit-journal.txt" 2>&1
    rec "done" 1
    exit 0
}
# abort WHY: nothing after this can work; say why and end (the host fails the checks)
abort() {
    rec aborted "$1"
    finish
}

# -- 0: the system -------------------------------------------------------------------------
systemctl is-system-running --wait >"$R/0-system-state.txt" 2>&1
systemctl list-units --failed --no-legend --plain >"$R/0-failed-units.txt" 2>&1
systemd-analyze time >"$R/0-boot-time.txt" 2>&1
systemctl --version | head -1 >"$R/0-systemd-version.txt"
readlink /proc/1/exe >"$R/0-pid1.txt"
findmnt -rn -o TARGET,FSTYPE,OPTIONS >"$R/0-mounts.txt"
if grep -rq -- '--raw-dir' "$INSTALL/monitor/app/"; then
    # the raw bus log beside the recordings (a directory that exists: the StateDirectory),
    # if the monitor has the option by now (check 4 looks at it too)
    echo "MONITOR_ARGS=\"--raw-dir /var/lib/motor-monitor/$IFACE\"" \
        >"/etc/motor-monitor/$IFACE.env"
    rec raw_dir yes
else
    rec raw_dir no
fi

# -- 1: systemd-networkd brings vcan0 up at boot ----------------------------------------------
wait_until 20 sh -c "networkctl list --no-legend --no-pager $IFACE | grep -q configured"
networkctl list --no-legend --no-pager >"$R/1-networkctl-list.txt" 2>&1
ip -details link show "$IFACE" >"$R/1-link.txt" 2>&1
journalctl -b -o cat --no-pager -u systemd-networkd >"$R/1-networkd-journal.txt" 2>&1

# -- 2: the unit as shipped reaches active through READY=1; STATUS= counters ------------------
t=$EPOCHREALTIME
systemctl start "$U"
rec start_rc $?
rec start_s "$(since "$t")"
systemctl show "$U" -p Type,ActiveState,SubState,Result,MainPID,NRestarts,StatusText \
    -p WatchdogUSec,NotifyAccess,InvocationID >"$R/2-after-start.txt"
[ "$(prop ActiveState)" = active ] || abort "$U did not start"

# -- 7: sim-ecu@ drives the monitor; its events show the diagnosis ----------------------------
# the scenario: fault at 1.5 s, outage at 3 s, recovered at 4.5 s after the ECU's start
t=$EPOCHREALTIME
systemctl start "$E"
rec ecu_start_rc $?
wait_until 60 grep -q '"previous":"no_data"' "$STATE/events.jsonl" \
    || abort "no estimate from $E's frames"  # the first estimate
rec frames_wait_s "$(since "$t")"
sleep 1.2  # STATUS= comes once a second
systemctl status --no-pager -n 0 "$U" >"$R/2-status.txt" 2>&1
systemctl status --no-pager -n 0 "$E" >"$R/7-ecu-status.txt" 2>&1
# 3.5 s of the ECU's (unsigned) current and voltage frames, replayed in checks 4 and 6
timeout 20 candump -L -n 420 "$IFACE,110:7F0,120:7F0" >"$R/ecu-frames.log" 2>/dev/null
wait_until 45 grep -q '"previous":"outage"' "$STATE/events.jsonl"
rec events_wait_s "$(since "$t")"
cp "$STATE/events.jsonl" "$R/7-events.jsonl" 2>/dev/null
# the monitor's MonitorDiagnosis_N0 frames (0x180) on the bus
candump -n 5 -T 3000 "$IFACE,180:7FF" >"$R/7-candump.txt" 2>&1
systemctl stop "$E"  # the CPU is needed for the restarts below

# -- 5a: the running daemon: AOT kernel loaded, sandboxed -------------------------------------
pid=$(prop MainPID)
grep -F _fuzzy_ukf_aot "/proc/$pid/maps" >"$R/5-aot-maps.txt"
awk '$2 ~ /w.x/' "/proc/$pid/maps" >"$R/5-wx-maps.txt"
grep -E '^(Uid|NoNewPrivs|Seccomp|Seccomp_filters|CapEff|CapBnd):' "/proc/$pid/status" \
    >"$R/5-main-status.txt"

# -- 3: a daemon that stops sending WATCHDOG=1 (SIGSTOP) is killed and restarted ---------------
rec watchdog_usec "$(prop WatchdogUSec)"
rec watchdog_nrestarts_before "$(prop NRestarts)"
rec watchdog_old_pid "$pid"
t=$EPOCHREALTIME
kill -STOP "$pid"
wait_restarted "$pid" "$R/3-states.txt" || abort "no restart after the watchdog"
rec watchdog_restart_s "$(since "$t")"
pid=$(prop MainPID)
rec watchdog_new_pid "$pid"
rec watchdog_nrestarts_after "$(prop NRestarts)"

# -- 4: SIGKILL while frames flow -> restarted, recordings intact -----------------------------
# with the drop-ins of checks 5 and 6 in place, so that this restart also applies them: the
# sandbox probed from inside the unit (ExecStartPre=), and the SecOC key as a credential
# (secoc.conf.example, installed as systemd/README.md says)
mkdir -p "/etc/systemd/system/$U.d"
cp "$DROPINS/sandbox-probe.conf" "/etc/systemd/system/$U.d/"
install -D -m 0644 "$INSTALL/systemd/motor-monitor@.service.d/secoc.conf.example" \
    /etc/systemd/system/motor-monitor@.service.d/secoc.conf
systemctl daemon-reload
rec kill_nrestarts_before "$(prop NRestarts)"
rec kill_old_pid "$pid"
files "$R/4-files-before.txt"
canplayer -I "$R/ecu-frames.log" &
player=$!
sleep 1
rec kill_time "$EPOCHREALTIME"
t=$EPOCHREALTIME
systemctl kill -s KILL "$U"
rec kill_returned "$EPOCHREALTIME"  # the kill came between kill_time and this
prop StatusText >"$R/4-status-at-kill.txt"  # the last STATUS= the killed daemon sent
wait "$player"
files "$R/4-files-killed.txt"
wait_restarted "$pid" "$R/4-states.txt" || abort "no restart after SIGKILL"
rec kill_restart_s "$(since "$t")"
pid=$(prop MainPID)
rec kill_new_pid "$pid"
rec kill_nrestarts_after "$(prop NRestarts)"
files "$R/4-files-after.txt"

# -- 5b: what the sandbox refused the probe (ExecStartPre= of this start) -----------------------
journal_sync
inv=$(prop InvocationID)
journalctl --no-pager -o cat "_SYSTEMD_INVOCATION_ID=$inv" >"$R/4-journal.txt"
grep '^PROBE ' "$R/4-journal.txt" >"$R/5-probe-unit.txt"
/usr/bin/python3 "$PROBE" >"$R/5-probe-root.txt" 2>&1  # the same, as root, no sandbox
# IPAddressDeny= on its own (the unit refuses AF_INET sockets before it would matter)
systemd-run --quiet --wait --pipe -p DynamicUser=yes -p IPAddressDeny=any \
    /usr/bin/python3 "$PROBE" --udp >"$R/5-ipdeny.txt" 2>&1
systemd-run --quiet --wait --pipe -p DynamicUser=yes \
    /usr/bin/python3 "$PROBE" --udp >"$R/5-ipdeny-control.txt" 2>&1

# -- 6: LoadCredential= delivered the key; the daemon verifies with it ------------------------
systemctl show "$U" -p ActiveState,SubState,LoadCredential >"$R/6-after-start.txt"
tr '\0' ' ' <"/proc/$pid/cmdline" >"$R/6-cmdline.txt"
cred=/run/credentials/$U/secoc.key
stat -c '%a %u %s %n' "$cred" >"$R/6-credential.txt" 2>&1
stat -c '%u' "/proc/$pid" >"$R/6-main-uid.txt"
if cmp -s "$cred" /etc/motor-monitor/secoc.key; then
    rec credential_same yes
else
    rec credential_same no
fi
# the ECU's frames carry no MAC: with the key, the daemon must reject them
rec secoc_rejected_before "$(counter rejected)"
rec secoc_estimated_before "$(counter estimated)"
canplayer -I "$R/ecu-frames.log"
sleep 1.5  # STATUS= comes once a second
prop StatusText >"$R/6-status.txt"
rec secoc_rejected_after "$(counter rejected)"
rec secoc_estimated_after "$(counter estimated)"

# -- the end: a clean stop (SIGTERM) closes the last recording ---------------------------------
finish
