"""The twin of a CANopen rig: a CiA 402 drive on the bus, and the host that drives it.

`Cia402ECU` is `sim_ecu.rig_ecu.RigECU` for a rig with ``[bus] protocol = "canopen"``. With
``host="self"`` (the default) the twin is its own host too; each sample of the rig's model
(the scenario's command on the inputs, its gamma on the faulty actuators) is one SYNC cycle,
in the order a CiA 402 drive sees it:

* at start, the drive's boot-up (0x700 + node, state 0) and the host's NMT start
  (COB-ID 0: ``01 <node>``); then the drive's heartbeat (0x700 + node, state 5,
  operational) every producer heartbeat time (0x1017 of the file; 100 ms where it is 0);
* the host's RPDOs (the command objects, the controlword: enable operation, 0x000F; fault
  reset, 0x0080, while the drive is in Fault), then the host's SYNC (0x80, no data);
* the drive's TPDOs as their mapping says: a synchronous TPDO (transmission type n in
  1..240) on every n-th SYNC, type 0 on every SYNC, an event-driven one (254, 255) each
  time its event timer runs out (every SYNC without a timer); types 252 and 253 (on
  request) are never sent. The model's outputs go in the objects the rig names, the
  statusword (0x6041) follows the drive's state (Operation enabled, 0x0027; Fault,
  0x0008), the mode of operation display (0x6061) is cyclic synchronous velocity (9),
  everything else 0;
* on an outage (the scenario's gamma at 1 on an actuator) the drive goes to Fault and
  sends an EMCY (0x80 + node: error code 0x5000, device hardware, error register 0x01,
  generic error); when it ends the drive sends the EMCY error reset (code 0) and is back
  in Operation enabled.

With ``host="external"`` (``sim-ecu --host external``) the twin is the drive only, for the
user's PLC or CANopen master on the bus (`Cia402ECU.run` only: it needs the host's frames):

* it sends its boot-up and waits in pre-operational; its heartbeat (0x700 + node: its NMT
  state, 127 pre-operational, 5 operational, 4 stopped) goes out every producer heartbeat
  time from then on. NMT (COB-ID 0) for its node or all nodes (node 0) moves it: start
  (1), stop (2), enter pre-operational (128), reset node (129: boot-up again, the CiA 402
  state, controlword and targets cleared) and reset communication (130: boot-up again);
* only while operational it reads the host's RPDOs (decoded with the rig's codec: the
  model's inputs, in the model's units, and the controlword 0x6040), a synchronous RPDO
  (type 0..240) at the next SYNC, any other on arrival, and answers each SYNC (0x80) with
  one sample of the model and its synchronous TPDOs (type n in 1..240: every n-th SYNC;
  0: every SYNC); an event-driven TPDO (254, 255) goes out every event timer, or when its
  data changes where it has none. Without SYNC from the bus no synchronous TPDO is sent;
* the controlword drives the CiA 402 state machine (`canopen.profiles.p402.State402`'s
  states and statusword values): shutdown (``0xxx x110``), switch on (``0xxx 0111``),
  enable operation (``0xxx 1111``, also from Ready to switch on), disable voltage
  (``0xxx xx0x``), quick stop (``0xxx x01x``) and fault reset (bit 7 rising, once the
  outage is over). Only in Operation enabled the drive applies the host's targets to the
  model; in any other state its input is 0 (the power stage is off);
* the scenario gives the fault only, on the model's time: SYNC n is at n / rate. An outage
  puts the drive in Fault with the EMCY above; its end sends the EMCY error reset, and the
  drive stays in Fault until the host's fault reset, as a real drive does.

Every PDO is encoded from the rig's bus description (`monitor.bus.canopen`), the frames the
monitor reads through the codec, so the twin and the monitor read the same bits.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Iterator, Mapping
from typing import Final, Literal, cast

import can
import numpy as np
from canopen.emcy import EMCY_STRUCT
from canopen.nmt import NMT_COMMANDS, NMT_STATES
from canopen.profiles.p402 import State402

from monitor.bus.canopen import CanopenNode, Pdo, canopen_database, canopen_node
from monitor.bus.codec import Decoded, RejectReason
from monitor.bus.errors import CodecError
from monitor.bus.rigcodec import RigCodec
from monitor.errors import one_line
from monitor.rig import Rig
from monitor.runtime.canbus import send_frame
from sim_ecu.ecu import DEFAULT_MAX_CATCH_UP, ECUError, ECUStats
from sim_ecu.plant import steady_state
from sim_ecu.rig_ecu import RigECU, _RigSimulation
from sim_ecu.scenario import Scenario

__all__ = ["EMCY_OUTAGE", "HOSTS", "STATUS_FAULT", "STATUS_OPERATION_ENABLED", "Cia402ECU",
           "Host"]

log = logging.getLogger(__name__)

Host = Literal["self", "external"]
HOSTS: Final[tuple[Host, ...]] = ("self", "external")
"""Who the CANopen master is: the twin itself, or a PLC or master on the bus."""

SYNC_ID = 0x80
NMT_ID = 0x000
STATUS_OPERATION_ENABLED = 0x0027
STATUS_FAULT = 0x0008
CONTROL_ENABLE_OPERATION = 0x000F
CONTROL_FAULT_RESET = 0x0080
MODE_CSV = 9  # cyclic synchronous velocity
EMCY_OUTAGE = 0x5000
"""The EMCY error code of an outage: device hardware (CiA 301), the output stage lost."""
DEFAULT_HEARTBEAT_MS = 100
"""The twin's heartbeat where the file's producer heartbeat time (0x1017) is 0."""
_NMT_OPERATIONAL = 5
_NMT_STATE = {name: code for code, name in NMT_STATES.items()}
_NMT_PRE_OPERATIONAL = _NMT_STATE["PRE-OPERATIONAL"]
_NMT_STOPPED = _NMT_STATE["STOPPED"]
_NMT_MOVES = {NMT_COMMANDS["OPERATIONAL"]: _NMT_OPERATIONAL,
              NMT_COMMANDS["STOPPED"]: _NMT_STOPPED,
              NMT_COMMANDS["PRE-OPERATIONAL"]: _NMT_PRE_OPERATIONAL}
_NMT_RESET_NODE = NMT_COMMANDS["RESET"]
_NMT_RESET_COMMUNICATION = NMT_COMMANDS["RESET COMMUNICATION"]
_POLL_S = 0.05
"""The longest the hosted drive blocks on the bus before it looks at its stop event."""
# the CiA 402 states (the names of `State402`)
SOD, RTSO, SO = "SWITCH ON DISABLED", "READY TO SWITCH ON", "SWITCHED ON"
OE, QSA, FAULT = "OPERATION ENABLED", "QUICK STOP ACTIVE", "FAULT"
_CW_FAULT_RESET = State402.CW_SWITCH_ON_DISABLED  # bit 7


def next_state(state: str, control: int, previous: int, outage: bool) -> str:
    """The CiA 402 state after controlword `control` (the one before: `previous`) in
    `state`: the device control commands of CiA 402 (transitions 2 to 12, 15 and 16; 3 and
    4 in one from Ready to switch on). Fault is left by a fault reset (bit 7 rising) only
    once the outage is over."""
    if state == FAULT:
        rising = bool(control & _CW_FAULT_RESET) and not previous & _CW_FAULT_RESET
        return SOD if rising and not outage else FAULT
    if control & _CW_FAULT_RESET:
        return state
    if not control & 0x02:  # disable voltage
        return SOD
    if not control & 0x04:  # quick stop
        return QSA if state in (OE, QSA) else SOD
    if control & 0x07 == State402.CW_SHUTDOWN:
        return RTSO if state in (SOD, SO, OE) else state
    if control & 0x0F == State402.CW_SWITCH_ON:
        return SO if state in (RTSO, OE) else state
    if control & 0x0F == State402.CW_OPERATION_ENABLED:
        return OE if state in (RTSO, SO, QSA) else state
    return state


def statusword(state: str) -> int:
    """The statusword of a CiA 402 state (`State402.SW_MASK`'s value bits)."""
    return State402.SW_MASK[state][1]


class Cia402ECU(RigECU):
    """One CiA 402 drive of a CANopen rig, simulated with its host: `frames` offline, `run`
    in real time on `bus`."""

    def __init__(self, bus: can.BusABC | None, codec: RigCodec, rig: Rig, node: int,
                 scenario: Scenario, *, seed: int = 0,
                 max_catch_up: int = DEFAULT_MAX_CATCH_UP, host: Host = "self") -> None:
        super().__init__(bus, codec, rig, node, scenario, seed=seed, max_catch_up=max_catch_up)
        if host not in HOSTS:
            raise ECUError(f"host must be one of {', '.join(HOSTS)}, got {host!r}")
        self.host: Host = host
        self.received: dict[str, int] = {}
        """What the drive took from the bus (``host="external"``): frames per kind (nmt,
        sync, rpdo), ``rejected`` RPDOs the codec refused and ``ignored`` frames (not
        for this drive, or not in a state that reads them)."""
        if rig.canopen is None:
            raise ECUError("the CiA 402 twin needs a CANopen rig ([bus] protocol = \"canopen\")")
        try:
            self.drive: CanopenNode = canopen_node(rig.canopen, node)
            db = canopen_database(rig.canopen)
        except CodecError as exc:
            raise ECUError(one_line(exc)) from None
        self.dbc = {m.name: m for m in db.messages}
        self.heartbeat_s = (self.drive.heartbeat_ms or DEFAULT_HEARTBEAT_MS) / 1000.0
        pdos = self.drive.pdos
        self.kinds = ("nmt", "sync", "heartbeat", "emcy", *(p.name for p in pdos))
        self.kind_of = {NMT_ID: "nmt", SYNC_ID: "sync", 0x700 + node: "heartbeat",
                        0x80 + node: "emcy", **{p.cob_id: p.name for p in pdos}}
        self.stats = self._new_stats()

    def _simulation(self, stats: ECUStats) -> _RigSimulation:
        return _Cia402Simulation(self, stats)

    def frames(self, duration: float | None = None, start_time: float = 0.0
               ) -> Iterator[can.Message]:
        """All frames of a fresh run with the twin as its own host (``host="self"``)."""
        if self.host == "external":
            raise ECUError("an externally hosted drive answers its host's frames: it runs on "
                           "a bus only (run)")
        return super().frames(duration, start_time)

    def run(self, duration: float | None = None, stop: threading.Event | None = None
            ) -> ECUStats:
        """Run in real time on the bus until done or `stop` is set. With ``host="external"``
        `duration` is the model's time, SYNC cycles answered / rate (None: the scenario's;
        inf: until stopped)."""
        if self.host == "self":
            return super().run(duration, stop)
        if self.bus is None:
            raise ECUError("run() needs a bus")
        d = self.scenario.duration if duration is None else duration
        self.stats = stats = self._new_stats()
        self.received = dict.fromkeys(("nmt", "sync", "rpdo", "rejected", "ignored"), 0)
        drive = _HostedDrive(self, stats)
        try:
            return drive.serve(self.bus, None if math.isinf(d) else self.samples_for(d),
                               stop if stop is not None else threading.Event())
        finally:
            log.info("node %d: received %s", self.node,
                     " ".join(f"{k}={v}" for k, v in self.received.items()))


class _Cia402Simulation(_RigSimulation):
    """One pass through the scenario: the plant, the drive's state, its timers."""

    ecu: Cia402ECU

    def __init__(self, ecu: Cia402ECU, stats: ECUStats) -> None:
        super().__init__(ecu, stats)
        self.fault = False
        self.next_heartbeat = 0.0
        self.next_event: dict[str, float] = {}

    def _due(self, pdo: Pdo, k: int, t: float) -> bool:
        """Whether TPDO `pdo` goes out in SYNC cycle k (at time t)."""
        trans = pdo.transmission if pdo.transmission is not None else 255
        if 1 <= trans <= 240:
            return k % trans == 0
        if trans == 0:
            return True
        if trans in (252, 253):
            return False
        timer = (pdo.event_timer_ms or 0) / 1000.0
        if timer <= 0:
            return True
        if t + 1e-9 >= self.next_event.get(pdo.name, 0.0):
            self.next_event[pdo.name] = self.next_event.get(pdo.name, 0.0) + timer
            return True
        return False

    def _values(self, pdo: Pdo, u: np.ndarray, y: np.ndarray) -> dict[str, float]:
        """The PDO's objects: the model's inputs and outputs (in the bus's units), the
        statusword, controlword and mode of operation, else 0."""
        ecu = self.ecu
        spec = ecu.codec.specs.get(pdo.name)
        model: dict[str, float] = {}
        if spec is not None:
            model = {s: float(u[i]) / f for i, s, f in spec.inputs}
            model.update({s: float(v) / f for (s, f), v in zip(spec.outputs, y, strict=False)})
        status, control = self._words()
        fixed = {0x6041: status, 0x6040: control, 0x6061: MODE_CSV, 0x6060: MODE_CSV}
        return {o.name: model.get(o.name, float(fixed.get(o.index, 0))) for o in pdo.objects}

    def _words(self) -> tuple[int, int]:
        """The statusword and the controlword the PDOs carry."""
        if self.fault:
            return STATUS_FAULT, CONTROL_FAULT_RESET
        return STATUS_OPERATION_ENABLED, CONTROL_ENABLE_OPERATION

    def _emcy(self, outage: bool, ts: float) -> can.Message:
        """The EMCY of an outage's start (`outage`) or end (the error reset)."""
        code, register = (EMCY_OUTAGE, 0x01) if outage else (0, 0)
        return can.Message(timestamp=ts, arbitration_id=0x80 + self.ecu.node,
                           is_extended_id=False, data=EMCY_STRUCT.pack(code, register, b""))

    def _pdo(self, pdo: Pdo, u: np.ndarray, y: np.ndarray, ts: float) -> can.Message:
        message = self.ecu.dbc[f"{pdo.name}_N{self.ecu.node}"]
        try:
            data = message.encode(self._values(pdo, u, y), scaling=True, padding=False,
                                  strict=True)
        except Exception as exc:  # cantools: a value outside its object's range
            raise CodecError(f"{pdo.name}: {one_line(exc)}") from None
        return can.Message(timestamp=ts, arbitration_id=pdo.cob_id, is_extended_id=False,
                           data=data)

    def step(self, emit: bool, time_base: float) -> list[can.Message]:
        ecu, plant = self.ecu, self.plant
        k, t, u, gamma, y = self.sample()
        ts = time_base + t
        node = ecu.node
        msgs: list[can.Message] = []
        if k == 0:
            msgs.append(can.Message(timestamp=ts, arbitration_id=0x700 + node,
                                    is_extended_id=False, data=b"\x00"))  # boot-up
            msgs.append(can.Message(timestamp=ts, arbitration_id=NMT_ID, is_extended_id=False,
                                    data=bytes((1, node))))  # the host: start remote node
        if t + 1e-9 >= self.next_heartbeat:
            self.next_heartbeat += ecu.heartbeat_s
            msgs.append(can.Message(timestamp=ts, arbitration_id=0x700 + node,
                                    is_extended_id=False, data=bytes((_NMT_OPERATIONAL,))))
        outage = bool(np.any(gamma >= 1.0))
        if outage != self.fault:
            self.fault = outage
            msgs.append(self._emcy(outage, ts))
        rx = [p for p in ecu.drive.pdos if not p.transmit]
        tx = [p for p in ecu.drive.pdos if p.transmit and self._due(p, k, t)]
        msgs += [self._pdo(p, u, y, ts) for p in rx]
        msgs.append(can.Message(timestamp=ts, arbitration_id=SYNC_ID, is_extended_id=False,
                                data=b""))
        msgs += [self._pdo(p, u, y, ts) for p in tx]
        plant.advance(u, gamma)
        self.k += 1
        self.stats.samples += 1
        if not emit:
            return []
        for m in msgs:
            self.stats.produced[ecu.kind_of[m.arbitration_id]] += 1
        return msgs


_Received = tuple[str, tuple[tuple[int, float], ...], Mapping[str, float]]
"""An RPDO read: its name, the model inputs it carries (index, value) and its objects."""


class _HostedDrive(_Cia402Simulation):
    """The drive alone on a bus with its host (``host="external"``): its NMT and CiA 402
    states, the host's latest targets and controlword, the plant stepped by each SYNC."""

    def __init__(self, ecu: Cia402ECU, stats: ECUStats) -> None:
        super().__init__(ecu, stats)
        zero = np.zeros(ecu.m)
        self.plant.x = steady_state(self.plant, zero)  # at rest: nothing drives it yet
        self.target = zero.copy()
        self.y = self.plant.output(zero, zero)  # what event-driven TPDOs carry before a SYNC
        self.nmt = _NMT_PRE_OPERATIONAL
        self.state = SOD
        self.control = 0
        self.pending: dict[int, _Received] = {}  # synchronous RPDOs, applied at the next SYNC
        rx = [p for p in ecu.drive.pdos if not p.transmit]
        self.rx = {p.cob_id: p for p in rx}
        self.control_object = {p.name: o.name for p in rx for o in p.objects
                               if o.index == 0x6040 and o.subindex == 0}
        self.tx_sync = [p for p in ecu.drive.pdos if p.transmit and p.transmission is not None
                        and 0 <= p.transmission <= 240]
        self.tx_event = [p for p in ecu.drive.pdos if p.transmit and p.transmission in
                         (None, 254, 255)]
        self.event_due: dict[str, float] = {}
        self.event_sent: dict[str, bytes] = {}
        self.rejecting = 0  # consecutive RPDOs the codec refused (the current burst)

    def _words(self) -> tuple[int, int]:
        return statusword(self.state), self.control

    def _frame(self, cob_id: int, data: bytes) -> can.Message:
        return can.Message(timestamp=time.time(), arbitration_id=cob_id, is_extended_id=False,
                           data=data)

    def _reset(self, node: bool) -> list[can.Message]:
        """Reset node (`node`) or communication: boot-up, pre-operational."""
        self.nmt = _NMT_PRE_OPERATIONAL
        self.pending.clear()
        if node:
            self.state, self.control = (FAULT if self.fault else SOD), 0
            self.target[:] = 0.0
        return [self._frame(0x700 + self.ecu.node, b"\x00")]

    def on_nmt(self, data: bytes) -> list[can.Message]:
        ecu = self.ecu
        if len(data) != 2 or data[1] not in (0, ecu.node):
            ecu.received["ignored"] += 1
            return []
        command = data[0]
        ecu.received["nmt"] += 1
        if command in (_NMT_RESET_NODE, _NMT_RESET_COMMUNICATION):
            return self._reset(command == _NMT_RESET_NODE)
        if command in _NMT_MOVES:
            self.nmt = _NMT_MOVES[command]
            if self.nmt != _NMT_OPERATIONAL:
                self.pending.clear()
        else:
            log.warning("node %d: NMT command %d not supported, ignored", ecu.node, command)
        return []

    def _control(self, value: int) -> None:
        self.state = next_state(self.state, value, self.control, self.fault)
        self.control = value

    def _apply(self, got: _Received) -> None:
        """The targets and the controlword of one of the host's RPDOs."""
        name, inputs, raw = got
        for i, v in inputs:
            self.target[i] = v
        control = self.control_object.get(name)
        if control is not None and control in raw:
            self._control(int(raw[control]))

    def _read(self, msg: can.Message, pdo: Pdo) -> _Received | str:
        """An RPDO's model inputs (the codec's, for the rig's input messages) and objects
        (the bus description's, for an RPDO only the CiA 402 state machine reads), or why
        it cannot be read."""
        ecu = self.ecu
        data = bytes(msg.data)
        got = ecu.codec.decode(msg.arbitration_id, data, msg.is_extended_id,
                               msg.is_remote_frame, msg.is_error_frame, msg.timestamp,
                               msg.is_fd)
        if isinstance(got, Decoded):
            return pdo.name, got.inputs, got.raw
        if got.reason is not RejectReason.UNKNOWN_ID:
            return f"{got.reason.value}: {got.detail}"
        try:
            raw = ecu.dbc[f"{pdo.name}_N{ecu.node}"].decode(
                data, decode_choices=False, scaling=True, allow_truncated=False,
                allow_excess=False)
        except Exception as exc:  # cantools raises several types on a malformed frame
            return f"malformed: {type(exc).__name__}: {one_line(exc)}"
        return pdo.name, (), cast("dict[str, float]", raw)

    def on_rpdo(self, msg: can.Message, pdo: Pdo) -> None:
        ecu = self.ecu
        if self.nmt != _NMT_OPERATIONAL:  # PDOs are read in operational only (CiA 301)
            ecu.received["ignored"] += 1
            return
        got = self._read(msg, pdo)
        if isinstance(got, str):
            ecu.received["rejected"] += 1
            if self.rejecting == 0:
                log.warning("node %d: %s rejected: %s (rejections are counted, not logged, "
                            "until one is read)", ecu.node, pdo.name, got)
            self.rejecting += 1
            return
        self.rejecting = 0
        ecu.received["rpdo"] += 1
        trans = pdo.transmission if pdo.transmission is not None else 255
        if trans <= 240:
            self.pending[msg.arbitration_id] = got
        else:
            self._apply(got)

    def on_sync(self) -> list[can.Message]:
        """One sample of the model and the synchronous TPDOs due on this SYNC."""
        ecu, plant = self.ecu, self.plant
        if self.nmt != _NMT_OPERATIONAL:
            ecu.received["ignored"] += 1
            return []
        ecu.received["sync"] += 1
        for d in self.pending.values():
            self._apply(d)
        self.pending.clear()
        k = self.k
        t = k / ecu.rate
        gamma = self._gamma(min(t, self.last_scenario_time))
        msgs: list[can.Message] = []
        outage = bool(np.any(gamma >= 1.0))
        if outage != self.fault:
            self.fault = outage
            msgs.append(self._emcy(outage, time.time()))
            if outage:
                self.state = FAULT
        u = self.target.copy() if self.state == OE else np.zeros(ecu.m)
        self.y = y = plant.output(u, gamma)
        msgs += [self._pdo(p, self.target, y, time.time()) for p in self.tx_sync
                 if self._due(p, k, t)]
        plant.advance(u, gamma)
        self.k += 1
        self.stats.samples += 1
        return msgs

    def events(self, now: float) -> list[can.Message]:
        """The event-driven TPDOs due at `now` (monotonic): each event timer, or a change
        of their data where they have none."""
        if self.nmt != _NMT_OPERATIONAL:
            return []
        msgs = []
        for p in self.tx_event:
            timer = (p.event_timer_ms or 0) / 1000.0
            if timer > 0:
                due = self.event_due.get(p.name, now)
                if now < due:
                    continue
                self.event_due[p.name] = max(due + timer, now)
            msg = self._pdo(p, self.target, self.y, time.time())
            if timer <= 0 and self.event_sent.get(p.name) == bytes(msg.data):
                continue
            self.event_sent[p.name] = bytes(msg.data)
            msgs.append(msg)
        return msgs

    def serve(self, bus: can.BusABC, n: int | None, stop: threading.Event) -> ECUStats:
        """Boot up, then answer the host's frames until `n` SYNCs are answered (None: no
        end) or `stop` is set; the heartbeat goes out on the monotonic clock."""
        ecu, stats = self.ecu, self.stats
        failing = 0
        start = time.monotonic()

        def send(msgs: list[can.Message]) -> None:
            nonlocal failing
            for m in msgs:
                kind = ecu.kind_of[m.arbitration_id]
                stats.produced[kind] += 1
                try:
                    send_frame(bus, m, ecu.send_timeout)
                except (can.CanError, OSError) as exc:
                    stats.send_errors += 1
                    if failing == 0:
                        log.warning("node %d: send failed: %s (failures are counted, not "
                                    "logged, until a send succeeds)", ecu.node, exc)
                    failing += 1
                else:
                    stats.sent[kind] += 1
                    failing = 0

        try:
            send([self._frame(0x700 + ecu.node, b"\x00")])  # boot-up
            next_beat = start + ecu.heartbeat_s
            while not stop.is_set() and (n is None or self.k < n):
                now = time.monotonic()
                if now >= next_beat:
                    send([self._frame(0x700 + ecu.node, bytes((self.nmt,)))])
                    # after a stall the next beat is one period on, not a burst
                    next_beat = max(next_beat + ecu.heartbeat_s, now)
                send(self.events(now))
                msg = bus.recv(timeout=max(0.0, min(next_beat - now, _POLL_S)))
                if msg is None:
                    continue
                if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
                    ecu.received["ignored"] += 1
                elif msg.arbitration_id == NMT_ID:
                    send(self.on_nmt(bytes(msg.data)))
                elif msg.arbitration_id == SYNC_ID and len(msg.data) <= 1:  # 1: its counter
                    send(self.on_sync())
                elif msg.arbitration_id in self.rx:
                    self.on_rpdo(msg, self.rx[msg.arbitration_id])
                else:
                    ecu.received["ignored"] += 1
        finally:
            stats.elapsed = time.monotonic() - start
        return stats
