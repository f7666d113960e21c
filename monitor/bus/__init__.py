"""The bus stage: CAN frames <-> typed samples.

Everything that knows about payload bytes lives here: the DBC, the AUTOSAR E2E CRC and
alive counter, SecOC authentication and freshness, and the faults of the bus itself.

* `monitor.bus.codec`: `load_database` / `MotorDatabase`, encoding samples to frames and
  the never-raising decoder (`Decoded`, `Rejected`, `RejectReason`), the one order of a
  frame's checks (`CHECK_ORDER`, `check_payload`).
* `monitor.bus.route`: `Route`, what one arbitration ID is and how it is read, which every
  codec builds and exposes alike (`RouteSource`: ``routes``, ``accepts_extended``,
  ``frame_by_frame``), for the per-frame and the column decoder.
* `monitor.bus.scheme`: the bus layout (`Kind`, `KINDS`, `N_NODES`, `frame_id`, E2E data
  IDs), the checks a DBC must pass and the routes built from it.
* `monitor.bus.rigcodec`: `RigCodec`, a rig's own DBC and node layout.
* `monitor.bus.counters`: `CounterTracker`, the alive-counter supervision per stream.
* `monitor.bus.secoc`: SecOC keys, frame layouts, signing/verifying and the freshness
  state file (a package).
* `monitor.bus.faults`: SocketCAN error frames and the kernel's count of dropped frames.
* `monitor.bus.errors`: `CodecError` and `SecOCError` (both `monitor.errors.MonitorError`).
* ``motor.dbc``: the DBC shipped with the package (a link to dbc/motor.dbc).
"""
