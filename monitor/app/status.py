"""`motor-monitor status FILE.prom [--watch S]`: the daemon's figures in the terminal, read
from the metrics file it writes (`run --metrics`), parsed with prometheus_client's own
text parser: per node its health, model-mismatch flag, gamma^, NIS and the estimator's
noise factors (the noisiest output's and the process noise's: 1 where the model's noises
fit); the bus load,
frames, error frames, drops and rejections; the busiest IDs with their period and jitter;
the estimation latency.

The file is read like every file a user names (`monitor.files.read_user_text`: a regular
file, at most `METRICS_FILE_LIMIT`), and what it holds is checked before it is shown: a
file that is not Prometheus text, holds no metrics, or has a sample the monitor never
writes (a health state that is no `HealthState`, a model-mismatch flag other than 0 or 1,
a node or ID label missing or not a number) is one `UsageError` line naming the file.
"""

from __future__ import annotations

import argparse
import errno
import math
import sys
import time
from pathlib import Path
from typing import Any

from prometheus_client.parser import text_string_to_metric_families

from monitor.diagnosis import HealthState
from monitor.errors import MonitorError, UsageError, one_line
from monitor.files import MIB, UserFileError, read_user_text, shown_path
from monitor.runtime.argtypes import positive_float

__all__ = ["METRICS_FILE_LIMIT", "add_command", "read_metrics", "render"]

METRICS_FILE_LIMIT = 8 * MIB
"""The largest metrics file read. The monitor writes a few kB (a few hundred lines for 16
nodes and a few dozen IDs); a larger file is not the monitor's, and parsing it would take
seconds and gigabytes."""

_HINT = "is the monitor running with --metrics?"
_P = "motor_monitor_"

Samples = dict[str, list[tuple[dict[str, str], float]]]


def read_metrics(path: Path) -> Samples:
    """Every sample of the file, by sample name; `UsageError` (or `UserFileError`), one
    line, if the file cannot be read, is not Prometheus text or holds no sample."""
    try:
        text = read_user_text(path, what="metrics file", limit=METRICS_FILE_LIMIT)
    except UserFileError as exc:
        if exc.errno == errno.ENOENT:
            raise UsageError(f"{exc}; {_HINT}") from None
        raise
    out: Samples = {}
    try:
        for fam in text_string_to_metric_families(text):
            for s in fam.samples:
                out.setdefault(s.name, []).append((dict(s.labels), float(s.value)))
    except ValueError as exc:
        raise UsageError(f"metrics file {shown_path(path)}: not Prometheus text "
                         f"({one_line(exc, limit=160)})") from None
    if not out:
        raise UsageError(f"metrics file {shown_path(path)}: no metrics in it; {_HINT}")
    return out


def _one(m: Samples, name: str, default: float = math.nan) -> float:
    rows = m.get(name)
    return rows[0][1] if rows else default


def _labelled(m: Samples, name: str, label: str, path: Path) -> list[tuple[str, float]]:
    """(label value, sample value) of every sample `name`; `UsageError` if a sample lacks
    the label, or a ``node`` label is not a node number or an ``id`` label not an ID
    (0x...): the labels are printed, so only what the monitor writes is."""
    out: list[tuple[str, float]] = []
    for labels, value in m.get(name, []):
        text = labels.get(label)
        if text is None:
            raise UsageError(f"metrics file {shown_path(path)}: a {name} sample has no "
                             f"'{label}' label")
        expected = _LABEL_FORMS.get(label)
        if expected is not None and not expected[0](text):
            raise UsageError(f"metrics file {shown_path(path)}: {name}: label {label}="
                             f"{one_line(repr(text), limit=40)} is not {expected[1]}")
        out.append((text, value))
    return out


def _is_node(text: str) -> bool:
    return 0 < len(text) <= 6 and text.isascii() and text.isdecimal()


def _is_can_id(text: str) -> bool:
    digits = text[2:]
    return (text[:2] == "0x" and 0 < len(digits) <= 8
            and all(c in "0123456789abcdefABCDEF" for c in digits))


_LABEL_FORMS = {"node": (_is_node, "a node number"), "id": (_is_can_id, "a CAN ID (0x...)")}


def _state_label(value: float, node: str, path: Path) -> str:
    """The label of the health state number `value`; `UsageError` if it is none."""
    if math.isfinite(value) and value == int(value):
        try:
            return HealthState(int(value)).label
        except ValueError:
            pass
    raise UsageError(f"metrics file {shown_path(path)}: {_P}node_health_state of node "
                     f"{node} is {value!r}, not a health state (0 to "
                     f"{int(max(HealthState))})")


def _flag(value: float, node: str, path: Path) -> str:
    """"yes" or "no" for the model-mismatch gauge's 1 or 0; `UsageError` for anything else."""
    if value in (0.0, 1.0):
        return "yes" if value else "no"
    raise UsageError(f"metrics file {shown_path(path)}: {_P}node_model_mismatch of node "
                     f"{node} is {value!r}, not 0 or 1")


