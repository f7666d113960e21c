"""The units under a real systemd: PID 1 in a User-Mode Linux guest (tests/systemd_guest).

One boot (harness.py) installs the units as systemd/README.md says and runs
guest_checks.sh, which gathers the evidence; the tests below judge it, one per check:

1. systemd-networkd brings vcan0 up at boot (80-vcan0.netdev/.network).
2. ``systemctl start motor-monitor@vcan0`` returns once READY=1 came (Type=notify: active),
   and ``systemctl status`` shows the daemon's STATUS= counters.
3. A daemon that stops sending WATCHDOG=1 (SIGSTOP) is killed by the watchdog (SIGABRT,
   result 'watchdog') and restarted (NRestarts).
4. SIGKILL (``systemctl kill -s KILL``) while frames flow: restarted; the recordings and
   the raw bus logs of the state directory are intact and readable.
5. The sandbox holds with the AOT kernel running: probes inside the unit (an ExecStartPre=
   drop-in, so all of the unit's settings apply), each compared with the same probe as
   plain root -- a refusal counts as enforced only where plain root is allowed; where the
   guest kernel itself refuses, the directive is "not enforceable here" (with the reason).
6. ``LoadCredential=`` (secoc.conf.example) hands the SecOC key to the daemon, which
   verifies with it (the ECU's unsigned frames are rejected).
7. sim-ecu@vcan0 (a short fault scenario) drives the monitor: its events show the diagnosis.

``SYSTEMD_GUEST_KEEP=1`` keeps the guest's directory (its path is printed);
``SYSTEMD_GUEST_REUSE=DIR`` judges such a kept run again without booting.

Skipped without User-Mode Linux or mmdebstrap (or not as root); with CI set, a skip is a
failure (the ``vcan`` marker, tests/conftest.py). 1.5 to 2.5 minutes (more on a loaded
host: the guest has one CPU), plus ~1 minute once to build the root file system and ~30 s
to build the AOT kernel when its source has changed.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import can
import pytest

from monitor.sinks.journal import TRANSITION_ID
from tests.systemd_guest import harness
from tests.systemd_guest.harness import GuestRun

pytestmark = pytest.mark.vcan

UNIT = "motor-monitor@vcan0.service"

#: Outcomes, for the summary printed by the last test.
REPORT: dict[str, str] = {}
NOT_ENFORCEABLE: dict[str, str] = {}


@pytest.fixture(scope="module")
def guest() -> Iterator[GuestRun]:
    reuse = os.environ.get("SYSTEMD_GUEST_REUSE")
    if reuse:  # judge a kept run again (SYSTEMD_GUEST_KEEP=1 printed its directory)
        yield GuestRun(root=Path(reuse) / "root")
        return
    reason = harness.unavailable_reason()
    if reason is not None:
        pytest.skip(reason)
    t0 = time.monotonic()
    aot = harness.ensure_aot_kernel()
    harness.compile_bytecode()
    t1 = time.monotonic()
    tarball, build_s = harness.rootfs_tarball()
    workdir = harness.new_workdir()
    try:
        run = harness.boot_guest(workdir, tarball)
        run.timings.update(host_setup_s=t1 - t0, rootfs_build_s=build_s,
                           total_s=time.monotonic() - t0)
        REPORT["timings"] = ", ".join(f"{k} {v:.0f} s" for k, v in run.timings.items()) + \
            f" (AOT kernel {aot})"
        if run.values().get("done") != "1":
            pytest.fail("the guest checks did not finish (guest exit "
                        f"{run.returncode}, {run.timings['guest_s']:.0f} s):\n"
                        f"{run.diagnostics()}", pytrace=False)
        yield run
    finally:
        if harness.keep_workdir():
            print(f"\nsystemd guest kept in {workdir}")
        else:
            shutil.rmtree(workdir, ignore_errors=True)


def unit_journal(run: GuestRun) -> str:
    return run.text("unit-journal.txt")


def lines_matching(text: str, pattern: str) -> list[str]:
    return [ln for ln in text.splitlines() if re.search(pattern, ln)]


def states(run: GuestRun, name: str) -> list[dict[str, str]]:
    """The unit's states seen while waiting for a restart (guest_checks.sh wait_restarted)."""
    out = []
    for line in run.text(name).splitlines():
        fields = dict(f.split("=", 1) for f in line.split("|")[1:] if "=" in f)
        out.append(fields)
    return out


