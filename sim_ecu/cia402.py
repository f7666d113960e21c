"""The twin of a CANopen rig: a CiA 402 drive on the bus, and the host that drives it.

`Cia402ECU` is `sim_ecu.rig_ecu.RigECU` for a rig with ``[bus] protocol = "canopen"``. Each
sample of the rig's model (the scenario's command on the inputs, its gamma on the faulty
actuators) is one SYNC cycle, in the order a CiA 402 drive sees it:

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

Every PDO is encoded from the rig's bus description (`monitor.bus.canopen`), the frames the
monitor reads through the codec, so the twin and the monitor read the same bits.
"""

from __future__ import annotations

import can
import numpy as np
from canopen.emcy import EMCY_STRUCT

from monitor.bus.canopen import CanopenNode, Pdo, canopen_database, canopen_node
from monitor.bus.errors import CodecError
from monitor.bus.rigcodec import RigCodec
from monitor.errors import one_line
from monitor.rig import Rig
from sim_ecu.ecu import DEFAULT_MAX_CATCH_UP, ECUError, ECUStats
from sim_ecu.rig_ecu import RigECU, _RigSimulation
from sim_ecu.scenario import Scenario

__all__ = ["EMCY_OUTAGE", "STATUS_FAULT", "STATUS_OPERATION_ENABLED", "Cia402ECU"]

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


class Cia402ECU(RigECU):
    """One CiA 402 drive of a CANopen rig, simulated with its host: `frames` offline, `run`
    in real time on `bus`."""

    def __init__(self, bus: can.BusABC | None, codec: RigCodec, rig: Rig, node: int,
                 scenario: Scenario, *, seed: int = 0,
                 max_catch_up: int = DEFAULT_MAX_CATCH_UP) -> None:
        super().__init__(bus, codec, rig, node, scenario, seed=seed, max_catch_up=max_catch_up)
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
        status = STATUS_FAULT if self.fault else STATUS_OPERATION_ENABLED
        control = CONTROL_FAULT_RESET if self.fault else CONTROL_ENABLE_OPERATION
        fixed = {0x6041: status, 0x6040: control, 0x6061: MODE_CSV, 0x6060: MODE_CSV}
        return {o.name: model.get(o.name, float(fixed.get(o.index, 0))) for o in pdo.objects}

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
            code, register = (EMCY_OUTAGE, 0x01) if outage else (0, 0)
            msgs.append(can.Message(timestamp=ts, arbitration_id=0x80 + node,
                                    is_extended_id=False,
                                    data=EMCY_STRUCT.pack(code, register, b"")))
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
