"""SecOC-style authentication of the ECU frames: truncated AES-CMAC and freshness counters.

AUTOSAR SecOC appends to an *authentic* PDU a truncated freshness value and a truncated
authenticator (MAC) over ``data ID || authentic PDU || full freshness value``. Here the
MotorCurrent and MotorVoltage frames carry 8 or 4 freshness bits and a 24-bit AES-CMAC,
written before the E2E CRC (E2E over SecOC); one authenticated ``SecOCSync_N<n>`` frame
per stream and second carries the full freshness value, so a receiver that starts late,
restarts or loses frames resynchronises by itself.

Modules (their public API is re-exported here; the helpers they share among themselves,
such as `keys.check_key` or `state.read_state_file`, are not):

* `monitor.bus.secoc.keys`: `load_key` / `parse_key` (an AES-128/256 key from a file
  only its owner can access).
* `monitor.bus.secoc.layout`: `SecOCLayout` and `SyncLayout` (where freshness and MAC sit
  in a DBC message, what the MAC covers; the frame diagrams), the signal and attribute names.
* `monitor.bus.secoc.engine`: `SecOC` (CMAC, `sign` / `verify` and their sync
  counterparts, the freshness counters per stream, the receiver rules), `SecOCHolder` (a
  codec's `secoc` / `secoc_enabled`), `Verdict`, `nearest_freshness`, `aes_cmac`,
  `DEFAULT_WINDOW`.
* `monitor.bus.secoc.state`: the counters' names and values and the state file behind
  `SecOC.save_state` / `SecOC.load_state` (`STATE_FORMAT`, `STATE_VERSION`).

`SecOCError` (one line, a `monitor.errors.MonitorError` and a `ValueError`) is raised for
every key, key file, layout or state file that cannot be used.
"""

from __future__ import annotations

from monitor.bus.errors import SecOCError
from monitor.bus.secoc.engine import (
    DEFAULT_WINDOW,
    SecOC,
    SecOCHolder,
    Verdict,
    aes_cmac,
    nearest_freshness,
)
from monitor.bus.secoc.keys import KEY_LENGTHS, load_key, parse_key
from monitor.bus.secoc.layout import (
    AUTH_ALGORITHM,
    AUTHENTICATOR_SIGNAL,
    DATA_ID_ATTRIBUTE,
    FRESHNESS_ALGORITHM,
    FRESHNESS_LENGTH_ATTRIBUTE,
    FRESHNESS_SIGNAL,
    SYNC_AUTHENTICATOR_SIGNAL,
    SYNC_FRESHNESS_SIGNAL,
    SYNC_KIND_SIGNAL,
    SecOCLayout,
    SyncLayout,
)
from monitor.bus.secoc.state import STATE_FORMAT, STATE_VERSION

__all__ = [
    "AUTHENTICATOR_SIGNAL",
    "AUTH_ALGORITHM",
    "DATA_ID_ATTRIBUTE",
    "DEFAULT_WINDOW",
    "FRESHNESS_ALGORITHM",
    "FRESHNESS_LENGTH_ATTRIBUTE",
    "FRESHNESS_SIGNAL",
    "KEY_LENGTHS",
    "STATE_FORMAT",
    "STATE_VERSION",
    "SYNC_AUTHENTICATOR_SIGNAL",
    "SYNC_FRESHNESS_SIGNAL",
    "SYNC_KIND_SIGNAL",
    "SecOC",
    "SecOCError",
    "SecOCHolder",
    "SecOCLayout",
    "SyncLayout",
    "Verdict",
    "aes_cmac",
    "load_key",
    "nearest_freshness",
    "parse_key",
]