def show(run: GuestRun, name: str) -> dict[str, str]:
    return dict(ln.split("=", 1) for ln in run.text(name).splitlines() if "=" in ln)


def status_counts(status: str) -> dict[str, int]:
    return {k: int(v) for v, k in re.findall(r"(\d+) (frames|estimated|rejected|lost)", status)}


def why_not_started(run: GuestRun) -> str:
    """The daemon's own last words, for a start that failed."""
    journal = unit_journal(run)
    errors = lines_matching(journal, r"Error|error:|Failed|Traceback")
    hint = ""
    if "cannot allocate executable memory" in journal:
        hint = ("(importing numba allocates executable memory -- llvmlite's "
                "check_jit_execution() -- which MemoryDenyWriteExecute=yes forbids: with "
                "NUMBA_DISABLE_JIT=1 the daemon must not import numba at all)\n")
    return hint + ("\n".join(errors[-12:]) or journal[-3000:])


def evidence(run: GuestRun, key: str) -> dict[str, str]:
    """The guest's values, failing the check if the guest gave up before ``key``."""
    v = run.values()
    if key not in v:
        pytest.fail(f"the guest checks stopped early ({v.get('aborted', 'no reason given')}):"
                    f"\n{why_not_started(run)}", pytrace=False)
    return v


# -- 1 ----------------------------------------------------------------------------------------


def test_1_networkd_brings_vcan0_up_at_boot(guest: GuestRun) -> None:
    listing = guest.text("1-networkctl-list.txt")
    link = guest.text("1-link.txt")
    networkd = guest.text("1-networkd-journal.txt")
    assert re.search(r"\bvcan0\s+can\s+\S+\s+configured\b", listing), listing
    assert re.search(r"<[^>]*\bUP\b[^>]*>", link) and "link/can" in link, link
    assert re.search(r"^\s+vcan\b", link, re.M), link
    assert "vcan0: netdev ready" in networkd, networkd  # created by networkd, not by hand
    assert "vcan0: Configuring with /etc/systemd/network/80-vcan0.network" in networkd
    assert not lines_matching(networkd, r"80-vcan0\.net(dev|work):\d+"), networkd
    assert guest.text("0-pid1.txt").strip().endswith("/systemd")
    REPORT["1 networkd"] = (f"vcan0 created and configured at boot ({listing.split()[-1]}), "
                            f"{guest.text('0-boot-time.txt').splitlines()[0]}")


# -- 2 ----------------------------------------------------------------------------------------


def test_2_start_reaches_active_through_ready_and_shows_counters(guest: GuestRun) -> None:
    v = guest.values()
    after = show(guest, "2-after-start.txt")
    assert v.get("start_rc") == "0", f"systemctl start failed:\n{why_not_started(guest)}"
    # Type=notify: `systemctl start` returns, and the unit is active, only after READY=1
    assert after.get("Type") == "notify" and after.get("NotifyAccess") == "main"
    assert (after.get("ActiveState"), after.get("SubState")) == ("active", "running"), after
    assert after.get("StatusText", "").startswith("bus up;"), after  # STATUS= with READY=1
    journal = unit_journal(guest)
    first = journal.split("Started motor-monitor@vcan0.service", 1)[0]
    assert "monitoring socketcan:vcan0" in first  # the daemon's line before READY=1
    status = guest.text("2-status.txt")
    m = re.search(r'^\s*Status: "(.*)"$', status, re.M)
    assert m, status
    counts = status_counts(m.group(1))
    assert "frames" in m.group(1) and counts["frames"] > 0, m.group(1)
    assert counts["estimated"] > 0, m.group(1)
    REPORT["2 READY/STATUS"] = (f"active after {v['start_s']} s (systemctl start); "
                                f'systemctl status: Status: "{m.group(1)}"')


# -- 3 ----------------------------------------------------------------------------------------


