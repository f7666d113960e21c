"""Bad input against the real monitor daemon on a real vcan bus, shared by
``tests/test_robustness_vcan.py`` (assertions) and ``tests/bench/bad_input.py`` (the matrix).

Two User-Mode Linux boots (or native vcan, see tests/vcan_harness.py) do everything:

* **Boot A** -- the daemon (``motor-monitor -v run --nodes 0 --rrd --events``), a healthy
  ``sim-ecu`` of node 0 and ``candump -L any`` (error frames included; bound to every
  interface, so it survives the interface being deleted). Then, one after the other:
  every kind of bad frame, sent with ``cansend`` in its own time window (see
  `frame_kinds`); the interface set down for 1 s and up again with the ECU running; the
  ECU stopped (a silent node); the last captured current frame of the ECU sent again
  (a replay: same alive counter); the interface deleted and re-created
  (``ip link del/add``) and a new ECU started; SIGTERM. Plus, in the background while the
  daemon starts, the two programs pointed at a CAN channel that does not exist.
* **Boot B** -- the daemon and a healthy ECU, then ``cangen`` at full rate for 10 s (random
  standard frames, and a mix of extended, remote and CAN FD frames) while the daemon's RSS
  is sampled every 0.5 s, 3 s of calm, and a SIGKILL of the daemon.

What the host reads afterwards: the scripts' ``key=value`` lines (``mark_*`` times in the
guest's clock, which is the clock of the kernel's frame time stamps), the candump capture,
the daemon's ``.rrd`` recording (samples, and the counters it logs about once per second of
bus time: `Snapshots`), its ``--events`` JSON lines and its stderr.

Counter windows: the daemon logs all its counters together, at the first estimated sample
at least 1 s after the previous log, so each bad-frame window (a few hundred ms) is
bracketed by the last snapshot before it and the first one after it; the kinds are 1.5 s
apart so that no bracket holds two windows (checked by `BootA.bracket`).
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np
import pyarrow as pa
from cantools.autosar.end_to_end import apply_profile2_crc
from numpy.typing import NDArray
from rerun.chunk import RrdReader

from monitor.bus.codec import Decoded, Kind, MotorDatabase, RejectReason
from monitor.pipeline import MonitorConfig, MonitorPipeline
from monitor.sinks.rerun import salvage_rrd
from tests.vcan_harness import PROJECT_ROOT, VcanResult

Array = NDArray[np.float64]
RunOnVcan = Callable[..., VcanResult]

BIN = Path(sys.executable).parent
MONITOR_EXE = BIN / "motor-monitor"
SIM_ECU_EXE = BIN / "sim-ecu"
RERUN_EXE = BIN / "rerun"

NODE = 0  # the monitored node
OTHER = 1  # a node the daemon is told not to monitor
F1 = 0.15  # default thresholds: the healthy ECU must stay below F1
NO_DATA = 3  # HealthState raw value
SILENCE_S = 0.5  # the daemon's silence timeout
MAX_KILL_LOSS_S = 0.25  # after SIGKILL, readable up to this long before the kill
PER_KIND = 20  # frames of each bad kind
REPLAYS = 10
KIND_GAP_S = 1.5  # between bad-frame windows (> the 1 s counter period)
FLOOD_S = 10.0
TIME_TOL_S = 3e-6  # candump prints microseconds; the .rrd has float seconds -> ns

#: Outcome counters of the daemon that a genuine ECU never moves: a bad kind must move only
#: its own ones (prefixes).
BAD_OUTCOMES = ("rejected/", "ignored/", "bus/error_frames", "bus/errors/", "e2e/repeated",
                "time/non_monotonic")
#: Counters that together count every received frame exactly once (at each snapshot).
OUTCOME_PREFIXES = ("rejected/", "ignored/", "bus/error_frames", "e2e/repeated",
                    "time/non_monotonic", "samples/no_voltage", "samples/estimated",
                    "samples/voltage", "samples/truth")

CAN_ERR_FLAG = 0x20000000
CAN_EFF_MASK = 0x1FFFFFFF


# ----------------------------------------------------------------------------- frames


@dataclass(frozen=True)
class Frame:
    """One classic CAN (or CAN FD) frame, as cansend writes and candump -L prints it."""

    arbitration_id: int
    data: bytes = b""
    extended: bool = False
    remote: bool = False
    error: bool = False
    fd: bool = False
    dlc: int = 0  # remote frames: the DLC they carry

    @property
    def key(self) -> tuple[int, bytes, bool, bool, bool, bool]:
        return (self.arbitration_id, self.data, self.extended, self.remote, self.error, self.fd)

    def cansend(self) -> str:
        """The frame in cansend's syntax (``123#11223344``, ``00000123#R8``, ...)."""
        if self.error:
            ident = f"{CAN_ERR_FLAG | self.arbitration_id:08X}"
        elif self.extended:
            ident = f"{self.arbitration_id:08X}"
        else:
            ident = f"{self.arbitration_id:03X}"
        if self.remote:
            return f"{ident}#R{self.dlc or ''}"
        return f"{ident}#{self.data.hex().upper()}"

    def message(self, t: float) -> can.Message:
        return can.Message(timestamp=t, arbitration_id=self.arbitration_id,
                           data=b"" if self.remote else self.data,
                           dlc=self.dlc if self.remote else len(self.data),
                           is_extended_id=self.extended, is_remote_frame=self.remote,
                           is_error_frame=self.error, is_fd=self.fd, check=False)


def parse_frame(text: str) -> Frame:
    """A frame in cansend / candump -L syntax (the inverse of `Frame.cansend`)."""
    ident, sep, rest = text.partition("#")
    if not sep or len(ident) not in (3, 8):
        raise ValueError(f"not a CAN frame: {text!r}")
    can_id = int(ident, 16)
    fd = rest.startswith("#")
    if fd:
        rest = rest[2:]  # the flags nibble
    error = len(ident) == 8 and bool(can_id & CAN_ERR_FLAG)
    extended = len(ident) == 8 and not error
    arb = can_id & CAN_EFF_MASK if len(ident) == 8 else can_id
    if error:
        arb = can_id & ~CAN_ERR_FLAG & CAN_EFF_MASK
    if rest[:1] in ("R", "r"):
        return Frame(arb, b"", extended, True, error, fd, int(rest[1:] or 0))
    return Frame(arb, bytes.fromhex(rest.replace(".", "")), extended, False, error, fd)