def _factor(value: float | None) -> str:
    """A noise factor as the table shows it: three digits, "-" where there is none."""
    return "-" if value is None else f"{value:.3g}"


def render(m: Samples, path: Path, age_s: float) -> str:
    """The figures of `m` as the terminal shows them; `UsageError`, one line, for a sample
    the monitor never writes (see the module's docstring)."""
    ev = dict(_labelled(m, _P + "events_total", "name", path))
    rejected = sum(v for k, v in ev.items() if k.startswith("rejected/"))
    lines = [
        f"{path} (written {age_s:.0f} s ago)",
        f"bus load {100 * _one(m, _P + 'bus_load_ratio'):.1f} %, "
        f"{_one(m, _P + 'bus_frames_total', ev.get('frames/received', 0)):.0f} frames, "
        f"{ev.get('bus/error_frames', 0):.0f} error frames, "
        f"{ev.get('bus/socket_drops', 0):.0f} kernel drops, {rejected:.0f} rejected, "
        f"{ev.get('e2e/lost_frames', 0):.0f} lost, "
        f"{ev.get('publish/sent', 0):.0f} diagnoses sent",
        "",
        f"{'node':>4s}  {'state':11s} {'mismatch':8s} {'gamma^':>7s} {'NIS':>7s} "
        f"{'noise x':>8s} {'process x':>9s} {'samples':>9s}",
    ]
    gamma = dict(_labelled(m, _P + "node_gamma", "node", path))
    nis = dict(_labelled(m, _P + "node_nis", "node", path))
    samples = dict(_labelled(m, _P + "node_samples_total", "node", path))
    # the noisiest output's factor ("-" in a file of a monitor from before the factors)
    noise: dict[str, float] = {}
    for n, v in _labelled(m, _P + "node_output_noise_factor", "node", path):
        noise[n] = max(v, noise.get(n, -math.inf))
    process = dict(_labelled(m, _P + "node_process_noise_factor", "node", path))
    # "-": a file of a monitor from before the flag (no such gauge)
    mismatch = {n: _flag(v, n, path)
                for n, v in _labelled(m, _P + "node_model_mismatch", "node", path)}
    for n, v in sorted(_labelled(m, _P + "node_health_state", "node", path),
                       key=lambda r: int(r[0])):
        state = _state_label(v, n, path)
        lines.append(f"{n:>4s}  {state:11s} {mismatch.get(n, '-'):8s} "
                     f"{gamma.get(n, math.nan):7.3f} "
                     f"{nis.get(n, math.nan):7.2f} {_factor(noise.get(n)):>8s} "
                     f"{_factor(process.get(n)):>9s} {samples.get(n, 0):9.0f}")
    ids = sorted(_labelled(m, _P + "id_frames_total", "id", path), key=lambda r: -r[1])[:8]
    if ids:
        period = dict(_labelled(m, _P + "id_period_seconds", "id", path))
        jitter = dict(_labelled(m, _P + "id_jitter_seconds", "id", path))
        lines += ["", f"{'id':>10s} {'frames':>9s} {'period ms':>10s} {'jitter ms':>10s}"]
        for i, v in ids:
            lines.append(f"{i:>10s} {v:9.0f} {1e3 * period.get(i, math.nan):10.2f} "
                         f"{1e3 * jitter.get(i, math.nan):10.3f}")
    count = _one(m, _P + "estimation_latency_seconds_count", 0.0)
    if count:
        mean = _one(m, _P + "estimation_latency_seconds_sum") / count
        lines += ["", f"estimation latency: mean {1e3 * mean:.2f} ms over {count:.0f} samples"]
    return "\n".join(lines)


def _screen(path: Path) -> str:
    m = read_metrics(path)
    age = time.time() - _one(m, _P + "last_write_timestamp_seconds", time.time())
    return render(m, path, max(age, 0.0))


def _cmd_status(args: argparse.Namespace) -> int:
    """Print the figures once; with --watch, redraw them every S seconds until interrupted.

    A file that cannot be shown at the start is the error (one line, exit 2). Once it has
    been shown, --watch keeps watching through a problem: the daemon replaces the file by
    a rename and may be restarting, so a missing or unreadable file then takes the table's
    place as one line and the next redraw tries again.
    """
    path = Path(args.metrics)
    text = _screen(path)
    if not args.watch:
        print(text)
        return 0
    while True:
        sys.stdout.write("\x1b[H\x1b[2J" + text + "\n")
        sys.stdout.flush()
        time.sleep(args.watch)
        try:
            text = _screen(path)
        except MonitorError as exc:
            text = (f"motor-monitor: {one_line(exc, limit=500)} (trying again every "
                    f"{args.watch:g} s)")


def add_command(sub: argparse._SubParsersAction[Any]) -> None:
    s = sub.add_parser("status", help="the running daemon's figures, from its metrics file")
    s.add_argument("metrics", metavar="FILE.prom", help="the file of run --metrics")
    s.add_argument("--watch", type=positive_float, default=None, metavar="S",
                   help="redraw every S seconds, like top")
    s.set_defaults(func=_cmd_status)