def test_3_watchdog_kills_a_stopped_daemon_and_restarts_it(guest: GuestRun) -> None:
    v = evidence(guest, "watchdog_nrestarts_after")
    old = v.get("watchdog_old_pid")
    journal = unit_journal(guest)
    assert v.get("watchdog_usec") == "10s"  # the unit as shipped
    assert lines_matching(journal, r"Watchdog timeout \(limit 10s\)!"), why_not_started(guest)
    assert lines_matching(journal, rf"Killing process {old} \(motor-monitor\) with signal "
                                   r"SIGABRT"), journal[-3000:]
    assert lines_matching(journal, r"Main process exited, code=killed, status=6/ABRT")
    assert lines_matching(journal, r"Failed with result 'watchdog'")
    # the restart: the short auto-restart state as polled, or systemd's own line for it (the
    # polling may miss the state on a loaded machine: seen in a full run, the old pid active,
    # then the new one)
    seen = states(guest, "3-states.txt")
    assert any(s.get("Result") == "watchdog" and s.get("SubState") == "auto-restart"
               for s in seen) or lines_matching(
        journal, r"Scheduled restart job, restart counter is at \d+"), (seen, journal[-3000:])
    assert seen[-1].get("ActiveState") == "active", seen[-1]
    assert int(v["watchdog_nrestarts_after"]) == int(v["watchdog_nrestarts_before"]) + 1
    assert v["watchdog_new_pid"] not in (old, "0")
    REPORT["3 watchdog"] = (f"SIGSTOP pid {old}: 'Watchdog timeout (limit 10s)', SIGABRT, "
                            f"result 'watchdog', NRestarts {v['watchdog_nrestarts_before']} -> "
                            f"{v['watchdog_nrestarts_after']}, active again as pid "
                            f"{v['watchdog_new_pid']} {v['watchdog_restart_s']} s after the "
                            "SIGSTOP")


# -- 4 ----------------------------------------------------------------------------------------


@dataclass
class Listed:
    name: str
    size: int


def listing(run: GuestRun, name: str) -> dict[str, Listed]:
    out = {}
    for line in run.text(name).splitlines():
        parts = line.split()
        if len(parts) >= 7 and parts[0].startswith("-"):
            out[parts[-1]] = Listed(parts[-1], int(parts[4]))
    return out


def rrd_gamma_times(path: Path) -> list[float]:
    """Time stamps of node 0's gamma estimates in a recording (strict reader)."""
    import pyarrow as pa
    from rerun.chunk import RrdReader

    times: list[float] = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # no footer: the writer was killed
        for chunk in RrdReader(path).stream():
            if chunk.is_static or chunk.entity_path != "/node/0/gamma/estimate":
                continue
            col = chunk.to_record_batch().column("time").cast(pa.int64())
            times.extend(t / 1e9 for t in col.to_pylist())
    return times


def readable_rrd(path: Path) -> tuple[list[float], int]:
    """(gamma time stamps, bytes cut by salvage_rrd): a killed writer may leave a torn last
    message, which the daemon's salvage tool cuts off for strict readers."""
    from monitor.sinks.salvage import salvage_rrd

    try:
        return rrd_gamma_times(path), 0
    except (RuntimeError, ValueError):
        cut = salvage_rrd(path)
        return rrd_gamma_times(path), cut


