"""`motor-monitor identify CAPTURE... --out RIG_OUT`: learn each node's model from a healthy
capture, and write a rig file that `run --rig RIG_OUT` uses at once.

The captures are decoded with the input rig (its DBC, node layout, signals, protection);
per node, every output sample becomes one row of (u, y) with the inputs held from their
latest frame. Rejected frames are left out and counted; lost output samples split the
capture into segments and the longest one is fitted (`monitor.identify` needs a regular
sampling). The sample period is the capture's own (the median spacing of the output
samples). The fit and its report come from `monitor.identify.identify`; RIG_OUT is the
input rig with the learned model (DC-motor parameters or state-space matrices), noise
(process_noise / Q and R) and rate; the report is written beside it as JSON (and PNG when
matplotlib is installed) and summarised on standard output.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import tomllib
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from monitor.app import options
from monitor.app.replay import read_log
from monitor.bus.codec import Decoded, Rejected
from monitor.errors import UsageError
from monitor.estimation.model import DCMotorParameters
from monitor.identify import KINDS, Identification, identify
from monitor.rig import Rig

__all__ = ["NodeCapture", "add_command", "collect", "rig_document"]

log = logging.getLogger("motor_monitor")
GAP_PERIODS = 1.5  # an output spacing above this many periods is a lost sample


@dataclass
class NodeCapture:
    """The (t, u, y) rows of one node, in capture order."""

    t: list[float] = field(default_factory=list)
    u: list[list[float]] = field(default_factory=list)
    y: list[tuple[float, ...]] = field(default_factory=list)
    inputs: list[float] | None = None
    seen: list[bool] = field(default_factory=list)


def collect(args: argparse.Namespace, rig: Rig, paths: list[Path]) -> tuple[
        dict[int, NodeCapture], dict[str, int]]:
    """Rows per node from the captures, and what happened to the frames."""
    m = len(rig.inputs)
    nodes: dict[int, NodeCapture] = defaultdict(NodeCapture)
    counts: dict[str, int] = defaultdict(int)
    for path in paths:
        decoder = options.database(args, rig)
        for msg in read_log(path):
            counts["frames"] += 1
            if msg.is_error_frame:
                counts["error_frames"] += 1
                continue
            d = decoder.decode_can(msg)
            if isinstance(d, Rejected):
                counts[f"rejected/{d.reason}"] += 1
                continue
            _row(nodes[d.node], d, m, counts)
    return dict(nodes), dict(counts)


def _row(nc: NodeCapture, d: Decoded, m: int, counts: dict[str, int]) -> None:
    if nc.inputs is None:
        nc.inputs, nc.seen = [0.0] * m, [False] * m
    for i, v in d.inputs:
        nc.inputs[i] = v
        nc.seen[i] = True
    if d.outputs:
        if all(nc.seen):
            nc.t.append(d.timestamp)
            nc.u.append(list(nc.inputs))
            nc.y.append(d.outputs)
            counts["samples"] += 1
        else:
            counts["before_inputs"] += 1


def longest_segment(t: np.ndarray, T: float) -> slice:
    """The longest run of samples without a gap of more than GAP_PERIODS periods."""
    gaps = np.flatnonzero(np.diff(t) > GAP_PERIODS * T) + 1
    edges = np.concatenate([[0], gaps, [t.size]])
    k = int(np.argmax(np.diff(edges)))
    return slice(int(edges[k]), int(edges[k + 1]))


def _matrix(a: np.ndarray) -> list[list[float]]:
    return [[float(v) for v in row] for row in np.atleast_2d(a)]


def rig_document(rig: Rig, ident: Identification, out: Path) -> dict[str, Any]:
    """The input rig's TOML document with the learned model, ready to write at `out`."""
    if rig.source is not None:
        with open(rig.source, "rb") as fh:
            doc = tomllib.load(fh)
    else:
        doc = {"bus": {"layout": rig.layout.kind},
               "signals": {"inputs": [_ref(r) for r in rig.inputs],
                           "outputs": [_ref(r) for r in rig.outputs],
                           **({"truth": _ref(rig.truth)} if rig.truth else {})},
               "protection": {k: {"kind": v.kind, "counter": v.counter, "crc": v.crc,
                                  "data_id": "id_low_byte" if v.data_id is None else v.data_id}
                              for k, v in rig.protection.items()},
               "diagnosis": {}}
    base = out.resolve().parent
    doc["bus"]["dbc"] = [_relative(p.resolve(), base) for p in rig.dbc]
    model: dict[str, Any] = {"rate": 1.0 / ident.T}
    if ident.motor is not None:
        mp: DCMotorParameters = ident.motor
        model.update(kind="dc_motor", J=mp.J, b=mp.b, Ke=mp.Ke, Ki=mp.Ki, Ra=mp.Ra, La=mp.La,
                     process_noise=float(ident.q),
                     speed_noise_ratio=float(ident.report.get("speed_noise_ratio_kappa", 1.0)),
                     output_sigma=float(math.sqrt(float(ident.R[0, 0]))))
    else:
        md = ident.model
        model.update(kind="state_space", domain="continuous", E=_matrix(md.E),
                     A=_matrix(md.A), B=_matrix(md.B), C=_matrix(md.C), Q=_matrix(md.Qc),
                     R=_matrix(md.R), states=list(md.state_names))
        if np.any(md.D):
            model["D"] = _matrix(md.D)
    doc["model"] = model
    return doc


