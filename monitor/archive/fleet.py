"""The fleet overview of an archive replay: a PNG with one row per log and node, its
health state over the log's time, and a row saying why for each log that failed.

matplotlib comes with the `archive` extra and is imported only when the figure is drawn
(the daemon never loads a plotting library). The states take the colours the recording
gives them in the Rerun viewer's plots: fault in the colour of threshold F1 and outage in
that of F2 (the thresholds that lead into them, `monitor.sinks.blueprint.STYLES`),
fault-free in the true gamma's green, no data in the NIS grey, lightened. (The
model-mismatch flag stands beside the state: the summary's `seconds_model_mismatch`.)
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from monitor.archive.result import STATES, LogResult
from monitor.sinks.blueprint import STYLES

__all__ = ["STATE_COLOURS", "write_fleet_png"]

_STYLE_COLOUR = {suffix: colour for suffix, _, colour, _, _ in STYLES}


def _lighten(rgb: tuple[int, int, int], by: float) -> tuple[int, int, int]:
    return tuple(int(c + (255 - c) * by) for c in rgb)  # type: ignore[return-value]


STATE_COLOURS: dict[str, tuple[int, int, int]] = {
    "fault_free": _STYLE_COLOUR["gamma/true"],
    "fault": _STYLE_COLOUR["gamma/F1"],
    "outage": _STYLE_COLOUR["gamma/F2"],
    "no_data": _lighten(_STYLE_COLOUR["nis"], 0.55),
}
assert set(STATE_COLOURS) == set(STATES)

_FAILED_COLOUR = (90, 90, 90)
_MAX_HEIGHT_IN = 120.0


def _rgb(c: tuple[int, int, int]) -> tuple[float, float, float]:
    return (c[0] / 255, c[1] / 255, c[2] / 255)


def write_fleet_png(path: Path, results: Sequence[LogResult]) -> None:
    """One row per (log, node): its health state against seconds since the log's first
    frame. Raises ImportError without matplotlib."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    dirs = [os.path.dirname(os.path.abspath(r.log)) for r in results]
    common = os.path.commonpath(dirs) if dirs else ""

    def label(r: LogResult) -> str:  # the log's path below the directory all share
        return os.path.relpath(os.path.abspath(r.log), common)

    rows: list[tuple[str, LogResult, int | None]] = []
    for r in results:
        if r.ok and r.nodes:
            rows += [(f"{label(r)}  node {n.node}", r, i) for i, n in enumerate(r.nodes)]
        else:
            rows.append((label(r), r, None))
    n_rows = max(len(rows), 1)
    height = min(1.6 + 0.32 * n_rows, _MAX_HEIGHT_IN)
    fig, ax = plt.subplots(figsize=(12.0, height))
    longest = max((r.duration_s for r in results if r.ok), default=0.0) or 1.0
    for y, (_, r, i) in enumerate(rows):
        if i is None:
            text = (f"failed: {r.reason.removeprefix(r.log + ': ')}" if not r.ok
                    else "no node in this log")
            ax.text(0.005 * longest, y, text, va="center", ha="left", fontsize=7,
                    color=_rgb(_FAILED_COLOUR), clip_on=True)
            continue
        assert r.t_first is not None and r.t_last is not None
        for start, end, state in r.nodes[i].timeline(r.t_first, r.t_last):
            ax.barh(y, end - start, left=start - r.t_first, height=0.8,
                    color=_rgb(STATE_COLOURS.get(state, _FAILED_COLOUR)), linewidth=0)
    ax.set_yticks(range(len(rows)), [label for label, _, _ in rows],
                  fontsize=7 if n_rows > 30 else 9)
    ax.set_ylim(len(rows) - 0.5, -0.5)
    ax.set_xlim(0.0, longest)
    ax.set_xlabel("time since the log's first frame (s)")
    ax.set_ylabel(f"log below {common}, node", fontsize=8)
    ok = sum(1 for r in results if r.ok)
    ax.set_title(f"fleet health: {ok} of {len(results)} logs replayed")
    ax.legend(handles=[Patch(color=_rgb(STATE_COLOURS[s]), label=s) for s in STATES],
              loc="upper center", bbox_to_anchor=(0.5, -0.9 / height), ncol=len(STATES),
              fontsize=8, frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