def test_4_sigkill_restarts_with_the_recordings_intact(guest: GuestRun) -> None:
    v = evidence(guest, "kill_nrestarts_after")
    old = v.get("kill_old_pid")
    journal = unit_journal(guest)
    assert lines_matching(journal, rf"Sent signal SIGKILL to main process {old} "
                                   r"\(motor-monitor\)"), why_not_started(guest)
    assert lines_matching(journal, r"Main process exited, code=killed, status=9/KILL")
    assert lines_matching(journal, r"Failed with result 'signal'")
    seen = states(guest, "4-states.txt")
    assert seen[-1].get("ActiveState") == "active", seen[-1]
    assert int(v["kill_nrestarts_after"]) == int(v["kill_nrestarts_before"]) + 1
    assert v["kill_new_pid"] not in (old, "0")
    kill_time = float(v["kill_time"])  # just before `systemctl kill`
    killed_by = float(v["kill_returned"])  # once it had returned
    before = listing(guest, "4-files-before.txt")
    killed = listing(guest, "4-files-killed.txt")
    end = listing(guest, "end-files.txt")
    state = guest.state
    # Nothing of before the kill is lost or rewritten by the restarted daemon: every file is
    # still there, as long as when the kill left it; the restart opened new files. (The
    # events are appended to; the metrics file is rewritten every 5 s by design, its size
    # going with the digits of its values, so it may also shrink.)
    assert set(before) <= set(killed), (before, killed)
    for name, f in killed.items():
        assert name in end, f"{name} gone after the restart"
        if name == "monitor.prom":
            continue
        if name != "events.jsonl":
            assert end[name].size == f.size, f"{name} changed after the restart"
        if name in before:
            assert f.size >= before[name].size, (name, before[name], f)
    new = sorted(set(end) - set(killed))
    assert any(n.endswith(".rrd") for n in new), new
    # Every recording reads back (a torn last message cut off first, as salvage_rrd does);
    # the one being written at the kill has the estimates up to (nearly) the kill.
    recordings = sorted(n for n in end if n.endswith(".rrd"))
    at_kill = max(n for n in killed if n.endswith(".rrd"))
    cuts = {}
    last_rrd = float("nan")
    for name in recordings:
        times, cuts[name] = readable_rrd(state / name)
        if name in killed:  # (the daemon after the kill rejects every frame: check 6)
            assert times, f"{name}: no gamma estimates"
        if name == at_kill:
            assert max(times) <= killed_by, (name, killed_by, max(times))
            assert kill_time - max(times) < 1.5, (name, kill_time, max(times))
            last_rrd = max(times) - kill_time
    events = [json.loads(ln) for ln in (state / "events.jsonl").read_text().splitlines()]
    assert events, "events.jsonl is empty"
    raw = "raw bus logs: the monitor has no --raw-dir yet, not checked"
    if v.get("raw_dir") == "yes":
        logs = sorted(n for n in end if n.startswith("bus-") and n.endswith(".blf"))
        raw_at_kill = max(n for n in killed if n.startswith("bus-"))
        for name in logs:
            frames = list(can.LogReader(str(state / name)))
            if name == raw_at_kill:
                assert frames, f"{name}: no frames"
                assert kill_time - frames[-1].timestamp < 1.5, (name, frames[-1].timestamp)
                assert frames[-1].timestamp <= killed_by
                raw = (f"raw bus logs ({len(logs)} BLF files) readable; the one written at "
                       f"the kill has {len(frames)} frames, the last "
                       f"{frames[-1].timestamp - kill_time:+.2f} s from the call")
    REPORT["4 SIGKILL"] = (f"pid {old} killed, result 'signal', NRestarts "
                           f"{v['kill_nrestarts_before']} -> {v['kill_nrestarts_after']}, "
                           f"active again in {v['kill_restart_s']} s; {len(recordings)} "
                           f"recordings readable (torn bytes cut: {sum(cuts.values())}), "
                           "the one written at the kill reads up to it (last estimate "
                           f"{last_rrd:+.2f} s from the call of `systemctl kill`); "
                           f"{len(events)} events intact; {raw}")


# -- 5 ----------------------------------------------------------------------------------------

#: What the unit's sandbox must make of each probe (sandbox_probe.py), and the directive
#: responsible: the outcome, or "refused:" for a refusal with any errno.
EXPECTED = {
    "write_state_directory": ("StateDirectory=, UMask=0077", "ok:0600"),
    "write_etc": ("ProtectSystem=strict", "refused:EROFS"),
    "write_var_lib": ("ProtectSystem=strict", "refused:EROFS"),
    "list_root_home": ("ProtectHome=yes", "refused:"),
    "wx_mmap": ("MemoryDenyWriteExecute=yes", "refused:EPERM"),
    "wx_mprotect": ("MemoryDenyWriteExecute=yes", "refused:EPERM"),
    "af_inet": ("RestrictAddressFamilies=", "refused:EAFNOSUPPORT"),
    "af_inet6": ("RestrictAddressFamilies=", "refused:EAFNOSUPPORT"),
    "af_packet": ("RestrictAddressFamilies=", "refused:EAFNOSUPPORT"),
    "af_can": ("RestrictAddressFamilies= (allowed)", "ok"),
    "af_netlink": ("RestrictAddressFamilies= (allowed)", "ok"),
    "setpriority": ("SystemCallFilter=~@resources", "refused:EPERM"),
    "unshare_user": ("RestrictNamespaces=yes", "refused:EPERM"),
    "personality": ("LockPersonality=yes", "refused:EPERM"),
    "setuid_bit": ("RestrictSUIDSGID=yes", "refused:EPERM"),
    "list_kernel_modules": ("ProtectKernelModules=yes", "refused:"),
    "proc_meminfo": ("ProcSubset=pid", "refused:ENOENT"),
    "proc_pid1": ("ProtectProc=invisible", "refused:ENOENT"),
    "cgroup_mount": ("ProtectControlGroups=yes", "ok:ro"),
    "sys_mount": ("ProtectKernelTunables=yes", "ok:ro"),  # /sys read-only
}