@dataclass(frozen=True)
class Captured:
    t: float
    frame: Frame


_CANDUMP_RE = re.compile(r"^\((\d+\.\d+)\)\s+(\S+)\s+(\S+)")


def read_candump(path: Path) -> list[Captured]:
    """A ``candump -L`` log (error frames as error frames, which python-can's reader does not
    do), in file order."""
    out: list[Captured] = []
    if not path.exists():
        return out
    for line in path.read_text(errors="replace").splitlines():
        m = _CANDUMP_RE.match(line)
        if m is None:
            continue
        try:
            out.append(Captured(float(m.group(1)), parse_frame(m.group(3))))
        except ValueError:
            continue
    return out


@dataclass(frozen=True)
class FrameKind:
    """A kind of bad frame: what is sent, and which daemon counters must count it.

    `expect` maps a counter to its increase per frame sent; every other counter of
    `BAD_OUTCOMES` must not move. `reason` says why the daemon must not use the frame.
    """

    key: str  # [a-z_]+, used in the guest script's marks
    title: str
    frames: tuple[Frame, ...]
    expect: Mapping[str, int]
    reason: str = ""


def _current(mdb: MotorDatabase, node: int, amps: float, counter: int) -> bytes:
    return mdb.encode_current(node, amps, counter)


def _with_crc(mdb: MotorDatabase, kind: Kind, node: int, payload: bytes) -> bytes:
    protected = apply_profile2_crc(payload, mdb.message(kind, node))
    assert protected is not None
    return bytes(protected)


def _decode(mdb: MotorDatabase, f: Frame) -> Decoded | RejectReason:
    r = mdb.decode_can(f.message(0.0))
    return r if isinstance(r, Decoded) else r.reason


def _out_of_range(mdb: MotorDatabase, counter: int) -> Frame:
    """A frame with a valid CRC whose physical value lies beyond its DBC range."""
    candidates: list[tuple[Kind, str]] = [("current", "ArmatureCurrent"), ("truth", "TrueGamma")]
    for kind, name in candidates:
        msg = mdb.message(kind, NODE)
        sig = msg.get_signal_by_name(name)
        assert sig.maximum is not None
        values: dict[str, float] = {s.name: 0 for s in msg.signals}
        values[name] = float(sig.maximum) + 10.0 * float(sig.scale)
        if "Counter" in values:
            values["Counter"] = counter
        try:
            payload = bytes(msg.encode(values, scaling=True, padding=False, strict=False))
        except Exception:  # the raw field cannot carry it: try the next candidate
            continue
        if kind != "truth":
            payload = _with_crc(mdb, kind, NODE, payload)
        f = Frame(msg.frame_id, payload)
        if _decode(mdb, f) == RejectReason.OUT_OF_RANGE:
            return f
    raise AssertionError("no out-of-range frame can be built from this DBC")


