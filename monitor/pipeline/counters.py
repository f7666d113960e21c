"""The pipeline's counters: every frame's outcome lands in exactly one of them.

Names are "<group>/<what>" and are what the recording's daemon tab, the exit summary,
`systemctl status` and the tests read; they are written here once.

Nothing decoded is no success: `nothing_decoded` turns the counters of a run in which a
node (a configured one, or every node) got no estimated sample into one line -- the counts
by outcome and the likely cause -- that `replay`, `calibrate`, `identify`, the archive
summary and the live daemon (`DecodeWatch`) all give in the same words.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Final

from monitor.bus.cia402 import IGNORED_PROTOCOL

__all__ = ["Counters", "DecodeWatch", "bus_error", "decode_outcomes", "nothing_decoded",
           "rejected", "transition"]

FRAMES_RECEIVED: Final = "frames/received"
#: Of the frames received, those in CAN FD format, and those of them whose error state
#: indicator says the sender is error passive. Not outcomes: each such frame is also in
#: exactly one outcome counter (decoded, or e.g. ``rejected/fd_frame``).
FRAMES_FD: Final = "frames/fd"
FRAMES_FD_ESI: Final = "frames/fd_esi"
REJECTED_PREFIX: Final = "rejected/"
IGNORED_NODE: Final = "ignored/node"
IGNORED_DIAGNOSIS: Final = "ignored/diagnosis"
IGNORED_SECOC_SYNC: Final = "ignored/secoc_sync"
E2E_REPEATED: Final = "e2e/repeated"
E2E_COUNTER_JUMPS: Final = "e2e/counter_jumps"
E2E_LOST_FRAMES: Final = "e2e/lost_frames"
TIME_NON_MONOTONIC: Final = "time/non_monotonic"
TIME_JITTER: Final = "time/jitter"
TIME_OFF_RATE: Final = "time/off_rate"
SAMPLES_ESTIMATED: Final = "samples/estimated"
SAMPLES_INPUT: Final = "samples/input"
SAMPLES_TRUTH: Final = "samples/truth"
SAMPLES_SECOC_SYNC: Final = "samples/secoc_sync"
SAMPLES_NO_INPUT: Final = "samples/no_input"
SAMPLES_PREDICTED_THROUGH: Final = "samples/predicted_through"
ESTIMATOR_RESTARTS: Final = "estimator/restarts"
ESTIMATOR_NAN: Final = "estimator/nan"
ESTIMATOR_STRUCTURE_EVENTS: Final = "estimator/structure_events"
NODES_SILENT: Final = "nodes/silent"
NODES_MODEL_MISMATCH: Final = "nodes/model_mismatch"
PUBLISH_SENT: Final = "publish/sent"
PUBLISH_ERRORS: Final = "publish/errors"
PUBLISH_ENCODE_ERRORS: Final = "publish/encode_errors"
BUS_ERROR_FRAMES: Final = "bus/error_frames"
BUS_OUTAGES: Final = "bus/outages"
BUS_RECONNECTS: Final = "bus/reconnects"
BUS_SOCKET_DROPS: Final = "bus/socket_drops"


def rejected(reason: str) -> str:
    """The counter of frames the codec rejected for `reason` (a `RejectReason`)."""
    return REJECTED_PREFIX + reason


def bus_error(condition: str) -> str:
    """The counter of error frames reporting `condition` (bus_off, controller/...)."""
    return f"bus/errors/{condition}"


def transition(state: str) -> str:
    """The counter of transitions into health state `state`."""
    return f"transitions/{state}"


class Counters(dict[str, int]):
    """Named event counters."""

    def inc(self, name: str, n: int = 1) -> None:
        self[name] = self.get(name, 0) + n

    def received(self, frames: int, fd: int, fd_esi: int) -> None:
        """Frames received, of them CAN FD and FD with the error state indicator set
        (sub-counts of `frames/received`, not outcomes): counted alike by both engines."""
        self.inc(FRAMES_RECEIVED, frames)
        if fd:
            self.inc(FRAMES_FD, fd)
            if fd_esi:
                self.inc(FRAMES_FD_ESI, fd_esi)

    def rejected_total(self) -> int:
        """Frames rejected by the codec, for every reason."""
        return sum(v for k, v in self.items() if k.startswith(REJECTED_PREFIX))


# -- nothing decoded ----------------------------------------------------------------------

_OUTCOME_PREFIXES = (REJECTED_PREFIX, "ignored/", "samples/")
_OUTCOMES = (BUS_ERROR_FRAMES, E2E_REPEATED, TIME_NON_MONOTONIC)
_LAYOUT = "no frame matches the rig's messages: check [bus] layout / node_bits and the DBC"
_CAUSES: Final[Mapping[str, str]] = {
    rejected("unknown_id"): _LAYOUT,
    rejected("extended_id"): _LAYOUT,
    rejected("bad_crc"): "the frames fail their E2E check: check [protection] (crc, data_id) "
                         "and the DBC",
    rejected("wrong_length"): "the frames do not fit the DBC's messages: check the DBC",
    rejected("out_of_range"): "the signals are out of the DBC's ranges: check the DBC",
    rejected("malformed"): "the frames do not fit the DBC's messages: check the DBC",
    rejected("fd_frame"): "CAN FD and classic frames swapped: check the DBC's messages",
    rejected("remote_frame"): "only remote frames: no data to decode",
    rejected("error_frame"): "only error frames: the bus itself is failing",
    rejected("bad_mac"): "SecOC does not verify the frames: check --key",
    rejected("stale_freshness"): "SecOC freshness does not verify: check --key and "
                                 "--secoc-state",
    rejected("unsynced"): "SecOC never synchronised: the bus has no sync frames, or check "
                          "--key",
    BUS_ERROR_FRAMES: "only error frames: the bus itself is failing",
    IGNORED_NODE: "the frames are of other nodes: check the nodes asked for and [bus] node_bits",
    IGNORED_DIAGNOSIS: "only diagnosis frames (a monitor's output): check the rig",
    IGNORED_PROTOCOL: "only CANopen protocol frames (NMT, SYNC, heartbeat, SDO, PDOs the rig "
                      "does not read): check the rig's PDOs ([bus.pdo]) and node IDs",
    SAMPLES_NO_INPUT: "the outputs never follow an input frame: check [signals] inputs",
    SAMPLES_INPUT: "inputs but no output decoded: check [signals] outputs",
    SAMPLES_TRUTH: "no output decoded: check [signals] outputs",
    E2E_REPEATED: "the alive counters never advance: check [protection] counter",
    TIME_NON_MONOTONIC: "the time stamps go backwards",
}


def decode_outcomes(counters: Mapping[str, int]) -> str:
    """The frames and what became of them, largest first: "5000 frames, 4990 unknown_id,
    10 bus/error_frames" (a rejection by its reason alone)."""
    found = [(v, k) for k, v in counters.items()
             if v and (k.startswith(_OUTCOME_PREFIXES) or k in _OUTCOMES)]
    parts = [f"{v} {k.removeprefix(REJECTED_PREFIX)}"
             for v, k in sorted(found, key=lambda x: (-x[0], x[1]))]
    return ", ".join([f"{counters.get(FRAMES_RECEIVED, 0)} frames", *parts])