def as_expected(got: str, want: str) -> bool:
    return got == want or (want.endswith(":") and got.startswith(want))


def probes(text: str) -> dict[str, str]:
    return {m[1]: m[2] for m in re.finditer(r"^PROBE (\w+)=(.*)$", text, re.M)}


def test_5_hardening_is_enforced_with_the_aot_kernel(guest: GuestRun) -> None:
    evidence(guest, "kill_nrestarts_after")
    unit = probes(guest.text("5-probe-unit.txt"))
    root = probes(guest.text("5-probe-root.txt"))
    assert unit, f"no probe output from the unit's ExecStartPre=:\n{why_not_started(guest)}"
    assert root, guest.text("5-probe-root.txt")
    failures = []
    enforced = []
    for name, (directive, want) in EXPECTED.items():
        got, plain = unit.get(name, "missing"), root.get(name, "missing")
        ok = as_expected(got, want)
        if ok and got.startswith("refused:") and plain.startswith("refused:"):
            # the guest kernel refuses it without any sandbox: nothing to enforce here
            NOT_ENFORCEABLE[f"{directive} ({name})"] = (
                f"the UML guest kernel refuses it to plain root too ({plain})"
                + (": the Debian UML kernel has no IPv6" if name == "af_inet6" else ""))
        elif ok:
            enforced.append(f"{directive}: {name} {got} (plain root: {plain})")
        else:
            failures.append(f"{directive}: {name} gave {got} (plain root: {plain})")
    # The main process itself: seccomp filters on, no privileges, no capabilities, the AOT
    # kernel mapped, no W+X mapping at all.
    status = dict(ln.split(":\t", 1) for ln in guest.text("5-main-status.txt").splitlines()
                  if ":\t" in ln)
    checks = {
        "Seccomp (SystemCallFilter=, MemoryDenyWriteExecute=, ...)":
            status.get("Seccomp", "").strip() == "2",
        "NoNewPrivs (NoNewPrivileges=yes)": status.get("NoNewPrivs", "").strip() == "1",
        "CapEff (CapabilityBoundingSet=)": int(status.get("CapEff", "1"), 16) == 0,
        "CapBnd (CapabilityBoundingSet=)": int(status.get("CapBnd", "1"), 16) == 0,
        "Uid (DynamicUser=yes)": status.get("Uid", "0").split()[0] not in ("", "0"),
    }
    failures += [f"main process: {k}: {status}" for k, ok in checks.items() if not ok]
    ns_unit = dict(kv.split("=") for kv in unit.get("namespaces", "ok:").removeprefix("ok:")
                   .split(",") if "=" in kv)
    ns_root = dict(kv.split("=") for kv in root.get("namespaces", "ok:").removeprefix("ok:")
                   .split(",") if "=" in kv)
    for ns, directive, differs in (("user", "PrivateUsers=yes", True),
                                   ("mnt", "PrivateMounts=/ProtectSystem=", True),
                                   ("uts", "ProtectHostname=yes", True),
                                   ("net", "no PrivateNetwork= (vcan0 visible)", False)):
        if (ns_unit.get(ns) != ns_root.get(ns)) != differs:
            failures.append(f"{directive}: {ns} namespace {ns_unit.get(ns)} vs plain root "
                            f"{ns_root.get(ns)}")
    if unit.get("tmp") == root.get("tmp"):
        failures.append(f"PrivateTmp=yes: the unit's /tmp is root's ({unit.get('tmp')})")
    devices = [int(p.get("dev_entries", "ok:0").removeprefix("ok:") or 0) for p in (unit, root)]
    if not 0 < devices[0] < devices[1]:
        failures.append(f"PrivateDevices=yes: /dev has {devices[0]} entries in the unit, "
                        f"{devices[1]} outside")
    ipdeny = probes(guest.text("5-ipdeny.txt")).get("udp_send")
    ipdeny_plain = probes(guest.text("5-ipdeny-control.txt")).get("udp_send")
    if ipdeny_plain != "ok":
        NOT_ENFORCEABLE["IPAddressDeny=any"] = f"UDP refused even without it ({ipdeny_plain})"
    elif ipdeny != "refused:EPERM":
        failures.append(f"IPAddressDeny=any: a UDP datagram to 127.0.0.1 gave {ipdeny}")
    aot = guest.text("5-aot-maps.txt")
    wx = guest.text("5-wx-maps.txt").strip()
    if "_fuzzy_ukf_aot" not in aot:
        failures.append("the daemon has not loaded the AOT kernel (no _fuzzy_ukf_aot mapping)")
    if wx:
        failures.append(f"W+X mappings in the daemon: {wx}")
    journal = unit_journal(guest)
    if lines_matching(journal, r"estimator runs\s+interpreted|no usable AOT kernel"):
        failures.append("the journal says the estimator runs interpreted")
    said = [ln for ln in lines_matching(journal, r"motor-monitor\[\d+\]: .*(?i:\bkernel\b)")
            if re.search(r"(?i)\b(aot|jit|python|interpreted)\b", ln)]
    if said and not any(re.search(r"(?i)\baot\b", ln) for ln in said):
        failures.append(f"the journal names another kernel: {said}")
    assert not failures, "\n".join(failures)
    kernel = (f"journal: {said[-1].split(': ', 1)[-1]}" if said else
              "the daemon logs no kernel line; /proc/PID/maps has _fuzzy_ukf_aot mapped and "
              "the journal has no 'interpreted' warning")
    REPORT["5 hardening"] = (f"{len(enforced)} probes refused/allowed as the unit says, main "
                             f"process Seccomp 2, NoNewPrivs 1, no capabilities, no W+X "
                             f"mapping; IPAddressDeny=any: UDP {ipdeny}; AOT kernel: {kernel}")


