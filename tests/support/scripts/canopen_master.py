"""A CANopen master for canopen.sh (inside the vcan guest): the canopen library's Network on
vcan0, node 1 from the drive's EDS with TPDO4 enabled as the rig enables it. It prints
``master up`` once listening, runs until ``ecu.done`` exists (or SECONDS have passed), and
writes what it heard (heartbeats, TPDO4 statusword and velocity, EMCYs, NMT state) to
``master.json`` in the working directory. Arguments: EDS SECONDS."""

from __future__ import annotations

import json
import os
import socket
import sys
import time
from typing import Any

import canopen
from can.interfaces.socketcan import SocketcanBus

#: Linux's (root: past net.core.rmem_max); Python does not name it.
SO_RCVBUFFORCE = 33


def main(eds: str, seconds: float) -> None:
    network = canopen.Network()
    # the drive's heartbeat, EMCY and TPDO4 only, into a large buffer: on the busy one-CPU
    # guest a master held up for a moment must not lose frames from its socket
    network.connect(interface="socketcan", channel="vcan0",
                    can_filters=[{"can_id": i, "can_mask": 0x7FF} for i in (0x701, 0x081, 0x481)])
    assert isinstance(network.bus, SocketcanBus), network.bus
    network.bus.socket.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, 4194304)
    node = canopen.RemoteNode(1, eds)
    network.add_node(node)
    node.tpdo.read(from_od=True)
    tpdo = node.tpdo[4]
    tpdo.enabled = True
    tpdo.subscribe()
    beats: list[int] = []
    pdos: list[tuple[Any, Any]] = []
    node.nmt.add_heartbeat_callback(beats.append)
    tpdo.add_callback(lambda m: pdos.append((m["Statusword 1"].raw,
                                             m["Velocity Actual Value 1"].raw)))
    print("master up", flush=True)
    end = time.time() + seconds
    # until the twin's run is over (the script says so), then what is still queued
    while time.time() < end and not os.path.exists("ecu.done"):
        time.sleep(0.1)
    time.sleep(1.0)
    network.disconnect()
    with open("master.json", "w") as fh:
        json.dump({"beats": beats, "pdos": pdos,
                   "emcy": [[e.code, e.register, e.get_desc()] for e in node.emcy.log],
                   "state": node.nmt.state}, fh)


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]))