def _malformed(mdb: MotorDatabase, counter: int) -> Frame:
    """A frame with a valid CRC and a reserved (unused) bit set."""
    valid: list[tuple[Kind, bytes]] = [
        ("truth", mdb.encode_truth(NODE, 0.5, 123.45, 100.0)),
        ("diagnosis", mdb.encode_diagnosis(NODE, "fault_free", 0.0, 0.0, 2, counter)),
        ("current", _current(mdb, NODE, 123.45, counter)),
    ]
    for kind, payload in valid:
        for bit in range(63, 7, -1):
            data = bytearray(payload)
            data[bit // 8] ^= 1 << (bit % 8)
            raw = bytes(data) if kind == "truth" else _with_crc(mdb, kind, NODE, bytes(data))
            f = Frame(mdb.frame_id(kind, NODE), raw)
            if _decode(mdb, f) == RejectReason.MALFORMED:
                return f
    raise AssertionError("no frame with a reserved bit can be built from this DBC")


def frame_kinds(mdb: MotorDatabase, n: int = PER_KIND) -> list[FrameKind]:
    """The bad frames of boot A, built on the host with our codec (values distinct from the
    healthy ECU's ~68 A, so a frame that reached the estimator would show)."""
    cur_id = mdb.frame_id("current", NODE)
    amps = 123.45
    valid = [_current(mdb, NODE, amps, k % 16) for k in range(n)]

    def flip(p: bytes) -> bytes:
        d = bytearray(p)
        d[2] ^= 0x01  # the low byte of the current: CRC no longer matches
        return bytes(d)

    unknown = [0x555, 0x000, 0x7FF, 0x130, 0x17F, 0x190, 0x7DF, 0x7F0]
    errors = {
        "bus_off": Frame(0x040, bytes(8), error=True),
        "controller/rx_overflow": Frame(0x004, bytes([0, 0x01, 0, 0, 0, 0, 0, 0]), error=True),
        "controller/rx_error_passive": Frame(0x004, bytes([0, 0x10, 0, 0, 0, 0, 0, 0]),
                                             error=True),
    }
    kinds = [
        FrameKind("unknown_id", "unknown ID", tuple(
            Frame(unknown[k % len(unknown)], bytes(range(k, k + 8))) for k in range(n)),
            {"rejected/unknown_id": 1}, "not in the DBC"),
        FrameKind("wrong_length", "wrong length (node 0 current, 4 bytes)", tuple(
            Frame(cur_id, p[:4]) for p in valid), {"rejected/wrong_length": 1}),
        FrameKind("bad_crc", "bad CRC (a valid frame with one bit flipped)", tuple(
            Frame(cur_id, flip(p)) for p in valid), {"rejected/bad_crc": 1}),
        FrameKind("out_of_range", "out of range (valid CRC, value beyond the DBC range)", tuple(
            _out_of_range(mdb, k % 16) for k in range(n)), {"rejected/out_of_range": 1}),
        FrameKind("malformed", "malformed (valid CRC, reserved bit set)", tuple(
            _malformed(mdb, k % 16) for k in range(n)), {"rejected/malformed": 1}),
        FrameKind("remote", "remote frame (node 0 current ID)", tuple(
            Frame(cur_id, remote=True, dlc=8) for _ in range(n)), {"rejected/remote_frame": 1}),
        FrameKind("extended", "extended ID (node 0 current ID and payload)", tuple(
            Frame(cur_id, p, extended=True) for p in valid), {"rejected/extended_id": 1}),
        FrameKind("masquerade", "spoofed: node 0's valid frame under node 1's ID", tuple(
            Frame(mdb.frame_id("current", OTHER), p) for p in valid), {"rejected/bad_crc": 1}),
        FrameKind("other_node", "spoofed: valid frame of an unmonitored node (1)", tuple(
            Frame(mdb.frame_id("current", OTHER), _current(mdb, OTHER, amps, k % 16))
            for k in range(n)), {"ignored/node": 1}),
        FrameKind("fake_diagnosis", "spoofed: another monitor's MonitorDiagnosis (outage)",
                  tuple(Frame(mdb.frame_id("diagnosis", NODE),
                              mdb.encode_diagnosis(NODE, "outage", 1.0, 220.0, 9, k % 16))
                        for k in range(n)), {"ignored/diagnosis": 1}),
    ]
    for name, frame in errors.items():
        kinds.append(FrameKind(
            "err_" + name.split("/")[-1], f"error frame: {name}", (frame,) * max(1, n // 2),
            {"bus/error_frames": 1, f"bus/errors/{name}": 1}))
    return kinds


def check_kinds_offline(mdb: MotorDatabase, kinds: Sequence[FrameKind]) -> dict[str, dict[str,
                                                                                      int]]:
    """Feed each kind to a fresh pipeline (nodes=(0,)) after a valid voltage: the counters
    each moves. Used to check the frames are built as intended before any vcan run."""
    out: dict[str, dict[str, int]] = {}
    for kind in kinds:
        pipe = MonitorPipeline(mdb, MonitorConfig(nodes=(NODE,)))
        pipe.feed(Frame(mdb.frame_id("voltage", NODE), mdb.encode_voltage(NODE, 220.0, 0))
                  .message(1.0))
        before = dict(pipe.counters)
        for i, f in enumerate(kind.frames):
            pipe.feed(f.message(2.0 + 0.01 * i))
        out[kind.key] = {k: v - before.get(k, 0) for k, v in pipe.counters.items()
                         if v != before.get(k, 0)}
    return out


# ----------------------------------------------------------------------------- recordings


def read_rrd(path: Path) -> dict[str, tuple[Array, Array]]:
    """(time [s], value) of every Scalars entity of an .rrd file, sorted by time. A file of a
    killed writer is read from a copy, salvaged if its last message is torn."""
    def read(p: Path) -> dict[str, tuple[Array, Array]]:
        ts: dict[str, list[NDArray[np.int64]]] = {}
        vs: dict[str, list[Array]] = {}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # no footer: a warning
            for chunk in RrdReader(p).stream():
                if chunk.is_static:
                    continue
                rb = chunk.to_record_batch()
                if "Scalars:scalars" not in rb.schema.names or "time" not in rb.schema.names:
                    continue
                ts.setdefault(chunk.entity_path, []).append(
                    rb.column("time").cast(pa.int64()).to_numpy())
                vs.setdefault(chunk.entity_path, []).append(
                    rb.column("Scalars:scalars").flatten().to_numpy())
        out: dict[str, tuple[Array, Array]] = {}
        for e in ts:
            t, v = np.concatenate(ts[e]), np.concatenate(vs[e])
            order = np.argsort(t, kind="stable")
            out[e] = (t[order] / 1e9, v[order].astype(np.float64))
        return out

    try:
        return read(path)
    except RuntimeError:
        with tempfile.TemporaryDirectory() as tmp:
            copy = Path(tmp) / path.name
            shutil.copyfile(path, copy)
            salvage_rrd(copy)
            return read(copy)


def series(rrd: Mapping[str, tuple[Array, Array]], entity: str) -> tuple[Array, Array]:
    return rrd.get(entity, (np.zeros(0), np.zeros(0)))


COUNTERS_PREFIX = "/monitor/counters/"


@dataclass
class Snapshots:
    """The daemon's counters as logged into the .rrd: `t[i]` and each counter at `t[i]`."""

    t: Array
    values: dict[str, NDArray[np.int64]]

    @classmethod
    def from_rrd(cls, rrd: Mapping[str, tuple[Array, Array]]) -> Snapshots:
        cols = {e[len(COUNTERS_PREFIX):]: tv for e, tv in rrd.items()
                if e.startswith(COUNTERS_PREFIX)}
        t = np.unique(np.concatenate([tv[0] for tv in cols.values()])) if cols else np.zeros(0)
        values: dict[str, NDArray[np.int64]] = {}
        for name, (ct, cv) in cols.items():
            col = np.zeros(len(t), dtype=np.int64)
            idx = np.searchsorted(t, ct)
            col[idx] = np.round(cv).astype(np.int64)  # absent from a row: did not exist yet
            values[name] = col
        return cls(t, values)

    def __len__(self) -> int:
        return len(self.t)

    def at(self, i: int) -> dict[str, int]:
        return {k: int(v[i]) for k, v in self.values.items() if v[i]}

    def last_before(self, t: float) -> int | None:
        i = int(np.searchsorted(self.t, t, side="left")) - 1
        return i if i >= 0 else None

    def first_after(self, t: float) -> int | None:
        i = int(np.searchsorted(self.t, t, side="right"))
        return i if i < len(self.t) else None

    def delta(self, i: int | None, j: int | None) -> dict[str, int]:
        """Counters that changed from snapshot i (None: the start) to snapshot j."""
        if j is None:
            return {}
        a = {} if i is None else self.at(i)
        b = self.at(j)
        return {k: b.get(k, 0) - a.get(k, 0) for k in set(a) | set(b)
                if b.get(k, 0) != a.get(k, 0)}


def outcome_total(c: Mapping[str, int]) -> int:
    """Frames accounted for by the outcome counters (each frame in exactly one of them)."""
    return sum(v for k, v in c.items()
               if any(k == p or (p.endswith("/") and k.startswith(p)) for p in OUTCOME_PREFIXES))


def bad_outcomes(c: Mapping[str, int]) -> dict[str, int]:
    return {k: v for k, v in c.items()
            if v and any(k == p or (p.endswith("/") and k.startswith(p)) for p in BAD_OUTCOMES)}


# ----------------------------------------------------------------------------- script parts


def script_values(stdout: str) -> dict[str, str]:
    return dict(m.groups() for m in re.finditer(r"^(\w+)=(\S*)$", stdout, re.MULTILINE))


_SUMMARY_RE = re.compile(
    r"motor-monitor: stopped \(signal 15\): (\d+) frames, (\d+) estimated, (\d+) rejected, "
    r"(\d+) diagnosis frames sent")


def monitor_summary(stderr: str) -> dict[str, int] | None:
    m = _SUMMARY_RE.search(stderr)
    if m is None:
        return None
    return dict(zip(("frames", "estimated", "rejected", "sent"), map(int, m.groups()),
                    strict=True))


def read_events(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


SCRIPT_PRELUDE = r"""
set -u
cd "$OUT"
now() { date +%s.%N; }
mark() { echo "mark_$1=$(now)"; }
alive() { if kill -0 "$MON" 2>/dev/null; then echo 1; else echo 0; fi; }
wait_for() {  # FILE PATTERN SECONDS [FROM_LINE]: poll until FILE has PATTERN after FROM_LINE
  n=0
  while ! tail -n +"${4:-1}" "$1" 2>/dev/null | grep -q -- "$2"; do
    n=$((n + 1))
    [ "$n" -gt $(($3 * 10)) ] && return 1
    sleep 0.1
  done
}
inject() {  # KEY FRAME...: cansend each frame, in a window marked by mark_KEY_start/end
  key=$1; shift
  mark "${key}_start"
  ok=0
  for f in "$@"; do cansend vcan0 "$f" && ok=$((ok + 1)); done
  mark "${key}_end"
  echo "sent_${key}=$ok"
  echo "alive_${key}=$(alive)"
  sleep "$GAP"
}
ecu() {  # SEED LOG: a healthy node-0 ECU until stopped
  sim-ecu --interface socketcan --channel vcan0 --node 0 --scenario healthy --duration 0 \
      --seed "$1" 2> "$2" &
  ECU=$!
}
"""

SCRIPT_A = r"""
candump -L any,0:0,#FFFFFFFF > cap.log 2> candump.err &
DUMP=$!
motor-monitor -v run --interface socketcan --channel vcan0 --nodes 0 --rrd "$OUT/a.rrd" \
    --events "$OUT/ev.jsonl" 2> mon.err &
MON=$!
ecu 1 ecu1.err
# Wrong CLI on a real SocketCAN kernel, while the daemon starts: a channel that does not exist.
( motor-monitor run --interface socketcan --channel vcan9 > /dev/null 2> cli_mon_nochan.err
  echo "$?" > cli_mon_nochan.rc ) &
CLI1=$!
( sim-ecu --interface socketcan --channel vcan9 --node 0 --scenario healthy > /dev/null \
      2> cli_ecu_nochan.err
  echo "$?" > cli_ecu_nochan.rc ) &
CLI2=$!
if wait_for cap.log ' 180#' 200 && wait_for cap.log ' 110#' 200; then
  echo "ready=1"
else
  echo "ready=0"; kill $MON $ECU $DUMP; exit 3
fi
wait $CLI1 $CLI2
sleep 2
mark bad_start
__INJECT__
# interface down for 1 s and up again, the ECU running
mark down
ip link set down vcan0
sleep 1
ip link set up vcan0
mark up
echo "alive_linkdown=$(alive)"
sleep 2.5
# a silent ECU
mark ecu_stop
kill -TERM $ECU; wait $ECU; echo "ecu1_rc=$?"
mark ecu_stopped
sleep 1.5
# a replay: the ECU's last current frame again, same alive counter
LAST=$(grep ' vcan0 110#' cap.log | tail -n 1 | awk '{print $3}')
echo "replayed=$LAST"
inject replay $(for i in $(seq __REPLAYS__); do echo "$LAST"; done)
# the interface deleted and re-created under the running daemon; a new ECU
mark del
ip link del vcan0
sleep 1
ip link add dev vcan0 type vcan
ip link set up vcan0
mark add
echo "alive_linkdel=$(alive)"
N0=$(wc -l < cap.log)
ecu 3 ecu2.err
if wait_for cap.log ' 110#' 200 $((N0 + 1)); then echo "ecu2_up=1"; else echo "ecu2_up=0"; fi
mark ecu2_up
sleep 2.5
mark term
kill -TERM $MON; wait $MON; echo "mon_rc=$?"
mark term_done
kill -TERM $ECU; wait $ECU; echo "ecu2_rc=$?"
sleep 0.3
kill -INT $DUMP; wait $DUMP; echo "dump_rc=$?"
"""

SCRIPT_B = r"""
motor-monitor -v run --interface socketcan --channel vcan0 --nodes 0 --rrd "$OUT/b.rrd" \
    --events "$OUT/ev.jsonl" 2> mon.err &
MON=$!
ecu 2 ecu.err
if wait_for ev.jsonl '"state":"fault_free"' 200; then
  echo "ready=1"
else
  echo "ready=0"; kill $MON $ECU; exit 3
fi
( while kill -0 $MON 2>/dev/null; do
    echo "$(now) $(awk '/^VmRSS/ {print $2}' /proc/$MON/status 2>/dev/null)"
    sleep 0.5
  done ) > rss.txt 2> /dev/null &
sleep 2
echo "tx_before=$(cat /sys/class/net/vcan0/statistics/tx_packets)"
mark flood_start
cangen vcan0 -g 0 -I r -L r -D r -i 2> cangen1.err &
G1=$!
cangen vcan0 -g 0 -m -i 2> cangen2.err &
G2=$!
sleep __FLOOD__
kill -INT $G1 $G2; wait $G1 $G2
mark flood_end
echo "tx_after=$(cat /sys/class/net/vcan0/statistics/tx_packets)"
echo "alive_flood=$(alive)"
sleep 3
mark kill
kill -KILL $MON
mark killed
wait $MON; echo "mon_rc=$?"
kill -TERM $ECU; wait $ECU; echo "ecu_rc=$?"
"""


def script_a(kinds: Sequence[FrameKind]) -> str:
    lines = [f"inject {k.key} " + " ".join(f.cansend() for f in k.frames) for k in kinds]
    return (SCRIPT_PRELUDE + SCRIPT_A).replace("__INJECT__", "\n".join(lines)).replace(
        "__REPLAYS__", str(REPLAYS))


def script_b(flood_s: float = FLOOD_S) -> str:
    return (SCRIPT_PRELUDE + SCRIPT_B).replace("__FLOOD__", f"{flood_s:g}")


def _run(vcan: RunOnVcan, script: str, out: Path, timeout: float) -> tuple[VcanResult, float]:
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    res = vcan(script, env={"OUT": str(out), "GAP": f"{KIND_GAP_S:g}"}, timeout=timeout)
    wall = time.monotonic() - t0
    (out / "script.json").write_text(json.dumps({
        "returncode": res.returncode, "stdout": res.stdout, "stderr": res.stderr,
        "backend": res.backend, "duration": res.duration, "wall_s": wall}))
    return res, wall


def _load_result(out: Path) -> tuple[VcanResult, float]:
    """The outcome of a boot as `_run` saved it (to read a kept directory again)."""
    d = json.loads((out / "script.json").read_text())
    return VcanResult(d["returncode"], d["stdout"], d["stderr"], d["backend"],
                      d["duration"]), float(d["wall_s"])


def logs_tail(out: Path, chars: int = 3000) -> str:
    return "\n".join(f"--- {p.name} ---\n{p.read_text(errors='replace')[-chars:]}"
                     for p in sorted(out.glob("*.err")))


# ----------------------------------------------------------------------------- boot A


class _BootReadback:
    """What both boots' results offer: script marks, readiness, and the node's series."""

    values: dict[str, str]
    rrd: dict[str, tuple[Array, Array]]

    def mark(self, name: str) -> float:
        return float(self.values[f"mark_{name}"])

    @property
    def ok(self) -> bool:
        return self.values.get("ready") == "1"

    def gamma(self) -> tuple[Array, Array]:
        return series(self.rrd, f"/motor/{NODE}/gamma/estimate")

    def measured(self) -> tuple[Array, Array]:
        return series(self.rrd, f"/motor/{NODE}/current/measured")


@dataclass
class BootA(_BootReadback):
    """Everything boot A left behind, read back on the host."""

    out: Path
    result: VcanResult
    wall_s: float
    kinds: list[FrameKind]
    values: dict[str, str] = field(default_factory=dict)
    capture: list[Captured] = field(default_factory=list)
    rrd: dict[str, tuple[Array, Array]] = field(default_factory=dict)
    snaps: Snapshots = field(default_factory=lambda: Snapshots(np.zeros(0), {}))
    events: list[dict[str, Any]] = field(default_factory=list)
    mon_err: str = ""
    summary: dict[str, int] | None = None

    def has(self, name: str) -> bool:
        return f"mark_{name}" in self.values

    def bracket(self, start: float, end: float) -> tuple[int | None, int | None]:
        """Snapshots (last before `start`, first after `end` + 0.2 s: room for frames still
        queued in the daemon's socket at `end`)."""
        return self.snaps.last_before(start), self.snaps.first_after(end + 0.2)

    def injected(self, kind: FrameKind) -> list[Captured]:
        """Captured frames of `kind` inside its window."""
        if not self.has(f"{kind.key}_start"):
            return []
        lo, hi = self.mark(f"{kind.key}_start"), self.mark(f"{kind.key}_end")
        keys = {f.key for f in kind.frames}
        if kind.key == "replay":
            keys = {f.key for f in self.replay_frames()}
        return [c for c in self.capture if lo <= c.t <= hi and c.frame.key in keys]

    def replay_frames(self) -> list[Frame]:
        text = self.values.get("replayed", "")
        return [parse_frame(text)] if "#" in text else []

    def restart_repeats(self, mdb: MotorDatabase) -> int:
        """Streams (current, voltage) whose first frame from the new ECU carries the same alive
        counter as the old ECU's last: the daemon, which keeps the last counter over a
        silence, drops that genuine frame as repeated (a 1 in 16 chance per stream)."""
        if not (self.has("ecu_stopped") and self.has("add")):
            return 0
        stopped, add = self.mark("ecu_stopped"), self.mark("add")
        n = 0
        for kind in ("current", "voltage"):
            fid = mdb.frame_id(kind, NODE)
            old = [c for c in self.capture if c.frame.arbitration_id == fid and c.t <= stopped
                   and not c.frame.extended and not c.frame.remote and not c.frame.error]
            new = [c for c in self.capture if c.frame.arbitration_id == fid and c.t > add]
            counters = []
            for c in (old[-1:] + new[:1]):
                d = mdb.decode_can(c.frame.message(c.t))
                counters.append(d.counter if isinstance(d, Decoded) else None)
            n += len(counters) == 2 and counters[0] is not None and counters[0] == counters[1]
        return n

    def genuine_current(self, mdb: MotorDatabase) -> list[tuple[float, float]]:
        """(t, amps) of the ECUs' own current frames of node 0 in the capture."""
        bad: set[tuple[int, bytes, bool, bool, bool, bool]] = set()
        for k in self.kinds:
            bad.update(f.key for f in k.frames)
        lo = self.mark("replay_start") if self.has("replay_start") else math.inf
        hi = self.mark("replay_end") if self.has("replay_end") else -math.inf
        cur_id = mdb.frame_id("current", NODE)
        out: list[tuple[float, float]] = []
        for c in self.capture:
            f = c.frame
            if f.arbitration_id != cur_id or f.key in bad or lo <= c.t <= hi:
                continue
            d = mdb.decode_can(f.message(c.t))
            if isinstance(d, Decoded):
                out.append((c.t, d.value))
        return out

    def diagnosis_frames(self, mdb: MotorDatabase) -> list[tuple[float, int, float]]:
        """(t, HealthState, GammaEstimate) of the daemon's MonitorDiagnosis_N0 frames."""
        fake = {f.key for k in self.kinds if k.key == "fake_diagnosis" for f in k.frames}
        out: list[tuple[float, int, float]] = []
        for c in self.capture:
            if c.frame.key in fake or c.frame.arbitration_id != mdb.frame_id("diagnosis", NODE):
                continue
            d = mdb.decode_can(c.frame.message(c.t))
            if isinstance(d, Decoded) and d.kind == "diagnosis":
                out.append((c.t, int(d.raw["HealthState"]), d.value))
        return out

    def classify_rows(self, mdb: MotorDatabase) -> dict[str, int]:
        """Each recorded measured-current row matched to the captured frame it came from:
        {'genuine': n, '<kind>': n (an injected frame reached the estimator!), 'unmatched': n,
        'value_mismatch': n}."""
        t_rows, v_rows = self.measured()
        labelled: list[tuple[float, str, float]] = [(t, "genuine", a)
                                                    for t, a in self.genuine_current(mdb)]
        for k in [*self.kinds, FrameKind("replay", "replay", (), {})]:
            labelled.extend((c.t, k.key, math.nan) for c in self.injected(k))
        labelled.sort()
        ts = np.array([x[0] for x in labelled])
        out: dict[str, int] = {"genuine": 0, "unmatched": 0, "value_mismatch": 0}
        for t, v in zip(t_rows, v_rows, strict=True):
            i = int(np.searchsorted(ts, t - TIME_TOL_S))
            hits = [labelled[j] for j in range(i, len(ts)) if ts[j] <= t + TIME_TOL_S]
            if not hits:
                out["unmatched"] += 1
                continue
            genuine = [h for h in hits if h[1] == "genuine"]
            if genuine:
                out["genuine"] += 1
                if not any(abs(h[2] - v) < 0.006 for h in genuine):
                    out["value_mismatch"] += 1
            else:
                out[hits[0][1]] = out.get(hits[0][1], 0) + 1
        return out

    def rows_between(self, i: int | None, j: int | None) -> int:
        """Recorded gamma rows with snapshot i's time < t <= snapshot j's time."""
        t, _ = self.gamma()
        lo = -math.inf if i is None else self.snaps.t[i]
        hi = math.inf if j is None else self.snaps.t[j]
        return int(np.count_nonzero((t > lo) & (t <= hi)))

    def nan_between(self, lo: float, hi: float) -> int:
        t, g = self.gamma()
        return int(np.count_nonzero(np.isnan(g[(t >= lo) & (t <= hi)])))


def run_boot_a(vcan: RunOnVcan, mdb: MotorDatabase, out: Path, timeout: float = 420.0) -> BootA:
    _run(vcan, script_a(frame_kinds(mdb)), out, timeout)
    return load_boot_a(mdb, out)


def load_boot_a(mdb: MotorDatabase, out: Path) -> BootA:
    res, wall = _load_result(out)
    boot = BootA(out=out, result=res, wall_s=wall, kinds=frame_kinds(mdb))
    boot.values = script_values(res.stdout)
    boot.capture = read_candump(out / "cap.log")
    if (out / "a.rrd").exists():
        boot.rrd = read_rrd(out / "a.rrd")
        boot.snaps = Snapshots.from_rrd(boot.rrd)
    boot.events = read_events(out / "ev.jsonl")
    boot.mon_err = (out / "mon.err").read_text(errors="replace") if (
        out / "mon.err").exists() else ""
    boot.summary = monitor_summary(boot.mon_err)
    return boot


# ----------------------------------------------------------------------------- boot B


@dataclass
class BootB(_BootReadback):
    out: Path
    result: VcanResult
    wall_s: float
    values: dict[str, str] = field(default_factory=dict)
    rrd: dict[str, tuple[Array, Array]] = field(default_factory=dict)
    snaps: Snapshots = field(default_factory=lambda: Snapshots(np.zeros(0), {}))
    events: list[dict[str, Any]] = field(default_factory=list)
    rss: list[tuple[float, float]] = field(default_factory=list)  # (t, MB)
    mon_err: str = ""


    def rss_at(self, t: float) -> float:
        """RSS (MB) of the sample nearest to guest time t."""
        if not self.rss:
            return math.nan
        return min(self.rss, key=lambda x: abs(x[0] - t))[1]

    def kill_margin(self) -> float:
        """Kill time minus the time of the last measured sample on disk (s)."""
        t, _ = self.measured()
        return self.mark("kill") - float(t[-1]) if len(t) else math.inf

    def bus_frames(self) -> int:
        try:
            return int(self.values["tx_after"]) - int(self.values["tx_before"])
        except (KeyError, ValueError):
            return 0


def run_boot_b(vcan: RunOnVcan, out: Path, flood_s: float = FLOOD_S,
               timeout: float = 300.0) -> BootB:
    _run(vcan, script_b(flood_s), out, timeout)
    return load_boot_b(out)


def load_boot_b(out: Path) -> BootB:
    res, wall = _load_result(out)
    boot = BootB(out=out, result=res, wall_s=wall)
    boot.values = script_values(res.stdout)
    if (out / "b.rrd").exists():
        boot.rrd = read_rrd(out / "b.rrd")
        boot.snaps = Snapshots.from_rrd(boot.rrd)
    boot.events = read_events(out / "ev.jsonl")
    boot.mon_err = (out / "mon.err").read_text(errors="replace") if (
        out / "mon.err").exists() else ""
    rss_path = out / "rss.txt"
    if rss_path.exists():
        for line in rss_path.read_text().splitlines():
            parts = line.split()
            if len(parts) == 2 and parts[1].isdigit():
                boot.rss.append((float(parts[0]), int(parts[1]) / 1024.0))
    return boot


# ----------------------------------------------------------------------------- CLI / files


@dataclass(frozen=True)
class CliCase:
    key: str
    title: str
    argv: tuple[str, ...]  # program name first: "motor-monitor" or "sim-ecu"
    expect: str  # a substring of the one error line


@dataclass(frozen=True)
class CliOutcome:
    case: CliCase
    returncode: int
    lines: tuple[str, ...]

    @property
    def traceback(self) -> bool:
        return any("Traceback" in ln for ln in self.lines)

    @property
    def clean(self) -> bool:
        """Exit status 2, one line naming the program, the expected text, no traceback."""
        prog = self.case.argv[0]
        return (self.returncode == 2 and len(self.lines) == 1 and not self.traceback
                and self.lines[0].startswith(f"{prog}") and ": error: " in self.lines[0]
                and self.case.expect in self.lines[0])


def write_bad_files(d: Path) -> dict[str, str]:
    """Malformed DBC, threshold and scenario files; returns name -> path."""
    d.mkdir(parents=True, exist_ok=True)
    dbc = (PROJECT_ROOT / "dbc" / "motor.dbc").read_text()
    files = {
        "garbage.dbc": 'VERSION ""\nBO_ 1 broken\n',
        "empty.dbc": "",
        "binary.dbc": "\x00\x01\x02\xff" * 10,
        "foreign.dbc": ('VERSION ""\n\nBU_: A\nBO_ 100 Foo: 8 A\n'
                        ' SG_ X : 0|8@1+ (1,0) [0|255] "" A\n'),
        "truncated.dbc": dbc[: len(dbc) // 3],
        "wrong_e2e.dbc": dbc.replace('BA_ "E2EDataID" BO_ 272 16;', 'BA_ "E2EDataID" BO_ 272 17;'),
        "no_current_n5.dbc": re.sub(r"BO_ 277 MotorCurrent_N5: 8 MotorECU\n(?: SG_[^\n]*\n)*",
                                    "", dbc),
        "bad.toml": "f1 = [unclosed\n",
        "swapped.toml": 'quantity = "gamma"\nf1 = 0.9\nf2 = 0.1\n',
        "nan.toml": 'quantity = "gamma"\nf1 = nan\nf2 = 0.8\n',
        "string.toml": 'quantity = "gamma"\nf1 = "low"\nf2 = 0.8\n',
        "no_f2.toml": 'quantity = "gamma"\nf1 = 0.1\n',
        "other_quantity.toml": 'quantity = "fault_volts"\nf1 = 0.1\nf2 = 0.8\n',
        "gamma2.toml": "duration = 5\n[[fault]]\nstart = 1\nend = 3\ngamma = 2\n",
        "backwards.toml": "duration = 5\n[[fault]]\nstart = 3\nend = 1\ngamma = 0.5\n",
        "negdur.toml": "duration = -5\n",
        "nangamma.toml": "duration = 5\n[[fault]]\nstart = 1\nend = 3\ngamma = nan\n",
        "badmotor.toml": "duration = 5\n[motor]\nJ = -1\n",
        "notoml.toml": "duration = = 5\n",
    }
    paths: dict[str, str] = {}
    for name, text in files.items():
        p = d / name
        p.write_text(text, errors="surrogateescape")
        paths[name] = str(p)
    paths["missing"] = str(d / "missing.file")
    return paths


def cli_cases(d: Path) -> list[CliCase]:
    """Malformed files and wrong arguments, each must end in one clear line, exit status 2."""
    f = write_bad_files(d)
    run = ("motor-monitor", "run", "--interface", "virtual", "--channel", "bad-input")
    ecu = ("sim-ecu", "--interface", "virtual", "--channel", "bad-input", "--node", "0",
           "--duration", "0.1")
    cases = [
        CliCase("dbc_garbage", "DBC: a broken message line", (*run, "--dbc", f["garbage.dbc"]),
                "garbage.dbc"),
        CliCase("dbc_empty", "DBC: empty file", (*run, "--dbc", f["empty.dbc"]), "empty.dbc"),
        CliCase("dbc_binary", "DBC: binary file", (*run, "--dbc", f["binary.dbc"]),
                "binary.dbc"),
        CliCase("dbc_foreign", "DBC: another bus's DBC", (*run, "--dbc", f["foreign.dbc"]),
                "unexpected message"),
        CliCase("dbc_truncated", "DBC: truncated", (*run, "--dbc", f["truncated.dbc"]),
                "truncated.dbc"),
        CliCase("dbc_e2e", "DBC: wrong E2EDataID", (*run, "--dbc", f["wrong_e2e.dbc"]),
                "E2EDataID"),
        CliCase("dbc_missing_msg", "DBC: a message missing",
                (*run, "--dbc", f["no_current_n5.dbc"]), "missing message MotorCurrent_N5"),
        CliCase("dbc_missing", "DBC: no such file", (*run, "--dbc", f["missing"]),
                "not found"),
        CliCase("thr_toml", "thresholds: invalid TOML", (*run, "--thresholds", f["bad.toml"]),
                "not valid TOML"),
        CliCase("thr_swapped", "thresholds: f1 >= f2",
                (*run, "--thresholds", f["swapped.toml"]), "must be less than"),
        CliCase("thr_nan", "thresholds: NaN", (*run, "--thresholds", f["nan.toml"]), "finite"),
        CliCase("thr_string", "thresholds: not a number",
                (*run, "--thresholds", f["string.toml"]), "must be a number"),
        CliCase("thr_nokey", "thresholds: key missing", (*run, "--thresholds", f["no_f2.toml"]),
                "missing key"),
        CliCase("thr_quantity", "thresholds: other quantity",
                (*run, "--thresholds", f["other_quantity.toml"]), "quantity"),
        CliCase("thr_missing", "thresholds: no such file", (*run, "--thresholds", f["missing"]),
                "not found"),
        CliCase("scen_gamma", "scenario: gamma > 1 (sim-ecu)",
                (*ecu, "--scenario", f["gamma2.toml"]), "[0, 1]"),
        CliCase("scen_backwards", "scenario: fault ends before it starts (sim-ecu)",
                (*ecu, "--scenario", f["backwards.toml"]), "start < end"),
        CliCase("scen_negdur", "scenario: negative duration (sim-ecu)",
                (*ecu, "--scenario", f["negdur.toml"]), "duration"),
        CliCase("scen_nan", "scenario: NaN gamma (sim-ecu)",
                (*ecu, "--scenario", f["nangamma.toml"]), "finite"),
        CliCase("scen_motor", "scenario: negative motor inertia (sim-ecu)",
                (*ecu, "--scenario", f["badmotor.toml"]), "positive"),
        CliCase("scen_toml", "scenario: invalid TOML (sim-ecu)",
                (*ecu, "--scenario", f["notoml.toml"]), "notoml"),
        CliCase("scen_unknown", "scenario: unknown name (sim-ecu)", (*ecu, "--scenario", "nope"),
                "unknown scenario"),
        CliCase("scen_demo", "scenario: gamma > 1 (motor-monitor demo)",
                ("motor-monitor", "demo", "--scenario", f["gamma2.toml"]), "[0, 1]"),
        CliCase("arg_nodes16", "CLI: --nodes 16", ("motor-monitor", "run", "--nodes", "16"),
                "0..15"),
        CliCase("arg_nodes_text", "CLI: --nodes a,b", ("motor-monitor", "run", "--nodes", "a,b"),
                "nodes must be"),
        CliCase("arg_rate_text", "CLI: --rate fast", (*run, "--rate", "fast"), "invalid float"),
        CliCase("arg_rate_zero", "CLI: --rate 0", (*run, "--rate", "0"), "rate"),
        CliCase("arg_rate_neg", "CLI: --rate -5", (*run, "--rate", "-5"), "rate"),
        CliCase("arg_rate_nan", "CLI: --rate nan", (*run, "--rate", "nan"), "rate"),
        CliCase("arg_iface", "CLI: unknown interface",
                ("motor-monitor", "run", "--interface", "nosuchbus", "--channel", "x"),
                "cannot open CAN interface"),
        CliCase("arg_rrd_dir", "CLI: --rrd into a missing directory",
                (*run, "--rrd", str(d / "nodir" / "x.rrd")), "does not exist"),
        CliCase("arg_events_dir", "CLI: --events into a missing directory",
                (*run, "--events", str(d / "nodir" / "ev.jsonl")), "nodir"),
        CliCase("arg_command", "CLI: unknown command", ("motor-monitor", "frobnicate"),
                "invalid choice"),
        CliCase("arg_ecu_node", "CLI: sim-ecu --node 16",
                (*ecu, "--scenario", "healthy", "--node", "16"), "--node"),
        CliCase("arg_ecu_rate", "CLI: sim-ecu --rate 0",
                (*ecu, "--scenario", "healthy", "--rate", "0"), "--rate"),
        CliCase("arg_ecu_duration", "CLI: sim-ecu --duration -1",
                ("sim-ecu", "--interface", "virtual", "--channel", "x", "--node", "0",
                 "--scenario", "healthy", "--duration", "-1"), "--duration"),
    ]
    return cases


def run_cli_case(case: CliCase, cwd: Path, timeout: float = 120.0) -> CliOutcome:
    exe = str(BIN / case.argv[0])
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAN_")}
    try:
        proc = subprocess.run([exe, *case.argv[1:]], capture_output=True, text=True,
                              timeout=timeout, cwd=cwd, env=env, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired as exc:
        err = exc.stderr.decode(errors="replace") if isinstance(exc.stderr, bytes) else ""
        lines = [ln for ln in err.splitlines() if ln.strip()]
        lines.append(f"(timed out after {timeout:.0f} s: the program ran instead of refusing)")
        return CliOutcome(case, -9, tuple(lines))
    lines = tuple(ln for ln in proc.stderr.splitlines() if ln.strip())
    return CliOutcome(case, proc.returncode, lines)


def run_cli_cases(cases: Iterable[CliCase], cwd: Path, workers: int = 2,
                  timeout: float = 60.0) -> list[CliOutcome]:
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(lambda c: run_cli_case(c, cwd, timeout), cases))


def guest_cli_outcomes(out: Path) -> list[CliOutcome]:
    """The wrong-channel runs of boot A, on a kernel with SocketCAN."""
    cases = [
        CliCase("guest_mon_nochan", "CLI: motor-monitor on a CAN channel that does not exist "
                "(SocketCAN kernel)", ("motor-monitor",), "cannot open CAN interface"),
        CliCase("guest_ecu_nochan", "CLI: sim-ecu on a CAN channel that does not exist "
                "(SocketCAN kernel)", ("sim-ecu",), "cannot open CAN"),
    ]
    res: list[CliOutcome] = []
    for case, stem in zip(cases, ("cli_mon_nochan", "cli_ecu_nochan"), strict=True):
        rc_path, err_path = out / f"{stem}.rc", out / f"{stem}.err"
        rc = int(rc_path.read_text().strip()) if rc_path.exists() else -1
        err = err_path.read_text(errors="replace") if err_path.exists() else ""
        res.append(CliOutcome(case, rc, tuple(ln for ln in err.splitlines() if ln.strip())))
    return res
