"""The pipeline's counters: every frame's outcome lands in exactly one of them.

Names are "<group>/<what>" and are what the recording's daemon tab, the exit summary,
`systemctl status` and the tests read; they are written here once.
"""

from __future__ import annotations

from typing import Final

__all__ = ["Counters", "bus_error", "rejected", "transition"]

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
SAMPLES_ESTIMATED: Final = "samples/estimated"
SAMPLES_VOLTAGE: Final = "samples/voltage"
SAMPLES_TRUTH: Final = "samples/truth"
SAMPLES_SECOC_SYNC: Final = "samples/secoc_sync"
SAMPLES_NO_VOLTAGE: Final = "samples/no_voltage"
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

    def rejected_total(self) -> int:
        """Frames rejected by the codec, for every reason."""
        return sum(v for k, v in self.items() if k.startswith(REJECTED_PREFIX))