# -- 6 ----------------------------------------------------------------------------------------


def test_6_loadcredential_delivers_the_secoc_key(guest: GuestRun) -> None:
    v = evidence(guest, "secoc_estimated_after")
    cmdline = guest.text("6-cmdline.txt")
    cred = f"/run/credentials/{UNIT}/secoc.key"
    assert f"--key {cred}" in cmdline, f"{cmdline}\n{why_not_started(guest)}"
    assert "--secoc-state /var/lib/motor-monitor/vcan0/secoc-freshness.json" in cmdline
    assert v.get("credential_same") == "yes"  # the file's bytes, as /etc/motor-monitor had them
    mode, owner, _size, _path = guest.text("6-credential.txt").split()
    assert mode == "400" and owner == guest.text("6-main-uid.txt").strip(), \
        "the credential must be readable by the service's dynamic user alone"
    journal = guest.text("4-journal.txt")  # the start with the drop-in
    assert "SecOC freshness: fresh start, first sync trusted" in journal, journal
    rejected = int(v["secoc_rejected_after"]) - int(v["secoc_rejected_before"])
    estimated = int(v["secoc_estimated_after"]) - int(v["secoc_estimated_before"])
    assert rejected >= 300 and estimated == 0, guest.text("6-status.txt")
    # the same replay, to the daemon without the key (check 4), was estimated
    without_key = status_counts(guest.text("4-status-at-kill.txt"))
    assert without_key.get("estimated", 0) > 0, guest.text("4-status-at-kill.txt")
    reasons = sorted(set(re.findall(r"frame rejected \((\w+)", unit_journal(guest))))
    REPORT["6 LoadCredential"] = (f"{cred} (mode {mode}, the service's UID), identical to "
                                  f"/etc/motor-monitor/secoc.key, passed as --key; the ECU's "
                                  f"unsigned frames replayed: {rejected} rejected "
                                  f"({', '.join(reasons) or 'reason not logged'}), {estimated} "
                                  f"estimated (without the key: "
                                  f"{without_key.get('estimated')} estimated)")