def _likely_cause(counters: Mapping[str, int], decoded_elsewhere: bool) -> str:
    if not counters.get(FRAMES_RECEIVED, 0):
        return "no frame at all (an empty log, or a silent bus)"
    if decoded_elsewhere:  # other nodes were estimated: these send nothing the rig decodes
        return "no frame of theirs decoded: check the nodes asked for and [bus] node_bits"
    ranked = sorted(((v, k) for k, v in counters.items() if v and k in _CAUSES),
                    key=lambda x: (-x[0], x[1]))
    if ranked:
        return _CAUSES[ranked[0][1]]
    return "check that the rig (--rig) is the one of this bus"


def nothing_decoded(counters: Mapping[str, int], samples: Mapping[int, int],
                    nodes: Sequence[int] | None = None) -> str | None:
    """One line when a run decoded nothing, else None: with `nodes` (the configured nodes)
    when one of them has no estimated sample in `samples` (samples by node), without when
    no node has one. The line gives the counts by outcome and the likely cause, e.g.
    "0 samples: 5000 frames, 5000 unknown_id: no frame matches the rig's messages: check
    [bus] layout / node_bits and the DBC"."""
    if nodes:
        missing = [n for n in nodes if not samples.get(n, 0)]
        if not missing:
            return None
        who = f"node{'s' if len(missing) > 1 else ''} {', '.join(map(str, missing))}: "
        elsewhere = any(v > 0 for v in samples.values())
    else:
        if any(v > 0 for v in samples.values()):
            return None
        who, elsewhere = "", False
    return (f"{who}0 samples: {decode_outcomes(counters)}: "
            f"{_likely_cause(counters, elsewhere)}")


class DecodeWatch:
    """Nothing decoded on a live bus: `check` gives the `nothing_decoded` line once, the
    first time it is called `after_s` or more after `start` (the same clock) while no
    sample was decoded; `active` says whether that holds at the latest check (a metric a
    Prometheus rule alerts on)."""

    def __init__(self, nodes: Sequence[int] | None, after_s: float, start: float) -> None:
        self.nodes = tuple(nodes) if nodes else None
        self.after_s = after_s
        self.start = start
        self.active = False
        self._said = False

    def check(self, now: float, counters: Mapping[str, int],
              samples: Mapping[int, int]) -> str | None:
        if now - self.start < self.after_s:
            return None
        line = nothing_decoded(counters, samples, self.nodes)
        self.active = line is not None
        if line is None or self._said:
            return None
        self._said = True
        return line
