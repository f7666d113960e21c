"""How the monitor looks in the Rerun viewer: the entity layout, the series styles and the
default blueprint (one tab per node, one for the daemon), and a blueprint sender that does
not leak SDK threads.

Entity layout (``<n>`` is the CAN node id; ``<Output>`` and ``<Input>`` are the rig's DBC
signal names, `PlantSignals`: ``ArmatureCurrent`` and ``VoltageCommand`` on our bus)::

    /node/<n>/<Output>/measured   Scalars   each output as measured
    /node/<n>/<Output>/estimated  Scalars   its UKF estimate
    /node/<n>/<Output>/noise      Scalars   its noise variance as the estimator has adapted
                                            it, a factor on the model's (1: the model's noise
                                            fits; above: the sensor is noisier than it says)
    /node/<n>/gamma/estimate      Scalars   actuator loss of effectiveness gamma^
    /node/<n>/gamma/sd            Scalars   gamma^'s standard deviation (of the largest gamma^
                                            where several inputs may lose effectiveness: the
                                            one the diagnosis reads); NaN where none is given
    /node/<n>/gamma/true          Scalars   true gamma (only rows where it is given: sim/HIL)
    /node/<n>/gamma/F1            Scalars   diagnosis threshold F1 (step line)
    /node/<n>/gamma/F2            Scalars   diagnosis threshold F2
    /node/<n>/rules               Scalars   number of fuzzy rules of the estimator (step line)
    /node/<n>/health              Scalars   health state 0..3 (step line)
    /node/<n>/model_mismatch      Scalars   model-mismatch flag 0/1, beside the state (step line)
    /node/<n>/nis                 Scalars   normalised innovation squared
    /node/<n>/process_noise       Scalars   the factor the estimator puts on the model's
                                            process noise (1 to 100; far above 1: the model
                                            misses dynamics, a loss shows less in gamma^)
    /node/<n>/<Input>             Scalars   each input as its frames carry it (own rate, own
                                            buffer)
    /node/<n>/events              TextLog   state transitions etc.
    /monitor/counters/<name>      Scalars   daemon health counters (frames ok, rejected, ...);
                                            a ``/`` in a counter name nests the entity
    /monitor/events               TextLog   bus events (error frames, interface outages)

A signal's legend is its name and unit ("ArmatureCurrent measured (A)"). A signal name is
escaped as one entity path part; one that is the name of a series above (``gamma``,
``rules``...) or of another signal gets ``_signal``, ``_2``... appended (`signal_parts`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Final

import rerun as rr
import rerun.blueprint as rrb
import rerun_bindings

from monitor.pipeline.events import PlantSignals

__all__ = ["BUS_EVENTS_PATH", "ESTIMATED_COLOR", "INPUT_COLOR", "MEASURED_COLOR", "NOISE_COLOR",
           "STYLES", "BlueprintSender", "counter_path", "default_blueprint", "node_path",
           "series_style", "signal_legend", "signal_parts"]

_log = logging.getLogger(__name__)

Color = tuple[int, int, int]

_STEP: Final = rr.components.InterpolationMode.StepAfter

# (entity suffix, legend name, colour, line width, stepped) of the series every plant has;
# the inputs' and outputs' series are named after the rig's signals (`signal_parts`)
STYLES: Final[tuple[tuple[str, str, Color, float, bool], ...]] = (
    ("gamma/estimate", "gamma^ (estimate)", (31, 119, 180), 2.0, False),
    ("gamma/sd", "gamma^ standard deviation", (174, 199, 232), 1.0, False),
    ("gamma/true", "gamma (true)", (44, 160, 44), 1.5, False),
    ("gamma/F1", "F1", (230, 171, 2), 1.0, True),
    ("gamma/F2", "F2", (214, 39, 40), 1.0, True),
    ("rules", "fuzzy rules", (148, 103, 189), 1.5, True),
    ("health", "health state (0..3)", (23, 190, 207), 2.0, True),
    ("model_mismatch", "model mismatch", (227, 119, 194), 2.0, True),
    ("nis", "NIS", (127, 127, 127), 1.0, False),
    ("process_noise", "process noise factor", (196, 156, 148), 1.5, False),
)
MEASURED_COLOR: Final[Color] = (120, 144, 156)
"""An output as measured (line width 1)."""
ESTIMATED_COLOR: Final[Color] = (255, 127, 14)
"""An output's estimate (line width 1.5)."""
INPUT_COLOR: Final[Color] = (188, 189, 34)
"""An input (line width 1)."""
NOISE_COLOR: Final[Color] = (255, 187, 120)
"""An output's noise factor (line width 1): a light shade of the estimate's colour."""
COUNTER_COLOR: Final[Color] = (140, 86, 75)