# -- 7 ----------------------------------------------------------------------------------------


def test_7_sim_ecu_drives_the_monitor_to_a_diagnosis(guest: GuestRun) -> None:
    evidence(guest, "events_wait_s")
    text = guest.text("7-events.jsonl")
    assert text.strip(), f"no events from the monitor:\n{why_not_started(guest)}\n" \
        f"{guest.text('7-ecu-status.txt')}"
    events = [json.loads(ln) for ln in text.splitlines()]
    path = [(e["previous"], e["state"]) for e in events if e["node"] == 0]
    states_seen = [s for _, s in path]
    assert "fault" in states_seen and "outage" in states_seen, path
    assert states_seen.index("fault") < states_seen.index("outage"), path
    after = states_seen[states_seen.index("outage") + 1:]
    assert "fault_free" in after, path  # recovered at 4.5 s
    diag = guest.text("7-candump.txt")
    assert re.search(r"vcan0\s+180\s+\[8\]", diag), diag  # MonitorDiagnosis_N0 on the bus
    ecu = guest.text("7-ecu-status.txt")
    assert "active (running)" in ecu, ecu
    # Each transition is also in the journal as a structured entry that journalctl's own
    # field matching finds (the operator's query), with the same states as the events.
    entries = guest.journal_entries(f"MESSAGE_ID={TRANSITION_ID}", "NODE=0")
    journal_path = [(e.get("PREVIOUS"), e.get("STATE")) for e in entries]
    n = len(path)
    assert any(journal_path[i:i + n] == path for i in range(len(journal_path) - n + 1)), (
        journal_path, path)
    assert all(e.get("SYSLOG_IDENTIFIER") == "motor-monitor" and "GAMMA" in e
               and e.get("_SYSTEMD_UNIT") == "motor-monitor@vcan0.service"
               for e in entries), entries[-1]
    chain = " -> ".join([path[0][0], *states_seen])
    REPORT["7 sim-ecu"] = (f"sim-ecu@vcan0 active; node 0 events {chain}; "
                           "MonitorDiagnosis_N0 frames on the bus; the same transitions in "
                           f"journalctl MESSAGE_ID={TRANSITION_ID} NODE=0")


# -- summary ----------------------------------------------------------------------------------


#: The report's lines, one per check above (each test writes its own when it passes).
REPORTED = ("timings", "1 networkd", "2 READY/STATUS", "3 watchdog", "4 SIGKILL",
            "5 hardening", "6 LoadCredential", "7 sim-ecu")


def test_zz_report(guest: GuestRun) -> None:
    """The report of the boot is whole: every check passed and said what it saw, the guest
    was systemd as PID 1 and finished booting, and every directive the guest could not
    enforce has its reason. Printed, and kept in the cache directory (last-report.txt)."""
    version = guest.text("0-systemd-version.txt").strip()
    boot = (guest.text("0-boot-time.txt").splitlines() or ["(no systemd-analyze time)"])[0]
    lines = [f"{k}: {v}" for k, v in sorted(REPORT.items())]
    lines += [f"not enforceable in UML: {k}: {v}" for k, v in NOT_ENFORCEABLE.items()]
    lines.append(f"guest: {version}, {boot}")
    print("\n" + "\n".join(lines))
    harness.cache_dir().mkdir(parents=True, exist_ok=True)
    (harness.cache_dir() / "last-report.txt").write_text("\n".join(lines) + "\n")
    missing = [k for k in REPORTED if not REPORT.get(k)]
    assert not missing, f"checks that reported nothing (failed or did not run): {missing}"
    assert re.match(r"systemd \d+ ", version), f"PID 1 was not systemd: {version!r}"
    assert boot.startswith("Startup finished in "), f"the guest did not finish booting: {boot}"
    assert all(NOT_ENFORCEABLE.values()), NOT_ENFORCEABLE
