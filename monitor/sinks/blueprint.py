"""How the monitor looks in the Rerun viewer: the entity layout, the series styles and the
default blueprint (one tab per node, one for the daemon), and a blueprint sender that does
not leak SDK threads.

Entity layout (``<n>`` is the CAN node id)::

    /motor/<n>/current/measured   Scalars   measured armature current
    /motor/<n>/current/estimated  Scalars   UKF output estimate
    /motor/<n>/gamma/estimate     Scalars   actuator loss of effectiveness gamma^
    /motor/<n>/gamma/true         Scalars   true gamma (only rows where it is given: sim/HIL)
    /motor/<n>/gamma/F1           Scalars   diagnosis threshold F1 (step line)
    /motor/<n>/gamma/F2           Scalars   diagnosis threshold F2
    /motor/<n>/rules              Scalars   number of fuzzy rules of the estimator (step line)
    /motor/<n>/health             Scalars   health state 0..3 (step line)
    /motor/<n>/model_mismatch     Scalars   model-mismatch flag 0/1, beside the state (step line)
    /motor/<n>/nis                Scalars   normalised innovation squared
    /motor/<n>/voltage            Scalars   supply voltage (own rate, own buffer)
    /motor/<n>/events             TextLog   state transitions etc.
    /monitor/counters/<name>      Scalars   daemon health counters (frames ok, rejected, ...);
                                            a ``/`` in a counter name nests the entity
    /monitor/events               TextLog   bus events (error frames, interface outages)
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Final

import rerun as rr
import rerun.blueprint as rrb
import rerun_bindings

__all__ = ["BUS_EVENTS_PATH", "STYLES", "BlueprintSender", "counter_path", "default_blueprint",
           "node_path", "series_style"]

_log = logging.getLogger(__name__)

Color = tuple[int, int, int]

_STEP: Final = rr.components.InterpolationMode.StepAfter

# (entity suffix, legend name, colour, line width, stepped)
STYLES: Final[tuple[tuple[str, str, Color, float, bool], ...]] = (
    ("current/measured", "measured current", (120, 144, 156), 1.0, False),
    ("current/estimated", "estimated current", (255, 127, 14), 1.5, False),
    ("gamma/estimate", "gamma^ (estimate)", (31, 119, 180), 2.0, False),
    ("gamma/true", "gamma (true)", (44, 160, 44), 1.5, False),
    ("gamma/F1", "F1", (230, 171, 2), 1.0, True),
    ("gamma/F2", "F2", (214, 39, 40), 1.0, True),
    ("rules", "fuzzy rules", (148, 103, 189), 1.5, True),
    ("health", "health state (0..3)", (23, 190, 207), 2.0, True),
    ("model_mismatch", "model mismatch", (227, 119, 194), 2.0, True),
    ("nis", "NIS", (127, 127, 127), 1.0, False),
    ("voltage", "supply voltage", (188, 189, 34), 1.0, False),
)
COUNTER_COLOR: Final[Color] = (140, 86, 75)


def node_path(node: int, suffix: str) -> str:
    """The entity of series `suffix` (e.g. "gamma/estimate", "events") of `node`."""
    return f"/motor/{node}/{suffix}"


def counter_path(name: str) -> str:
    parts = [rr.escape_entity_path_part(p) for p in name.split("/") if p]
    if not parts:
        raise ValueError(f"invalid counter name {name!r}")
    return "/monitor/counters/" + "/".join(parts)


def series_style(name: str, color: Color, width: float, stepped: bool) -> rr.SeriesLines:
    return rr.SeriesLines(
        names=name,
        colors=[color],
        widths=width,
        interpolation_mode=_STEP if stepped else None,
    )


BUS_EVENTS_PATH = "/monitor/events"


def default_blueprint(nodes: Sequence[int]) -> rrb.Blueprint:
    """One tab per node (current, gamma^ vs thresholds, rules, health, model mismatch, NIS,
    voltage, events)
    and one tab with the daemon counters."""
    tabs: list[rrb.Container | rrb.View] = []
    for n in nodes:
        m = f"/motor/{n}"
        tabs.append(
            rrb.Vertical(
                rrb.TimeSeriesView(origin=f"{m}/current", name="measured vs estimated current"),
                rrb.TimeSeriesView(origin=f"{m}/gamma", name="gamma^ vs thresholds"),
                rrb.Horizontal(
                    rrb.TimeSeriesView(origin=f"{m}/rules", name="rule count"),
                    rrb.TimeSeriesView(
                        origin=f"{m}/health",
                        name="health state",
                        axis_y=rrb.ScalarAxis(range=(-0.25, 3.25), zoom_lock=True),
                    ),
                    rrb.TimeSeriesView(
                        origin=f"{m}/model_mismatch",
                        name="model mismatch",
                        axis_y=rrb.ScalarAxis(range=(-0.1, 1.1), zoom_lock=True),
                    ),
                    rrb.TimeSeriesView(
                        origin=f"{m}/nis",
                        name="NIS",
                        # chi-square(1): a fitting model stays mostly below 4; a start-up
                        # spike of 1000 would otherwise flatten the whole plot
                        axis_y=rrb.ScalarAxis(range=(0.0, 20.0), zoom_lock=False),
                    ),
                    rrb.TimeSeriesView(origin=f"{m}/voltage", name="supply voltage"),
                ),
                rrb.TextLogView(origin=f"{m}/events", name="events"),
                row_shares=[3.0, 3.0, 2.0, 2.0],
                name=f"motor {n}",
            )
        )
    tabs.append(
        rrb.Vertical(
            rrb.TimeSeriesView(origin="/monitor/counters", name="daemon counters"),
            rrb.TextLogView(origin=BUS_EVENTS_PATH, name="bus events"),
            row_shares=[3.0, 1.0],
            name="daemon",
        )
    )
    return rrb.Blueprint(rrb.Tabs(*tabs, active_tab=0), collapse_panels=False)


class BlueprintSender:
    """Sends blueprints to a recording through one long-lived blueprint stream.

    `RecordingStream.send_blueprint` creates a new blueprint `RecordingStream` per call, and the
    Python SDK never frees a stream's threads (rerun-io/rerun#2116): each call costs two threads
    and about 1 MB for the rest of the process, which a rotation per hour turns into a leak. This
    keeps one blueprint stream and gives it a fresh memory sink per blueprint -- the steps of
    ``rerun.sinks.send_blueprint`` in SDK 0.41, whose internals it uses; if they are missing
    (another SDK version) it falls back to the public call.
    """

    def __init__(self, rec: rr.RecordingStream, application_id: str) -> None:
        self._rec = rec
        self._stream: rr.RecordingStream | None = None
        try:
            self._stream = rr.RecordingStream._from_native(
                rerun_bindings.new_blueprint(
                    application_id=application_id,
                    make_default=False,
                    make_thread_default=False,
                    default_enabled=True,
                )
            )
        except (AttributeError, TypeError) as exc:  # pragma: no cover - other SDK versions
            _log.debug("rerun sink: public send_blueprint (%s)", exc)

    def send(self, blueprint: rrb.Blueprint) -> None:
        stream = self._stream
        if stream is not None:
            try:
                memory = stream.memory_recording()
                stream.set_time("blueprint", sequence=0)
                blueprint._log_to_stream(stream)
                rerun_bindings.send_blueprint(
                    memory.storage, True, True, recording=self._rec.to_native()
                )
                return
            except (AttributeError, TypeError) as exc:  # pragma: no cover - other SDK versions
                _log.debug("rerun sink: public send_blueprint (%s)", exc)
                self._stream = None
        self._rec.send_blueprint(blueprint, make_active=True, make_default=True)