def _ref(r: Any) -> dict[str, str]:
    return {k: v for k, v in (("message", r.message), ("signal", r.signal), ("unit", r.unit))
            if v is not None}


def _relative(p: Path, base: Path) -> str:
    try:
        return str(p.relative_to(base))
    except ValueError:
        import os

        return os.path.relpath(p, base)


def _cmd_identify(args: argparse.Namespace) -> int:
    rig = options.rig(args)
    paths = [Path(p) for p in args.captures]
    out = Path(args.out)
    if not out.resolve().parent.is_dir():
        raise UsageError(f"--out: directory {out.resolve().parent} does not exist")
    nodes, counts = collect(args, rig, paths)
    if args.node is not None:
        nodes = {n: c for n, c in nodes.items() if n == args.node}
    usable = {n: c for n, c in nodes.items() if len(c.t) > 1}
    if not usable:
        where = f"node {args.node}" if args.node is not None else "any node"
        raise UsageError(f"{', '.join(p.name for p in paths)}: no output samples of {where} "
                         f"decoded with this rig ({dict(counts)}); is --rig the rig the "
                         "capture was recorded on?")
    if len(usable) > 1 and args.node is None:
        raise UsageError(f"the capture holds nodes {', '.join(map(str, sorted(usable)))}: "
                         "choose one with --node (each node gets its own rig file)")
    node, nc = next(iter(usable.items()))
    t = np.asarray(nc.t)
    # candump logs keep microseconds: the median spacing, to the microsecond
    T = round(float(np.median(np.diff(t))), 6)
    seg = longest_segment(t, T)
    u = np.asarray(nc.u)[seg]
    y = np.asarray(nc.y)[seg]
    template = DCMotorParameters(**rig.model.motor) if rig.model.kind == "dc_motor" \
        else DCMotorParameters()
    ident = identify(u, y, T, kind=args.model, order=args.order, template=template,
                     input_names=[r.signal for r in rig.inputs],
                     output_names=[r.signal for r in rig.outputs])
    ident.report["capture"] = {"files": [str(p) for p in paths], "node": node,
                               "frames": counts, "period_s": T,
                               "segment": [seg.start, seg.stop], "samples": int(u.shape[0])}
    doc = rig_document(rig, ident, out)
    out.write_text(f"# identified by motor-monitor identify from "
                   f"{', '.join(p.name for p in paths)} (node {node})\n"
                   + tomli_w.dumps(doc))
    # the written rig must load (every key checked) before we say it is done
    from monitor.rig import load_rig

    load_rig(out)
    report_path = out.with_suffix(".identify.json")
    report_path.write_text(ident.to_json() + "\n")
    png = out.with_suffix(".identify.png")
    try:
        ident.to_png(png)
        wrote_png = True
    except UsageError as exc:  # matplotlib is an optional extra
        log.warning("no PNG: %s", exc)
        wrote_png = False
    print(_summary(ident, node, T, u.shape[0]))
    print(f"wrote {out}, {report_path}" + (f", {png}" if wrote_png else ""))
    return 0


def _summary(ident: Identification, node: int, T: float, n: int) -> str:
    rep = ident.report
    fit = rep.get("fit", {})
    lines = [f"node {node}: {ident.kind} model, order {ident.order}, from {n} samples at "
             f"{1.0 / T:g} Hz ({rep.get('seconds', 0.0):.1f} s)"]
    if "nrmse_holdout_pct" in fit:
        lines.append("  hold-out fit (NRMSE): " + ", ".join(
            f"{v:.1f} %" for v in fit["nrmse_holdout_pct"]))
    for key, label in (("whiteness", "innovations white (Ljung-Box p)"),
                       ("cross_correlation", "independent of the input (p)")):
        if key in rep and "p_value" in rep[key]:
            lines.append(f"  {label}: " + ", ".join(f"{p:.3g}" for p in rep[key]["p_value"]))
    if "identifiable" in rep:
        lines.append(f"  identifiable: {rep['identifiable']}")
    lines.append(f"  R = {json.dumps(np.asarray(ident.R).tolist())}, q = {ident.q:.4g}")
    return "\n".join(lines)


def add_command(sub: argparse._SubParsersAction[Any]) -> None:
    c = sub.add_parser("identify", help="learn a node's model from a healthy capture and "
                       "write a rig file for it")
    c.add_argument("captures", nargs="+", metavar="CAPTURE",
                   help="healthy bus captures (.log, .asc, .blf) with the input varying")
    options.add_rig_option(c)
    c.add_argument("--node", type=int, default=None, help="the node to identify")
    c.add_argument("--model", choices=KINDS, default="auto",
                   help="dc_motor (physical parameters), state_space (black box) or auto")
    c.add_argument("--order", type=int, default=None,
                   help="states of a black-box model (default: chosen from the data)")
    c.add_argument("--out", required=True, metavar="RIG_OUT",
                   help="the rig file to write (report beside it: .identify.json/.png)")
    c.set_defaults(func=_cmd_identify, dbc=None, key=None)