_RESERVED: Final = frozenset(s[0].split("/")[0] for s in STYLES) | {"events"}
"""The top-level parts of a node's own series: no signal's entity may take one."""


def node_path(node: int, suffix: str) -> str:
    """The entity of series `suffix` (e.g. "gamma/estimate", "events", a signal's part from
    `signal_parts`) of `node`."""
    return f"/node/{node}/{suffix}"


def signal_parts(signals: PlantSignals, m: int = 0,
                 p: int = 0) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The entity path part of each input and of each output under a node (at least `m`
    inputs and `p` outputs, beyond the names given ``u3``, ``y2``...): the signal name,
    escaped; a name a node's own series has gets ``_signal``, one taken already ``_2``,
    ``_3``..., so that every series has an entity of its own."""
    taken = set(_RESERVED)

    def part(name: str) -> str:
        base = rr.escape_entity_path_part(name) or "signal"
        if base in _RESERVED:
            base += "_signal"
        out, k = base, 1
        while out in taken:
            k += 1
            out = f"{base}_{k}"
        taken.add(out)
        return out

    ins = tuple(part(signals.input(i)[0]) for i in range(max(m, len(signals.inputs))))
    outs = tuple(part(signals.output(j)[0]) for j in range(max(p, len(signals.outputs))))
    return ins, outs


def signal_legend(signal: tuple[str, str | None], what: str = "") -> str:
    """A signal's legend: its name, what the series is of it, its unit ("ArmatureCurrent
    measured (A)")."""
    name, unit = signal
    text = f"{name} {what}" if what else name
    return f"{text} ({unit})" if unit else text


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


def default_blueprint(nodes: Sequence[int],
                      signals: PlantSignals | None = None) -> rrb.Blueprint:
    """One tab per node (each output measured vs estimated, gamma^ vs thresholds, rules,
    health, model mismatch, NIS, the noise factors, each input, events) and one tab with
    the daemon counters; the signals named as `signals` (default: our bus's) name them. An
    output's view shows its measured and estimated series only: its noise factor, a ratio
    near 1, is drawn with the process noise's factor in a view of their own. The gamma view
    shows every series under ``gamma/`` (its contents are its origin's subtree): gamma^, the
    true gamma, the thresholds, and gamma^'s standard deviation, thin and in a light shade of
    gamma^'s colour so that it reads as gamma^'s spread, not as another threshold."""
    sig = signals if signals is not None else PlantSignals()
    ins, outs = signal_parts(sig)
    tabs: list[rrb.Container | rrb.View] = []
    for n in nodes:
        m = f"/node/{n}"
        out_views = [rrb.TimeSeriesView(origin=f"{m}/{part}",
                                        contents=["$origin/measured", "$origin/estimated"],
                                        name=f"{sig.output(j)[0]}: measured vs estimated")
                     for j, part in enumerate(outs)]
        noise_view = rrb.TimeSeriesView(
            origin=m, contents=[*(f"$origin/{part}/noise" for part in outs),
                                "$origin/process_noise"],
            name="noise factors (1: the model's)")
        in_views = [rrb.TimeSeriesView(origin=f"{m}/{part}", name=signal_legend(sig.input(i)))
                    for i, part in enumerate(ins)]
        tabs.append(
            rrb.Vertical(
                out_views[0] if len(out_views) == 1 else rrb.Horizontal(*out_views),
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
                    noise_view,
                    *in_views,
                ),
                rrb.TextLogView(origin=f"{m}/events", name="events"),
                row_shares=[3.0, 3.0, 2.0, 2.0],
                name=f"node {n}",
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
