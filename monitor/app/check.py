"""`motor-monitor check [CAPTURE...] --rig FILE`: what the monitor reads from a rig file (each
message of each node: arbitration ID, length, the model's signals in it, its protection),
and, given captures, what it makes of every frame by arbitration ID (`monitor.rig.survey`,
the monitor's own frame decoder): how many, at what rate and length, read as which message
of which node, rejected and why, or the CANopen protocol's own.

Exit status: 0 the rig is read and (with captures) every message carrying a model input or
output is read from them, for each node the rig or --nodes names (a rig naming none: each
node with a frame read); 1 some is not (one line each saying what to
check); 2 a mistake in the rig file or the command line.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from monitor.app import options
from monitor.bus.logfile import read_log
from monitor.errors import UsageError
from monitor.rig.survey import RigFrame, Survey, rig_frames, survey

__all__ = ["add_command", "run_check"]


def _rig_table(frames: list[RigFrame]) -> list[str]:
    lines = [f"{'node':>4s}  {'message':<16s} {'ID':>10s} {'bytes':>5s}  {'protection':<10s} "
             "model signals"]
    for f in frames:
        ident = f"0x{f.frame_id:X}" + ("x" if f.extended else "")
        signals = "; ".join(p for p in (
            ("inputs " + ", ".join(f.inputs)) if f.inputs else "",
            ("outputs " + ", ".join(f.outputs)) if f.outputs else "") if p) or "-"
        lines.append(f"{f.node:>4d}  {f.name:<16s} {ident:>10s} {f.length:>5d}  "
                     f"{f.protection or '-':<10s} {signals}")
    return lines


def _capture_table(found: Survey) -> list[str]:
    lines = [f"{'ID':>10s} {'frames':>8s} {'Hz':>8s} {'bytes':>8s}  what the monitor makes of them"]
    for s in sorted(found.ids.values(), key=lambda s: (s.extended, s.frame_id)):
        ident = f"0x{s.frame_id:X}" + ("x" if s.extended else "")
        lengths = "/".join(str(k) for k, _ in s.lengths.most_common())
        outcome = ", ".join(f"{k} {n}" for k, n in s.outcomes.most_common())
        what = f"{s.read_as}: {outcome}" if s.read_as else outcome
        lines.append(f"{ident:>10s} {s.frames:>8d} {s.rate_hz:>8.1f} {lengths:>8s}  {what}")
    if found.error_frames:
        lines.append(f"and {found.error_frames} error frames")
    return lines


def run_check(args: argparse.Namespace) -> int:
    rig = options.rig(args, model_optional=True)
    codec = options.database(args, rig)
    frames = rig_frames(codec)
    if args.nodes is not None:
        frames = [f for f in frames if f.node in args.nodes]
        if not frames:
            raise UsageError(f"--nodes {','.join(map(str, args.nodes))}: the rig has no "
                             "message of these nodes")
    where = rig.source if rig.source is not None else "the built-in rig (rigs/motor.toml)"
    print(f"{where}: {len(frames)} messages the monitor reads")
    for line in _rig_table(frames):
        print("  " + line)
    if not args.captures:
        return 0
    problems: list[str] = []
    for capture in args.captures:
        path = Path(capture)
        found = survey(codec, read_log(path))
        print(f"\n{path}: {found.frames} frames")
        for line in _capture_table(found):
            print("  " + line)
        if not found.frames:
            problems.append(f"{path}: no frame in the capture")
        # a rig that names no nodes monitors those that send: only theirs are expected
        fixed = rig.nodes is not None or args.nodes is not None
        expected = [f for f in frames if fixed or f.node in found.nodes_read]
        problems += [f"{path}: {p}" for p in found.problems(expected)]
    if problems:
        print(file=sys.stderr)
        for p in problems:
            print(f"motor-monitor: check: {p}", file=sys.stderr)
        return 1
    print("\nevery message carrying the model's inputs and outputs is read from the capture")
    return 0


def add_command(sub: argparse._SubParsersAction[Any]) -> None:
    c = sub.add_parser("check", help="what the monitor reads from a rig file, and what it "
                       "makes of every frame of a capture (before identify or run)")
    options.add_captures_and_rig(c, nargs="*", what="bus captures {formats} to hold the rig "
                                 "against")
    c.add_argument("--dbc", default=None, help="DBC file (default: the rig's)")
    c.add_argument("--nodes", type=options.nodes, default=None,
                   help="only these nodes' messages, e.g. 0,3 (default: every node of the rig)")
    c.set_defaults(func=run_check, key=None)
